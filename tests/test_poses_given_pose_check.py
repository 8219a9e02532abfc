"""Given poses against the frames: the epipolar check (recon.poses.given.pose_check)."""

import numpy as np
import pytest

from recon.poses.given.pose_check import check_given_poses, epipolar_distance, fundamental_matrix

from helpers import SHARED_DATA


def test_flow_along_the_epipolar_lines_is_at_distance_zero():
    """A flow field that moves every pixel along its epipolar line (any depth) is 0 px from
    it; one moved across the lines is as far as it was moved."""
    rng = np.random.default_rng(0)
    intrinsics = (100.0, 100.0, 31.5, 23.5)
    pose_a = np.eye(4)
    pose_b = np.eye(4)
    pose_b[:3, 3] = (0.2, 0.05, 0.0)  # a sideways step: the lines are nearly horizontal
    F = fundamental_matrix(pose_a, pose_b, intrinsics)
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:48, 0:64].astype(np.float64)
    depth = rng.uniform(1.0, 4.0, u.shape)
    points = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1)
    moved = points - pose_b[:3, 3]  # camera b's coordinates (no rotation)
    end = np.stack([fx * moved[..., 0] / moved[..., 2] + cx, fy * moved[..., 1] / moved[..., 2] + cy], -1)
    flow = end - np.stack([u, v], -1)
    assert np.abs(epipolar_distance(flow, F)).max() < 1e-9
    normal = np.array([-0.05, 0.2]) / np.hypot(0.05, 0.2)  # across the lines
    np.testing.assert_allclose(epipolar_distance(flow + 0.7 * normal, F), 0.7, atol=0.05)


@pytest.mark.skipif(not SHARED_DATA.exists(), reason="needs ../shared/data")
@pytest.mark.parametrize("name, flagged", [("tum-fr1-rpy", True), ("7scenes-redkitchen", False),
                                           ("record3d-door-handle", False)])
def test_recordings_whose_poses_contradict_their_frames(name, flagged):
    """TUM fr1/rpy's motion capture misses its neighbouring frames' epipolar lines by over a
    pixel (its published lens undone first, as the pipeline does); 7-Scenes' KinectFusion and
    Record3D's ARKit poses by under half a pixel."""
    from recon.core.stages import undistort_known_lens
    from recon.io.frames import open_source

    source = open_source(SHARED_DATA / name, max_frames=17, width=320)
    undistort_known_lens(source, source.intrinsics, "dataset calibration")
    rgb = source.read_all().rgb
    check = check_given_poses(rgb, source.poses, source.intrinsics)
    assert check.judged >= 12 and (check.disagreement is not None) == flagged, check
    assert (check.median_px > 1.0) if flagged else (check.median_px < 0.5), check


@pytest.mark.skipif(not SHARED_DATA.exists(), reason="needs ../shared/data")
def test_keyframes_far_apart_give_no_verdict():
    """ScanNet's keyframes, 0.7 s apart: the flow between them is mostly not confident, so it
    says nothing about the poses, and the check gives no verdict rather than a wrong one."""
    from recon.io.frames import open_source

    source = open_source(SHARED_DATA / "scannet-scene0005_00", max_frames=12)
    check = check_given_poses(source.read_all().rgb, source.poses, source.intrinsics)
    assert check.judged < 4 and check.median_px is None and check.disagreement is None, check
