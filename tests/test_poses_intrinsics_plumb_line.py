"""The lens from straight edges (recon.poses.intrinsics.plumb_line)."""

import cv2
import numpy as np
import pytest
import torch

from recon.geometry import projective as pj
from recon.geometry.lens import distort_images
from recon.poses.intrinsics.plumb_line import LensEstimate, PlumbLineConfig, estimate_lens, line_support
from recon.synthetic import render_sequence

FOCAL = 500.0
WIDTH, HEIGHT = 640, 480
INTRINSICS = (FOCAL, FOCAL, (WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)


def _man_made_frames(count: int, seed: int = 0) -> np.ndarray:
    """Pinhole frames (count, H, W, 3) of overlapping boxes and panels at random angles:
    long straight step edges all over the frame, with some sensor noise."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(count):
        img = np.full((HEIGHT * 4, WIDTH * 4), 110.0, np.float32)
        for _ in range(14):
            centre = rng.uniform([0, 0], [WIDTH * 4, HEIGHT * 4])
            size = rng.uniform(600, 1800, 2)
            box = cv2.boxPoints(((float(centre[0]), float(centre[1])), (float(size[0]), float(size[1])),
                                 float(rng.uniform(-30, 30))))
            cv2.fillPoly(img, [np.round(box).astype(np.int32)], float(rng.uniform(20, 235)))
        img = cv2.resize(cv2.GaussianBlur(img, (0, 0), 2.0), (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
        img = np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)
        frames.append(np.repeat(img[..., None], 3, axis=2))
    return np.stack(frames)


@pytest.mark.parametrize("k1", [-0.08, -0.03, 0.0, 0.04])
def test_straight_edges_give_the_lens(k1):
    """Frames of straight edges recorded through a lens k1: the estimate's k1 at the true
    focal length is within 0.004 of it (0.001 of k1 moves the corner of a 640x480 frame by 0.25 px)."""
    recorded = distort_images(_man_made_frames(12), INTRINSICS, k1)
    estimate = estimate_lens(list(recorded))
    assert estimate.trusted, estimate
    assert estimate.regions >= PlumbLineConfig().min_regions
    assert abs(estimate.k1(FOCAL) - k1) < 0.004, (estimate.k1(FOCAL), k1)


def test_wide_frames_are_measured_downscaled():
    """Frames twice as wide as ``max_width`` are measured at that width: the same lens at
    twice the focal length (pixels of the frames given)."""
    k1 = -0.05
    recorded = distort_images(_man_made_frames(12), INTRINSICS, k1)
    wide = np.stack([cv2.resize(f, (2 * WIDTH, 2 * HEIGHT), interpolation=cv2.INTER_LINEAR) for f in recorded])
    estimate = estimate_lens(list(wide))
    assert estimate.trusted
    assert estimate.half_diagonal == pytest.approx(0.5 * np.hypot(2 * WIDTH - 1, 2 * HEIGHT - 1))
    assert abs(estimate.k1(2 * FOCAL) - k1) < 0.004, estimate.k1(2 * FOCAL)


def test_corner_shift_needs_no_focal_length():
    """Straight lines fix the lens in pixels (kappa = k1 / f^2): the same corner shift
    converted for two focal lengths undistorts every pixel to the same place."""
    estimate = LensEstimate(corner_shift=-0.02, half_diagonal=0.5 * np.hypot(WIDTH - 1, HEIGHT - 1), regions=50,
                            trusted=True)
    grid = pj.pixel_grid(HEIGHT, WIDTH)
    centre = ((WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)
    placed = [pj.undistort(grid, torch.tensor([f, f, *centre], dtype=torch.float64), estimate.k1(f))[0]
              for f in (400.0, 800.0)]
    assert torch.allclose(placed[0], placed[1], atol=1e-6)
    corner = placed[0][0, 0] - torch.tensor(centre, dtype=torch.float64)
    assert float(corner.norm()) == pytest.approx(estimate.half_diagonal / (1 - 0.02), rel=2e-3)


def test_texture_without_straight_edges_gives_no_estimate():
    """The rendered room's walls are textured and its edges broken by that texture: too
    few straight regions, so no lens is claimed (the focal search stays a pinhole search)."""
    seq = render_sequence(num_frames=6)
    estimate = estimate_lens(list(np.asarray(seq.rgb)))
    assert not estimate.trusted
    assert estimate.corner_shift == 0.0


def test_line_support_keeps_long_edges_only():
    """One bright bar: its two long sides are regions, its short ends are not."""
    img = np.full((HEIGHT, WIDTH), 60, np.uint8)
    cv2.rectangle(img, (100, 200), (500, 240), 200, thickness=-1)
    points, ids = line_support(img, PlumbLineConfig())
    assert len(np.unique(ids)) == 2 * 2  # each side once per orientation binning
    for region in np.unique(ids):
        y = points[ids == region, 1]
        assert np.ptp(y) < 1.5 and (abs(np.mean(y) - 199.5) < 1.0 or abs(np.mean(y) - 240.5) < 1.0)
