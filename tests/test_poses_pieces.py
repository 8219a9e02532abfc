"""Tracking in pieces after a loss (recon.poses.pieces), on a scripted tracker: where each
piece starts and ends, what a piece that loses the camera again at once or fails otherwise
becomes, and when the loss is handed back (for the SfM fallback)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.poses.pieces import track_in_pieces
from recon.poses.result import PoseResult, TrackingLostError
from recon.poses.scale_watch import ScaleWatch


def _scripted(losses: dict[int, int], refusals: tuple[int, ...] = ()):
    """A tracker that loses the camera at the video frames `losses` maps a piece's first frame
    to (absolute; absent: it tracks to its end), and refuses (not lost) pieces starting at
    `refusals`. Records the calls (first, stop, intrinsics, lens)."""
    calls = []

    def track(first, stop, intrinsics, lens):
        calls.append((first, stop, intrinsics, lens))
        if first in refusals:
            raise TrackingLostError("the camera turns on the spot", frame=0)
        lost = losses.get(first)
        if lost is not None and lost < stop:
            raise TrackingLostError(f"tracking lost at frame {lost - first}", frame=lost - first, lost=True)
        n = stop - first
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, 0, 3] = np.arange(n)
        watch = ScaleWatch(list(range(0, n, 3)), [1.0] * len(range(0, n, 3)), 0.05)
        return PoseResult(poses, intrinsics or (500.0, 500.0, 320.0, 240.0), np.arange(0, n, 3), 1.0,
                          {"frame_status": ["tracked"] * n, "frame_inlier": [0.9] * n, "lens_k1": -0.02,
                           "scale_watch": watch.to_dict()}, np.ones((len(range(0, n, 3)), 4, 5), np.float32))

    return track, calls


def test_pieces_start_where_the_camera_was_lost_with_the_first_pieces_camera():
    track, calls = _scripted({0: 40, 40: 45, 45: 80})
    res = track_in_pieces(track, 120, TrackingLostError("lost", frame=40, lost=True), None, min_frames=22)
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [
        ([0, 39], True), ([40, 44], False), ([45, 79], True), ([80, 119], True)]
    # Later pieces track with the first piece's camera and lens.
    assert calls[0][2:] == (None, None) and all(c[2:] == ((500.0, 500.0, 320.0, 240.0), -0.02) for c in calls[2:])
    assert not np.isfinite(res.poses[40:45]).any() and np.isfinite(res.poses[45:]).all()
    assert res.diagnostics["frame_status"][40:45] == ["lost"] * 5
    lost = [(b["before"], b["after"]) for b in res.diagnostics["scale_watch"]["breaks"] if b["kind"] == "lost"]
    assert lost == [(39, 45), (79, 80)]
    verdicts = ScaleWatch.from_dict(res.diagnostics["scale_watch"]).frame_verdicts(120)
    assert verdicts[39] == "ok" and verdicts[45] == "after break 1" and verdicts[80] == "after break 2"
    assert res.keyframes.tolist()[:2] == [0, 3] and 45 in res.keyframes
    assert len(res.keyframe_depth) == len(res.keyframes)


def test_a_later_piece_that_fails_otherwise_leaves_the_rest_without_poses():
    track, _ = _scripted({0: 50}, refusals=(50,))
    res = track_in_pieces(track, 90, TrackingLostError("lost", frame=50, lost=True), None, min_frames=22)
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [([0, 49], True), ([50, 89], False)]
    assert np.isfinite(res.poses[:50]).all() and not np.isfinite(res.poses[50:]).any()


def test_the_loss_is_handed_back_when_no_piece_tracks_or_the_first_is_short():
    loss = TrackingLostError("lost at 10", frame=10, lost=True)
    with pytest.raises(TrackingLostError) as info:
        track_in_pieces(_scripted({})[0], 60, loss, None, min_frames=22)
    assert info.value is loss
    # The first piece, tracked again on its own, loses the camera at once, and so does every
    # piece after it: nothing tracked, the first attempt's loss comes back.
    everywhere = {f: f + 1 for f in range(60)}
    with pytest.raises(TrackingLostError) as info:
        track_in_pieces(_scripted(everywhere)[0], 60, TrackingLostError("lost", frame=30, lost=True), None, 22)
    assert info.value.frame == 30


def test_only_on_break_segments_tracks_in_pieces():
    """--on-break segments (the default) asks the front end to start again after a loss; stop
    and keep fall back to SfM as before; the user's --pose-option has the last word."""
    from types import SimpleNamespace

    from recon.drivers.segments import estimator_options

    def options(on_break, **mine):
        return estimator_options(SimpleNamespace(on_break=on_break, pose_options=mine))

    assert options("segments") == {"restart_after_loss": True}
    assert "restart_after_loss" not in options("stop") and "restart_after_loss" not in options("keep")
    assert options("segments", restart_after_loss=False)["restart_after_loss"] is False


def test_a_refused_first_piece_is_said_with_the_loss_and_sfm_tried(pose_room, monkeypatch):
    """The phone's images 35-70: the camera lost at frame 29, the 29 frames before it tracked
    again on their own and refused (their motion), then SfM: its error says all three."""
    import recon.poses.frontend as fe
    import recon.poses.sfm as sfm
    from recon.poses import estimate_poses

    seq, prior = pose_room

    def frontend(frames, *args, **kwargs):
        if len(frames) == len(seq.rgb):
            raise TrackingLostError("tracking lost at frame 29", frame=29, lost=True)
        raise TrackingLostError("the camera turns on the spot", frame=0, sfm_may_help=False)

    def sfm_fails(*args, **kwargs):
        raise TrackingLostError("SfM registered only 3 of 36 frames")

    monkeypatch.setattr(fe, "estimate_poses_frontend", frontend)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", sfm_fails)
    with pytest.raises(TrackingLostError, match=r"front end failed \(tracking lost at frame 29; the frames before it, "
                                                r"tracked on their own: the camera turns on the spot\), and so did the "
                                                r"SfM fallback \(SfM registered only 3"):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False, restart_after_loss=True)
