"""The dense pose front end (recon.poses.frontend) on the synthetic room (conftest: pose_room):
accuracy, metric scale, lens calibration, focal search, and tracking loss named by frame."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from recon.eval.trajectory import ate_rmse, path_length, rpe, scale_error
from recon.lens import distort_images
from recon.poses import TrackingLostError, estimate_poses
from recon.poses.frontend import FrontendConfig


def test_frontend_synthetic_accuracy_and_metric_scale(pose_room):
    seq, prior = pose_room
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    assert res.poses.shape == (36, 4, 4) and np.isfinite(res.poses).all()
    assert res.diagnostics["method"] == "frontend" and len(res.keyframes) >= 4
    length = path_length(seq.poses)
    ate = ate_rmse(res.poses, seq.poses, "sim3")["rmse"]
    assert ate <= 0.01 * length, f"Sim(3) ATE {ate:.4f} m > 1% of the {length:.2f} m path"
    assert scale_error(res.poses, seq.poses) <= 0.10
    # Rotations are right too (ATE looks at camera centres only).
    assert rpe(res.poses, seq.poses, delta=10)["rot_rmse_deg"] < 0.5  # the true 10-frame rotation is ~4 deg
    assert res.keyframe_depth is not None and res.keyframe_depth.shape[0] == len(res.keyframes)


def test_frontend_calibrates_a_barrel_lens(pose_room):
    """The room filmed through a barrel lens (k1 = -0.1, 4 % at the corners): the front end
    finds k1 and keeps the path and scale; as a pinhole camera the scale is 19 % off."""
    seq, prior = pose_room
    rgb = distort_images(seq.rgb, seq.intrinsics, -0.1)
    depth = distort_images(prior, seq.intrinsics, -0.1, nearest=True)
    length = path_length(seq.poses)
    res = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False)
    assert abs(res.diagnostics["lens_k1"] + 0.1) < 0.02, res.diagnostics["lens_k1"]
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.01 * length
    assert scale_error(res.poses, seq.poses) <= 0.10
    pinhole = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False,
                             config=replace(FrontendConfig(), calibrate_lens=False))
    assert scale_error(pinhole.poses, seq.poses) > 0.10


def test_frontend_estimates_focal_length_when_intrinsics_are_withheld(pose_room):
    seq, prior = pose_room
    res = estimate_poses(seq.rgb, prior, None, method="frontend", progress=False)
    f_true = seq.intrinsics[0]
    assert abs(res.intrinsics[0] / f_true - 1) <= 0.05, (res.intrinsics, f_true)
    assert res.diagnostics["focal_search"]["bracketed"]
    length = path_length(seq.poses)
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.02 * length


def test_tracking_loss_names_the_frame(pose_room):
    seq, prior = pose_room
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=(14, 240, 320, 3), dtype=np.uint8)
    frames = np.concatenate([seq.rgb[:12], noise])
    depth = np.concatenate([prior[:12], prior[:14]])
    with pytest.raises(TrackingLostError, match="tracking lost at frame 12") as info:
        estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False)
    assert info.value.frame == 12
