"""The stages module on its own (recon.core.stages), without a driver: the frame budget and the
window size counted at 640x480, the frame selection it raises the stride for, decoding, the
intrinsics known before the poses, the lens, the pose source, the tracking states and the
rolling-shutter summary. The drivers' end-to-end runs are in test_commands_cli.py and
test_drivers_streamed.py."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest

from recon.core.stages import (
    BUDGET_FRAME_PIXELS,
    PosePlan,
    PoseStage,
    budget_capacity,
    decode,
    given_intrinsics,
    medea_settings,
    plan_poses,
    select_frames,
    shutter_summary,
    tracking_states,
    undistort_known_lens,
    window_frames,
)
from recon.errors import ReconInputError
from recon.io.pose_formats.trajectories import write_poses

from helpers import SOURCE_H, SOURCE_W, random_poses, write_images


@pytest.fixture
def folder(tmp_path):
    """An image folder of 12 frames (64x48, helpers.source_frame)."""
    write_images(tmp_path / "frames", [f"{i:04d}.png" for i in range(12)])
    return tmp_path / "frames"


def test_budget_counts_frames_at_640x480():
    assert BUDGET_FRAME_PIXELS == 640 * 480
    assert budget_capacity(150, (480, 640)) == 150
    assert budget_capacity(150, (960, 1280)) == 37  # four times the pixels: a quarter of the frames
    assert budget_capacity(150, (48, 64)) == 150  # a smaller frame still counts as one
    assert budget_capacity(1, (4000, 3000)) == 2  # never fewer than a pair


def test_window_counts_like_the_budget_and_keeps_its_overlap():
    config = SimpleNamespace(window=48, window_overlap=8)
    assert window_frames(config, (480, 640)) == 48
    assert window_frames(config, (960, 1280)) == 12
    assert window_frames(config, (4000, 3000)) == config.window_overlap + 2


def test_selection_raises_the_stride_to_fit_the_budget(folder, caplog):
    with caplog.at_level(logging.WARNING):
        source = select_frames(folder, frame_budget=4)
    assert source.count == 4 and "using one frame in 3" in caplog.text
    assert select_frames(folder, frame_budget=None).count == 12  # streamed: every frame
    assert select_frames(folder, stride=2, frame_budget=4).count == 6  # a stride given stands
    assert select_frames(folder, max_frames=5, frame_budget=4).count == 5


def test_decode_gives_every_selected_frame_at_working_size_with_its_name(folder):
    source = select_frames(folder, stride=3, frame_budget=None)
    seq = decode(source, progress=False)
    assert list(seq.indices) == [0, 3, 6, 9]
    assert seq.rgb.shape == (4, SOURCE_H, SOURCE_W, 3) and seq.rgb.dtype == np.uint8
    assert seq.names == ["0000", "0003", "0006", "0009"]
    assert np.all(np.diff(seq.timestamps) > 0)


def test_given_intrinsics_are_scaled_to_working_size_and_checked(folder):
    source = select_frames(folder, width=32, frame_budget=None)  # decoded at 64x48, worked at 32x24
    values, where = given_intrinsics(source, (60.0, 62.0, 32.0, 24.0))
    assert where == "given" and values == pytest.approx((30.0, 31.0, 16.0, 12.0), abs=0.3)
    with pytest.raises(ReconInputError, match="principal point"):
        given_intrinsics(source, (60.0, 62.0, 320.0, 240.0))  # another resolution's calibration
    values, where = given_intrinsics(source, fov=90.0)
    assert where == "fov 90 deg" and values[0] == pytest.approx(16.0, rel=0.05)
    assert given_intrinsics(source) == (None, "unknown")


def test_a_lens_needs_its_camera(folder):
    source = select_frames(folder, frame_budget=None)
    assert undistort_known_lens(source, None, "unknown") is None  # pinhole: nothing to do
    with pytest.raises(ReconInputError, match="--distortion needs"):
        undistort_known_lens(source, None, "unknown", distortion=(0.1, 0.0, 0.0, 0.0))


def test_pose_source_is_settled_before_any_work(folder, tmp_path):
    source = select_frames(folder, frame_budget=None)
    assert plan_poses("auto", source) == PosePlan("estimate")  # a plain folder has no ground truth
    with pytest.raises(ReconInputError, match="ground-truth"):
        plan_poses("gt", source)
    poses = random_poses(12)
    write_poses(tmp_path / "poses.txt", poses, "tum", timestamps=np.arange(12) / 10.0)
    plan = plan_poses(str(tmp_path / "poses.txt"), source)
    assert plan.kind == "file" and not plan.estimated
    np.testing.assert_allclose(plan.data.poses, poses, atol=1e-6)
    polishing = SimpleNamespace(refine="mvs", polish=True)
    assert plan.polishes(polishing) and not plan.polishes(SimpleNamespace(refine="none", polish=True))
    assert not PosePlan("estimate").polishes(polishing)


def test_tracking_states_name_dropped_frames_and_scale_breaks():
    poses = random_poses(3)
    stage = PoseStage(poses, None, "estimated", info={
        "frame_status": ["keyframe", "tracked", "tracked"],
        "quality": {"dropped_frames": [{"frame": 20, "reason": "too little texture"}]},
        "scale_watch": {"frame_verdicts": ["ok", "ok", "after break 1"]}})
    seq = SimpleNamespace(indices=np.array([0, 10, 20]))
    states = tracking_states(stage, seq)
    assert [s[0] for s in states] == [0, 10, 20]
    assert states[0][1] == "keyframe" and states[1][1] == "tracked"
    assert states[2][1] == "dropped: too little texture; scale after break 1"
    np.testing.assert_array_equal(states[1][2], poses[1])
    assert tracking_states(PoseStage(poses, None, "given"), seq) is None  # given poses: nothing tracked
    # A metric scale the depth prior cannot vouch for, kept (--on-break keep): on every frame.
    kept = PoseStage(poses, None, "estimated", info={"frame_status": ["keyframe", "tracked", "tracked"],
                                                     "metric_scale": {"trusted": False}})
    assert [s[1] for s in tracking_states(kept, seq)] == [
        "keyframe; metric scale untrusted", "tracked; metric scale untrusted", "tracked; metric scale untrusted"]


def test_shutter_summary_counts_the_frames_it_moved():
    omega = np.array([[0.0, np.radians(30.0), 0.0]] * 4)
    summary = shutter_summary(omega, np.array([0.1, 2.0, 3.0, 0.2]), 20.0)
    assert summary["readout_ms"] == 20.0 and summary["max_shift_px"] == 3.0
    assert summary["median_turn_deg_per_s"] == pytest.approx(30.0)
    assert 0 < summary["frames_resampled"] < 4


def test_medea_searches_the_priors_scale_under_given_poses_only():
    """Given poses carry a scale of their own; estimated ones take the prior's."""
    from dataclasses import replace
    from pathlib import Path

    from recon.core.config import PipelineConfig

    config = PipelineConfig(Path("in.mp4"), Path("out"))
    assert medea_settings(config, estimated=False).scale_search
    assert not medea_settings(config, estimated=True).scale_search
    assert not medea_settings(replace(config, scale_prior=False), estimated=False).scale_search
    asked = replace(config, medea=replace(config.medea, scale_search=True))
    assert medea_settings(asked, estimated=True).scale_search  # the user's own setting stands
    assert not config.medea.scale_search  # the config itself is left as it was
