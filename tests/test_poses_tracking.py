"""Tracking that survives fast hand-held motion, and never returns a wrong trajectory
silently: the synthetic room walked at several times its speed with motion blur, two
unrelated recordings back to back, the ORB/PnP start, and the quality gate."""

from __future__ import annotations

import numpy as np
import pytest

from recon.eval.trajectory import ate_rmse, path_length, scale_error
from recon.poses import TrackingLostError, estimate_poses
from recon.poses import features as ft
from recon.poses.quality import GateConfig, gate_trajectory, runs
from recon.poses.result import PoseResult
from recon.synthetic import render_sequence, simulate_prior


@pytest.fixture(scope="module")
def fast_room():
    """A fast walk: 6x the default path speed (~12 cm and up to ~3 degrees per frame),
    each frame the average of 4 sub-frames over half the frame interval (motion blur)."""
    seq = render_sequence(30, 640, 480, seed=2, speed=6, blur=4)
    return seq, simulate_prior(seq.depth, seed=1)


def test_blur_is_rendered_and_ground_truth_is_the_frame_time():
    sharp = render_sequence(4, 160, 120, seed=2, speed=6)
    blurred = render_sequence(4, 160, 120, seed=2, speed=6, blur=4)
    assert np.array_equal(sharp.poses, blurred.poses) and np.array_equal(sharp.depth, blurred.depth)
    difference = np.abs(sharp.rgb.astype(float) - blurred.rgb).mean()
    assert difference > 1.0  # grey levels: a blurred image, not the sharp one
    # Sharp frames at 6x speed are every 6th frame of the default path.
    assert np.allclose(render_sequence(19, 160, 120, seed=2).poses[::6], sharp.poses)


def test_front_end_tracks_a_fast_blurred_walk(fast_room):
    seq, prior = fast_room
    steps = np.linalg.norm(np.diff(seq.poses[:, :3, 3], axis=0), axis=1)
    assert np.median(steps) > 0.08  # the motion the front end has to hold
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    status = res.diagnostics["frame_status"]
    assert status.count("interpolated") <= 1, status
    length = path_length(seq.poses)
    ate = ate_rmse(res.poses, seq.poses, "sim3")["rmse"]
    assert ate <= 0.01 * length, f"Sim(3) ATE {ate:.3f} m > 1% of the {length:.2f} m path"
    assert scale_error(res.poses, seq.poses) <= 0.10


def test_two_unrelated_recordings_are_never_joined_silently(fast_room):
    """Room A then a different room B: the front end stops at the cut and names it."""
    seq, prior = fast_room
    other = render_sequence(16, 640, 480, seed=9)
    frames = np.concatenate([seq.rgb[:20], other.rgb])
    depth = np.concatenate([prior[:20], simulate_prior(other.depth, seed=3)])
    with pytest.raises(TrackingLostError, match="tracking lost at frame 20") as info:
        estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False)
    assert info.value.frame == 20


def test_orb_pnp_recovers_a_large_relative_pose():
    """The feature start: a keyframe and a frame 5 path-steps of the fast walk apart (too far
    for unseeded flow at a quarter of the size) give their relative pose by ORB + PnP."""
    seq = render_sequence(3, 320, 240, seed=2, speed=10)
    cfg = ft.FeatureConfig()
    gray = [np.ascontiguousarray(g.mean(-1).astype(np.uint8)) for g in seq.rgb]
    rel, inliers = ft.relative_pose(ft.detect(gray[0], cfg), seq.depth[0], ft.detect(gray[2], cfg),
                                    seq.intrinsics, (320, 240), cfg)
    assert rel is not None and inliers >= cfg.min_inliers
    truth = np.linalg.inv(seq.poses[2]) @ seq.poses[0]  # camera 0 -> camera 2
    assert np.linalg.norm(rel[:3, 3] - truth[:3, 3]) < 0.05 * max(np.linalg.norm(truth[:3, 3]), 0.1)
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3].T @ truth[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 1.0  # a start for the flow alignment, not the final pose


def test_orb_pnp_refuses_unrelated_images():
    a = render_sequence(1, 320, 240, seed=2)
    noise = np.random.default_rng(0).integers(0, 256, (240, 320), dtype=np.uint8)
    cfg = ft.FeatureConfig()
    rel, _ = ft.relative_pose(ft.detect(np.ascontiguousarray(a.rgb[0].mean(-1).astype(np.uint8)), cfg), a.depth[0],
                              ft.detect(noise, cfg), a.intrinsics, (320, 240), cfg)
    assert rel is None


def _result(status, inlier=None, method="frontend"):
    n = len(status)
    diagnostics = {"method": method, "frame_status": status}
    if inlier is not None:
        diagnostics["frame_inlier"] = inlier
    return PoseResult(np.tile(np.eye(4), (n, 1, 1)), (100.0, 100.0, 50.0, 50.0), np.arange(n), 0.0, diagnostics)


def test_quality_gate_drops_frames_without_evidence_and_names_them():
    status = ["keyframe", "tracked", "interpolated", "interpolated", "relocalised", "recovered", "tracked", "tracked"]
    inlier = [np.nan, 0.9, np.nan, np.nan, 0.6, np.nan, 0.1, 0.8]
    gate = gate_trajectory(_result(status, inlier))
    assert gate.keep.tolist() == [True, True, False, False, True, True, False, True]
    summary = gate.summary([10 * i for i in range(8)])  # video frame numbers
    assert summary["dropped"] == 3 and summary["dropped_ranges"] == [[20, 30], [60, 60]]
    assert "interpolated" in summary["dropped_frames"][0]["reason"]
    assert "10%" in summary["dropped_frames"][2]["reason"]


def test_quality_gate_refuses_a_trajectory_with_too_little_evidence():
    status = ["keyframe", "tracked"] + ["interpolated"] * 6
    with pytest.raises(TrackingLostError, match=r"sfm: only 2 of 8 frames .* frames 2-7"):
        gate_trajectory(_result(status, method="sfm"))
    assert gate_trajectory(_result(status), GateConfig(min_kept=0.2, min_frames=2)).keep.sum() == 2
    assert runs([1, 2, 3, 7, 9, 10]) == [(1, 3), (7, 7), (9, 10)]
