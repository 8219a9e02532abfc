"""Tracking in pieces after a loss (recon.poses.frontend.pieces.StreamingPieces), on scripted front
ends: where each piece starts and ends, that the frames before a loss are not tracked again,
what a piece that loses the camera again at once or fails otherwise becomes, and when the loss
is handed back (for the SfM fallback)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from recon.poses.checks.scale_watch import ScaleWatch
from recon.poses.frontend.pieces import StreamingPieces
from recon.poses.result import PoseResult, TrackingLostError

LOSS = 11  # frames in a row a front end fails on before it says it lost the camera (max_lost + 1)
CAMERA = (500.0, 500.0, 320.0, 240.0)


class _Scripted:
    """A front end for the piece that starts at video frame `first` (its frames numbered from
    0, as StreamingPieces feeds them): it cannot align frames from the video frame `lose_at`
    on, says so LOSS frames later (as the real one does after max_lost), and refuses its
    trajectory at finish when `refuse`."""

    def __init__(self, first, intrinsics, lens, lose_at, refuse, failing_from=None):
        self.first, self.lose_at, self.refuse, self.failing_from = first, lose_at, refuse, failing_from
        self.intrinsics, self.lens_k1, self.focal_choice = intrinsics or CAMERA, -0.02, None
        self.fed: list[int] = []
        self.failing = "not finished"

    def _lost(self, i):
        return self.lose_at is not None and self.first + i >= self.lose_at

    def add(self, i, frame):
        assert i == len(self.fed)  # in order, numbered from the piece's start
        assert not isinstance(frame, int) or frame == self.first + i  # the video's frame of that number
        self.fed.append(i)
        if self._lost(i) and self.first + i == self.lose_at + LOSS - 1:
            raise TrackingLostError(f"tracking lost at frame {self.lose_at - self.first}",
                                    frame=self.lose_at - self.first, lost=True)
        return self.current(i)

    def current(self, i):
        return ("lost", None) if self._lost(i) else ("tracked", np.eye(4))

    def finish_image(self, frame):
        return frame

    def flush(self):
        pass

    def lost_tail(self):
        run = [i for i in self.fed if self._lost(i)]
        return run[0] if len(run) > LOSS // 2 else None

    def finish(self, lookup, progress=False, stop=None, failing=None):
        n = len(self.fed) if stop is None else stop
        self.failing = failing
        if failing is not None and self.failing_from is not None:
            # Tracking was failing from video frame failing_from: those frames are forgotten,
            # at most lookback of them (StreamingFrontend.finish's failing).
            n = max(self.failing_from - self.first, n - failing[1])
        frames = [lookup(i) for i in range(n)]
        assert not isinstance(frames[0], int) or frames == list(range(self.first, self.first + n))  # by video frame
        if self.refuse:
            raise TrackingLostError("the camera turns on the spot", frame=0, sfm_may_help=False)
        if any(self._lost(i) for i in range(n)):
            raise TrackingLostError("lost at the end", frame=self.lose_at - self.first, lost=True)
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, 0, 3] = np.arange(n)
        kf = np.arange(0, n, 3)
        watch = ScaleWatch(kf.tolist(), [1.0] * len(kf), 0.05)
        return PoseResult(poses, self.intrinsics, kf, 1.0,
                          {"frame_status": ["tracked"] * n, "frame_inlier": [0.9] * n, "lens_k1": self.lens_k1,
                           "scale_watch": watch.to_dict()}, np.ones((len(kf), 4, 5), np.float32))


def _run(count, losses, refusals=(), min_frames=22, intrinsics=None, failing_from=None, failing=None, pieces=None,
         number=None):
    """StreamingPieces over frames 0..count-1 (each frame is its own number) with scripted
    pieces: losses maps a piece's first frame to the video frame it loses the camera at,
    failing_from to the video frame its tracking fails from (when finish is asked to forget
    such frames: StreamingPieces' failing). Returns (the result, the pieces made as (first,
    intrinsics, lens, frames fed)); `pieces`, a list, receives the scripted front ends;
    number: how the pieces name frames (default: positions)."""
    made = []

    def make(first, intr, lens):
        piece = _Scripted(first, intr, lens, losses.get(first), first in refusals, (failing_from or {}).get(first))
        made.append((first, intr, lens, piece))
        return piece

    stream = StreamingPieces(make, intrinsics, min_frames=min_frames, keep=LOSS + 1, failing=failing,
                             **({} if number is None else {"number": number}))
    for i in range(count):
        stream.add(i, i)
    result = stream.finish(lambda i: i)
    if pieces is not None:
        pieces.extend(piece for *_, piece in made)
    return result, [(first, intr, lens, piece.fed) for first, intr, lens, piece in made]


def test_pieces_start_where_the_camera_was_lost_with_the_first_pieces_camera():
    res, made = _run(120, {0: 40, 40: 45, 45: 80})
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [
        ([0, 39], True), ([40, 44], False), ([45, 79], True), ([80, 119], True)]
    # Later pieces track with the first piece's camera and lens; each starts where the last
    # lost the camera, and no frame before a loss is tracked again.
    assert [m[:3] for m in made] == [(0, None, None), (40, CAMERA, -0.02), (45, CAMERA, -0.02), (80, CAMERA, -0.02)]
    assert made[0][3] == list(range(40 + LOSS))
    assert not np.isfinite(res.poses[40:45]).any() and np.isfinite(res.poses[45:]).all()
    assert res.diagnostics["frame_status"][40:45] == ["lost"] * 5
    lost = [(b["before"], b["after"]) for b in res.diagnostics["scale_watch"]["breaks"] if b["kind"] == "lost"]
    assert lost == [(39, 45), (79, 80)]
    verdicts = ScaleWatch.from_dict(res.diagnostics["scale_watch"]).frame_verdicts(120)
    assert verdicts[39] == "ok" and verdicts[45] == "after break 1" and verdicts[80] == "after break 2"
    assert res.keyframes.tolist()[:2] == [0, 3] and 45 in res.keyframes
    assert len(res.keyframe_depth) == len(res.keyframes)


def test_one_piece_is_the_front_ends_own_result():
    res, made = _run(60, {})
    assert len(made) == 1 and "pieces" not in res.diagnostics and np.isfinite(res.poses).all()


def test_a_later_piece_that_fails_otherwise_leaves_the_rest_without_poses():
    res, _ = _run(90, {0: 50}, refusals=(50,))
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [([0, 49], True), ([50, 89], False)]
    assert np.isfinite(res.poses[:50]).all() and not np.isfinite(res.poses[50:]).any()


def test_a_loss_at_the_end_leaves_the_last_frames_without_poses():
    res, _ = _run(58, {0: 50})  # 8 lost frames at the end: not said while tracking, refused by finish
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [([0, 49], True), ([50, 57], False)]


def test_the_loss_is_handed_back_when_the_first_piece_is_short():
    with pytest.raises(TrackingLostError) as info:
        _run(60, {0: 10})
    assert info.value.frame == 10 and info.value.lost
    # Every piece after the first loses the camera at once: the first piece's frames keep
    # their poses (they are not tracked again), the rest get none.
    res, _ = _run(60, {f: f + 1 for f in range(30, 60)} | {0: 30})
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]][0] == ([0, 29], True)
    assert np.isfinite(res.poses[:30]).all() and not np.isfinite(res.poses[30:]).any()


class _Buffering(_Scripted):
    """The first piece with its focal length unknown: it keeps every frame until the focal
    search has enough, which a short video never gives it, and tracks them at flush."""

    def add(self, i, frame):
        self.fed.append(i)
        return "buffered", None

    def current(self, i):
        return "buffered", None

    def flush(self):
        self.current = super().current
        if self.lose_at is not None and self.lose_at + LOSS - 1 <= self.first + len(self.fed) - 1:
            raise TrackingLostError("tracking lost", frame=self.lose_at - self.first, lost=True)


def test_a_loss_among_the_frames_the_focal_search_waits_for_starts_a_new_piece():
    """A video shorter than the focal search's buffer is tracked at the end; a loss in it
    starts a new piece there, on the frames kept, with the camera the search found."""
    made = []

    def make(first, intr, lens):
        piece = (_Buffering if first == 0 else _Scripted)(first, intr, lens, {0: 30}.get(first), False)
        made.append((first, intr))
        return piece

    stream = StreamingPieces(make, None, min_frames=22, keep=LOSS + 1)
    assert all(stream.add(i, i) == ("buffered", None) for i in range(60))
    res = stream.finish(lambda i: i)
    assert made == [(0, None), (30, CAMERA)]
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [([0, 29], True), ([30, 59], True)]


def test_a_loss_while_the_kept_frames_are_tracked_again_starts_the_next_piece_once():
    """The focal search's buffer (60 frames) holds two losses: the piece started at the first
    loses the camera again while it is given the kept frames, and the piece started then
    takes the rest of them; none is given a frame twice or out of order."""
    made = []

    def make(first, intr, lens):
        piece = (_Buffering if first == 0 else _Scripted)(first, intr, lens, {0: 25, 25: 50}.get(first), False)
        made.append(piece)
        return piece

    stream = StreamingPieces(make, None, min_frames=22, keep=LOSS + 1)
    for i in range(90):
        stream.add(i, i)
    res = stream.finish(lambda i: i)
    assert [p.first for p in made] == [0, 25, 50]
    assert made[1].fed == list(range(25 + LOSS)) and made[2].fed == list(range(40))
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [
        ([0, 24], True), ([25, 49], True), ([50, 89], True)]


def test_a_refused_first_piece_is_said_with_the_loss():
    with pytest.raises(TrackingLostError, match=r"^tracking lost at frame 29; the frames before it: the camera "
                                                r"turns on the spot") as info:
        _run(60, {0: 29}, refusals=(0,))
    assert info.value.frame == 29 and info.value.sfm_may_help


def test_what_the_pieces_say_names_the_frames_as_the_video_numbers_them(caplog):
    """Every 2nd frame of a video from its frame 100: the loss at the end (position 30) is
    said as video frame 160, and the frames without a pose (positions 50-57) as 200-214;
    the error's frame stays a position."""
    every_2nd = lambda i: 100 + 2 * i  # noqa: E731
    with pytest.raises(TrackingLostError, match=r"^tracking lost at frame 160 and not recovered before the end of "
                                                r"the video; the frames before it: the camera turns") as info:
        _run(40, {0: 30}, refusals=(0,), number=every_2nd)
    assert info.value.frame == 30
    with caplog.at_level(logging.INFO, logger="recon"):
        _run(58, {0: 50}, number=every_2nd)
    said = [r.getMessage() for r in caplog.records if "get no pose" in r.getMessage()]
    assert said == ["frames 200-214 get no pose: the camera was lost and not found again before the end of the video"]


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
    """The phone's images 35-70: the camera lost at frame 29, the 29 frames before it refused
    (their motion), then SfM: its error says all three."""
    import recon.poses.frontend.streaming as fe
    import recon.poses.sfm.mapper as sfm
    from recon.poses import estimate_poses

    seq, prior = pose_room

    def scripted(intrinsics, prior, config, number, park=None):
        return StreamingPieces(lambda first, intr, lens: _Scripted(first, intr, lens, 29 if first == 0 else None,
                                                                   first == 0),
                               intrinsics, min_frames=22, keep=LOSS + 1)

    def sfm_fails(*args, **kwargs):
        raise TrackingLostError("SfM registered only 3 of 36 frames")

    monkeypatch.setattr(fe, "streaming_frontend", scripted)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", sfm_fails)
    said = (r"front end failed \(tracking lost at frame 29 and not recovered before the end of the video; the frames "
            r"before it: the camera turns on the spot\), and so did the SfM fallback ")
    with pytest.raises(TrackingLostError, match=said + r"\(SfM registered only 3"):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False, restart_after_loss=True)


def test_frames_failing_before_a_loss_get_no_pose():
    """A piece that ends at a loss is asked to forget the frames before it whose tracking was
    already failing (failing; its lookback never leaves it shorter than min_frames) and the
    last piece, which ends with the video, is not. The frames forgotten get no pose, are said
    with the reason, and the "lost" break runs from the piece's last posed frame to the next piece."""
    made = []
    res, _ = _run(120, {0: 40, 40: 68}, failing_from={0: 33, 40: 50}, failing=(0.85, LOSS), pieces=made)
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [
        ([0, 32], True), ([33, 39], False), ([40, 61], True), ([62, 67], False), ([68, 119], True)]
    # The second piece (frames 40-67) fails from frame 50 but keeps min_frames (22) of its 28.
    assert [p.failing for p in made] == [(0.85, LOSS), (0.85, 28 - 22), None]
    assert not np.isfinite(res.poses[33:40]).any() and np.isfinite(res.poses[:33]).all()
    assert [(b["before"], b["after"]) for b in res.diagnostics["scale_watch"]["breaks"] if b["kind"] == "lost"] \
        == [(32, 40), (61, 68)]
    why = [p.get("why") for p in res.diagnostics["pieces"]]
    assert why == [None, "tracking was failing there before the camera was lost", None,
                   "tracking was failing there before the camera was lost", None]


def test_without_failing_the_frames_before_a_loss_are_kept():
    made = []
    res, _ = _run(80, {0: 40}, failing_from={0: 33}, pieces=made)
    assert [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]] == [([0, 39], True), ([40, 79], True)]
    assert [p.failing for p in made] == [None, None]


def test_the_run_names_the_pieces_without_a_pose_by_video_frame(caplog):
    """recon.core.stages.gate_estimate says each piece without a pose with its reason, by
    video frame (--start 5, --stride 2 here), and report.json lists the pieces so."""
    from recon.core.stages import gate_estimate

    res, _ = _run(120, {0: 40, 40: 45, 45: 80})
    video = [5 + 2 * i for i in range(120)]
    with caplog.at_level(logging.WARNING, logger="recon"):
        kept, info, note = gate_estimate(res, video)
    said = [r.getMessage() for r in caplog.records if "no pose" in r.getMessage()]
    assert said == ["video frames 85-93 get no pose and are left out of depth and fusion: tracking, started again "
                    "after the camera was lost, lost it again within 22 frames"]
    assert [p["frames"] for p in info["diagnostics"]["pieces"]] == [[5, 83], [85, 93], [95, 163], [165, 243]]
    # Those frames said once: the gate's note is for frames it leaves out otherwise (none here).
    assert not kept[40:45].any() and kept[:40].all() and note == ""
    assert info["quality"]["dropped_ranges"] == [[85, 93]]
    res.diagnostics["frame_inlier"][10] = 0.01  # a frame the gate leaves out for its evidence: in the note alone
    with caplog.at_level(logging.WARNING, logger="recon"):
        _, _, note = gate_estimate(res, video)
    assert note.startswith("1 of 120 frames have no pose the images back (video frames 25)")
