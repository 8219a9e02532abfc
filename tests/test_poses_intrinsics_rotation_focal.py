"""The focal length of a camera that turns (recon.poses.intrinsics.rotation_focal): self-calibration from
the homographies between its frames, trusted only where the frames are rotations."""

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from recon.poses.intrinsics.rotation_focal import (
    RotationFocalConfig,
    estimate_focal_rotation,
    frame_pairs,
    pair_homography,
    rotation_cost,
)

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0


def _panorama(seed: int = 0) -> np.ndarray:
    """A textured image (1200, 1600, 3) of blobs and edges at several scales: the far wall a
    turning camera looks at."""
    rng = np.random.default_rng(seed)
    canvas = np.zeros((1200, 1600), np.float32)
    for size in (3, 9, 27):
        noise = rng.random((1200 // size + 1, 1600 // size + 1)).astype(np.float32)
        canvas += cv2.resize(noise, (1600, 1200), interpolation=cv2.INTER_CUBIC)[:1200, :1600]
    grey = cv2.normalize(canvas, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)


def _turning_frames(count: int, focal: float = FOCAL) -> list[np.ndarray]:
    """Frames of a pinhole camera (focal length `focal`, centre at the image's) that yaws,
    pitches and rolls on the spot in front of the panorama (a plane at infinity: each frame
    is the panorama through K R K_pano^-1)."""
    pano = _panorama()
    k_pano = np.array([[500.0, 0, 799.5], [0, 500.0, 599.5], [0, 0, 1]])
    k = np.array([[focal, 0, (WIDTH - 1) / 2], [0, focal, (HEIGHT - 1) / 2], [0, 0, 1]])
    t = np.linspace(0.0, 1.0, count)
    angles = np.stack([0.25 * np.sin(2 * np.pi * t), 0.35 * np.sin(np.pi * t), 0.15 * t], axis=1)
    frames = []
    for rotvec in angles:
        R = Rotation.from_rotvec(rotvec).as_matrix()
        H = k @ R @ np.linalg.inv(k_pano)  # panorama pixel -> frame pixel
        frames.append(cv2.warpPerspective(pano, H, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR))
    return frames


def test_the_cost_is_zero_at_the_focal_length_of_a_rotation():
    """K R K^-1 is a rotation only under the K it was made with; a roll about the optical
    axis is one under every K (it says nothing of f)."""
    k = np.diag([FOCAL, FOCAL, 1.0])
    turn = k @ Rotation.from_rotvec([0.1, 0.2, 0.05]).as_matrix() @ np.linalg.inv(k)
    focals = np.array([150.0, 300.0, 600.0])
    cost = rotation_cost(turn, focals)
    assert cost[1] < 1e-12 and cost[0] > 1e-3 and cost[2] > 1e-3
    roll = k @ Rotation.from_rotvec([0.0, 0.0, 0.3]).as_matrix() @ np.linalg.inv(k)
    assert np.allclose(rotation_cost(roll, focals), 0.0, atol=1e-12)


def test_pairs_span_every_gap():
    pairs = frame_pairs(10, (2, 4))
    assert (0, 2) in pairs and (8, 10) not in pairs and (6, 10) not in pairs and (4, 8) in pairs
    assert all(b - a in (2, 4) for a, b in pairs)


def test_a_turning_camera_gives_its_focal_length():
    """A camera turned on the spot (no parallax whatever the scene): the estimate is within
    2 % of its focal length, trusted, with a narrow range that holds it."""
    estimate = estimate_focal_rotation(_turning_frames(24))
    assert estimate.trusted, estimate
    assert abs(estimate.focal / FOCAL - 1) < 0.005, estimate
    assert estimate.low <= 1.01 * FOCAL and FOCAL <= 1.01 * estimate.high and estimate.high < 1.35 * estimate.low
    assert estimate.share > 0.9 and estimate.rotations >= 10


def test_a_homography_explains_a_rotation_as_well_as_a_fundamental_matrix_does():
    frames = _turning_frames(8)
    cfg = RotationFocalConfig()
    from recon.poses.intrinsics.rotation_focal import matched_points, sift_features

    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    pa, pb = matched_points(sift_features(grey[0], cfg), sift_features(grey[4], cfg), cfg)
    H, explained = pair_homography(pa, pb, np.array([(WIDTH - 1) / 2, (HEIGHT - 1) / 2], np.float32), 3.0)
    assert H is not None and explained > 0.9


def test_a_camera_that_walks_through_a_room_is_not_taken_for_a_turning_one(pose_room):
    """The synthetic room's hand-held walk: its parallax leaves f loose, so the estimate is
    not trusted (the focal search and the vanishing points decide there)."""
    seq, _ = pose_room
    estimate = estimate_focal_rotation(list(seq.rgb))
    assert not estimate.trusted, estimate
