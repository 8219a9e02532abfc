"""The focal length from vanishing points (recon.poses.intrinsics.vanishing)."""

import cv2
import numpy as np
import pytest

from recon.geometry.lens import distort_images
from recon.poses.intrinsics.plumb_line import estimate_lens
from recon.poses.intrinsics.vanishing import (
    VanishingConfig,
    agreeing_group,
    curve_peak,
    estimate_focal_vp,
)
from recon.synthetic.camera import camera_rotation

WIDTH, HEIGHT = 640, 480


def _room_edges() -> list[tuple[np.ndarray, np.ndarray]]:
    """World segments of a 6 x 3 x 6 m room (y down, camera at the origin): panels on every
    wall, the floor and the ceiling, their edges along the three axes."""
    half = np.array([3.0, 1.5, 3.0])
    edges = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            u, v = [a for a in range(3) if a != axis]
            for a in np.arange(-half[u] + 0.5, half[u], 1.0):
                for b in np.arange(-half[v] + 0.4, half[v] - 0.2, 0.8):
                    corner = np.zeros(3)
                    corner[axis], corner[u], corner[v] = side * half[axis], a, b
                    du, dv = np.zeros(3), np.zeros(3)
                    du[u], dv[v] = 0.6, 0.5
                    edges += [(corner, corner + du), (corner, corner + dv),
                              (corner + du, corner + du + dv), (corner + dv, corner + du + dv)]
    return edges


def _room_frames(focal: float, count: int, seed: int = 0, face_on: bool = False) -> np.ndarray:
    """Pinhole frames (count, H, W, 3) of the room's panel edges from random viewing
    directions (face_on: looking straight at a wall, level, so only one vanishing point is
    finite)."""
    rng = np.random.default_rng(seed)
    edges = _room_edges()
    centre = np.array([(WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0])
    t = np.linspace(0.0, 1.0, 40)[:, None]
    frames = []
    for _ in range(count):
        if face_on:
            rot = camera_rotation(np.radians(90.0 * rng.integers(0, 4)), 0.0, 0.0)
        else:
            yaw, pitch_up, roll = rng.uniform(-180, 180), rng.uniform(-25, 25), rng.uniform(-8, 8)
            rot = camera_rotation(*np.radians([yaw, -pitch_up, roll]))
        position = rng.uniform([-1.0, -0.5, -1.0], [1.0, 0.5, 1.0])
        img = np.full((HEIGHT * 2, WIDTH * 2), 150, np.uint8)
        for a, b in edges:
            cam = (a + t * (b - a) - position) @ rot  # world -> camera: R^T (X - c)
            cam = cam[cam[:, 2] > 0.05]
            if len(cam) < 2:
                continue
            px = (focal * cam[:, :2] / cam[:, 2:] + centre) * 2.0
            if np.abs(px).max() > 1e5:
                continue
            cv2.polylines(img, [np.round(px * 16).astype(np.int32)], False, 40, thickness=5,
                          lineType=cv2.LINE_AA, shift=4)
        img = cv2.resize(img, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
        frames.append(np.repeat(img[..., None], 3, axis=2))
    return np.stack(frames)


@pytest.mark.parametrize("focal", [420.0, 600.0])
def test_vanishing_points_give_the_focal_length(focal):
    """A room's panel edges seen from random directions: the focal length within 2 %."""
    estimate = estimate_focal_vp(list(_room_frames(focal, 12)), cfg=VanishingConfig(min_frames=4))
    assert estimate.trusted, estimate
    assert abs(estimate.focal / focal - 1.0) < 0.02, estimate.focal


def test_wide_frames_are_measured_downscaled():
    """Frames twice as wide as ``max_width`` are measured at that width and the focal length
    given in pixels of the frames given."""
    wide = [cv2.resize(f, (2 * WIDTH, 2 * HEIGHT), interpolation=cv2.INTER_LINEAR) for f in _room_frames(500.0, 12)]
    estimate = estimate_focal_vp(wide, cfg=VanishingConfig(min_frames=4))
    assert estimate.trusted, estimate
    assert abs(estimate.focal / 1000.0 - 1.0) < 0.02, estimate.focal


def test_the_edge_regions_found_once_serve_the_lens_and_the_vanishing_points_alike():
    """The regions the front end finds once (plumb_line.sample_regions) give the lens and the
    focal length each estimator finds on its own, to the bit; made for other frame settings,
    they are not used."""
    from dataclasses import replace

    from recon.poses.intrinsics.plumb_line import PlumbLineConfig, sample_regions

    focal, k1 = 500.0, -0.08
    intr = (focal, focal, (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)
    recorded = list(distort_images(_room_frames(focal, 12, seed=1), intr, k1))
    cfg, vp_cfg = PlumbLineConfig(), VanishingConfig(min_frames=4)
    regions = sample_regions(recorded, cfg, cfg.max_frames, cfg.max_width)
    lens, shared_lens = estimate_lens(recorded), estimate_lens(recorded, cfg, regions)
    assert shared_lens == lens and lens.trusted
    alone, shared = estimate_focal_vp(recorded, lens, vp_cfg), estimate_focal_vp(recorded, lens, vp_cfg, regions)
    assert shared == alone and shared.trusted
    fewer = replace(vp_cfg, max_frames=6)
    assert estimate_focal_vp(recorded, lens, fewer, regions) == estimate_focal_vp(recorded, lens, fewer)
    assert estimate_focal_vp(recorded, lens, fewer).frames == 6


def test_through_the_lens_from_straight_edges():
    """Recorded through a barrel lens, the segments bend; undistorted with the lens the
    straight edges give, the focal length is found again within 2 %."""
    focal, k1 = 500.0, -0.08
    intr = (focal, focal, (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)
    recorded = list(distort_images(_room_frames(focal, 12, seed=1), intr, k1))
    lens = estimate_lens(recorded)
    assert lens.trusted
    estimate = estimate_focal_vp(recorded, lens, VanishingConfig(min_frames=4))
    assert estimate.trusted, estimate
    assert abs(estimate.focal / focal - 1.0) < 0.02, estimate.focal


def test_face_on_walls_are_not_trusted():
    """Level views straight at a wall have one finite vanishing point, which says nothing of
    the focal length: the frames' peaks scatter and no estimate is claimed."""
    estimate = estimate_focal_vp(list(_room_frames(500.0, 12, seed=2, face_on=True)), cfg=VanishingConfig(min_frames=4))
    assert not estimate.trusted, estimate


def test_curve_peak_and_agreeing_group():
    focals = np.exp(np.linspace(np.log(300), np.log(900), 61))
    values = 1.0 - (np.log(focals) - np.log(512.0)) ** 2
    assert curve_peak(values, focals, 0.02) == pytest.approx(512.0, rel=1e-3)
    assert curve_peak(np.ones_like(focals), focals, 0.02) is None
    group = agreeing_group(np.array([500.0, 510.0, 495.0, 800.0, 300.0, 505.0]), 0.05)
    assert group.tolist() == [True, True, True, False, False, True]
