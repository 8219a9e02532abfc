"""The streamed run's tracking pass (recon.drivers.stream_track): SfM's second opinion, asked on
the depth frames where the front end doubts its trajectory (with --pose-method auto, not under
--on-break keep); with given poses, depth frames chosen at the poses' scale, not the prior's;
frames the front end posed only later chosen by the same rule at close."""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import numpy as np
import pytest

from recon.commands.demo import write_demo_inputs
from recon.core.clock import StageClock
from recon.core.config import PipelineConfig
from recon.core.stages import plan_poses, select_frames
from recon.drivers import stream_track
from recon.io.frame_store import FrameStore
from recon.io.output_folder import OutputFolder
from recon.poses.result import PoseResult
from recon.synthetic import render_sequence, simulate_prior

# The module (recon.poses exports a function of the same name).
so = importlib.import_module("recon.poses.second_opinion")


def _poser(pose_method: str, stop_untrusted: bool):
    poser = stream_track._Poser.__new__(stream_track._Poser)
    poser.config = SimpleNamespace(pose_method=pose_method)
    poser.frontend_config = SimpleNamespace(stop_untrusted=stop_untrusted)
    poser.intrinsics = None
    # Tracked under --start: position p is the video's frame 100 + p.
    poser.frame_number = {p: 100 + p for p in range(12)}
    # The store keeps the colour of the depth frames 0, 3, 6, 9 only.
    poser.store = SimpleNamespace(has=lambda p, kind: kind == "rgb" and p % 3 == 0, get=lambda p, kind: None)
    return poser


def _result(doubt: bool) -> PoseResult:
    diagnostics = {"motion_checks": {"short_flow": [[4, 9]] if doubt else []}}
    return PoseResult(np.tile(np.eye(4), (12, 1, 1)), (100.0, 100.0, 50.0, 40.0), np.arange(0, 12, 3), 0.0,
                      diagnostics)


@pytest.mark.parametrize("pose_method, stop_untrusted, doubt, asked", [
    ("auto", True, True, True), ("auto", True, False, False), ("frontend", True, True, False),
    ("auto", False, True, False)])
def test_sfm_is_asked_where_the_front_end_doubts(monkeypatch, pose_method, stop_untrusted, doubt, asked):
    calls = []

    def opinion(poses, views, frame, intrinsics, said, stretch):
        calls.append((list(views), said))
        return so.SecondOpinion(said, 4, 0.05, "disagree", "front end", "SfM posed some frames only")

    monkeypatch.setattr(so, "on_views", opinion)
    result = _result(doubt)
    _poser(pose_method, stop_untrusted)._second_opinion(result)
    assert bool(calls) == asked
    assert ("second_opinion" in result.diagnostics) == asked
    if asked:
        assert calls[0][0] == [0, 3, 6, 9] and "frames 104-109" in calls[0][1]
        assert result.diagnostics["second_opinion"]["verdict"] == "disagree"


@pytest.fixture(scope="module")
def room_walk(tmp_path_factory):
    """40 frames of the synthetic room at 192x144 as a video with its trajectory, and two prior
    folders: a simulated prior, and the same five times too far (the scale of an indoor network
    on a close-up)."""
    seq = render_sequence(40, 192, 144, seed=0)
    prior = simulate_prior(seq.depth, seed=1)
    inputs = write_demo_inputs(OutputFolder(tmp_path_factory.mktemp("near")), seq, prior)
    far = write_demo_inputs(OutputFolder(tmp_path_factory.mktemp("far")), seq, 5.0 * prior)
    return seq, inputs, far["prior"]


def _tracked(seq, inputs, prior_path, scale_prior: bool, max_frames: int | None = None, depth_frames_min: int = 0):
    config = PipelineConfig(input=inputs["video"], output=inputs["video"].parent / "unused", width=None,
                            max_frames=max_frames,
                            intrinsics=seq.intrinsics, poses=str(inputs["poses"]), prior="folder",
                            prior_path=prior_path, stream="on", depth_frames="motion", scale_prior=scale_prior,
                            depth_rotation=45.0, depth_frames_min=depth_frames_min,
                            progress=False)  # the path's turns take no frame here
    source = select_frames(config.input, max_frames=max_frames, frame_budget=None)
    with FrameStore() as store:
        return stream_track.track_video(config, source, plan_poses(config.poses, source), (seq.intrinsics, "given"),
                                        store, None, StageClock())


def test_given_poses_choose_depth_frames_at_their_own_scale(room_walk):
    seq, inputs, far = room_walk
    near = _tracked(seq, inputs, inputs["prior"], scale_prior=True)
    unscaled = _tracked(seq, inputs, far, scale_prior=False)
    scaled = _tracked(seq, inputs, far, scale_prior=True)
    # The motion rule measures the path in the median depth: a prior five times too far
    # makes it take a fraction of the frames...
    assert unscaled.depth_frame.sum() < 0.5 * near.depth_frame.sum()
    # ... unless the prior's factor against the poses is searched first.
    assert scaled.prior_scale["applied"] and 0.17 < scaled.prior_scale["factor"] < 0.23
    assert not near.prior_scale["applied"]
    assert abs(int(scaled.depth_frame.sum()) - int(near.depth_frame.sum())) <= 2
    assert unscaled.prior_scale is None
    # With a floor of 20 depth frames over the 40, the far prior's run takes one every 2nd
    # frame at least, those motion did not take counted apart.
    floored = _tracked(seq, inputs, far, scale_prior=False, depth_frames_min=20)
    gaps = np.diff(np.flatnonzero(floored.depth_frame))
    assert floored.depth_frame.sum() >= 20 and gaps.max() <= 2
    assert floored.depth_frame.sum() - floored.depth_by_gap <= unscaled.depth_frame.sum() < floored.depth_by_gap
    # Every frame is tracked once, in order, with the given pose.
    for video in (near, scaled):
        assert list(video.indices) == list(range(40))
        np.testing.assert_allclose(video.poses, seq.poses, atol=1e-5)


def test_a_video_shorter_than_the_scale_probe_is_tracked_whole(room_walk):
    seq, inputs, far = room_walk
    count = stream_track.SCALE_PROBE_FRAMES // 2
    video = _tracked(seq, inputs, far, scale_prior=True, max_frames=count)
    assert list(video.indices) == list(range(count)) and video.prior_scale["frames"] == count
    assert video.prior_scale["applied"] and 0.17 < video.prior_scale["factor"] < 0.23
    assert video.depth_frame[0] and 2 <= video.depth_frame.sum() < count


def test_frames_tracked_before_they_had_a_pose_are_chosen_at_close():
    # 100 frames walking 1.1 cm a frame, 2 m away; the first 60 waited for the focal search
    # (taken while tracked, no pose yet), the rest were chosen on their live poses.
    poses = np.repeat(np.eye(4)[None], 100, axis=0)
    poses[:, 0, 3] = np.cumsum(np.full(100, 0.011))
    # Their prior is made for the frames chosen, and kept in the store.
    from recon.priors.base import PriorOutput

    loop = stream_track._TrackLoop.__new__(stream_track._TrackLoop)
    loop.select = stream_track.MotionSelector(0.02, 2.0, max_gap=stream_track.depth_gap(100, 10))
    loop.unposed = list(range(60))
    loop.chosen = [True] * 60 + [loop.select(pose, 2.0) for pose in poses[60:]]
    made, kept = [], []
    flat = PriorOutput(np.full((1, 8, 8), 2.0, np.float32), "metric")
    loop._frame_prior = lambda position: made.append(int(position)) or flat
    loop._keep_prior = lambda position, depth, features: kept.append(int(position))
    chosen, by_gap = loop._choose_unposed(poses)
    assert np.array_equal(np.flatnonzero(chosen[:60]), np.arange(0, 60, 4))  # by motion, as if posed
    assert np.array_equal(chosen[60:], loop.chosen[60:]) and by_gap == 0
    assert sorted(set(made)) == kept == list(range(0, 60, 4))
    # Without a frame waiting, the choice is the one made while tracking.
    loop.unposed = []
    assert np.array_equal(loop._choose_unposed(poses)[0], loop.chosen)
