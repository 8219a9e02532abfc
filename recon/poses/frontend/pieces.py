"""Tracking that starts again where it lost the camera: a video tracked in pieces, each from
where the last one lost it, returned as one estimate whose pieces are apart.

Like ORB-SLAM's Atlas (a new map when tracking is lost, the old one kept), the front end is
started again at the first lost frame with the same camera, as often as the video needs;
each restart is a scale break of kind "lost", joined or written as segments downstream.
:class:`StreamingPieces` does so as the frames come; :func:`merge_pieces` puts the pieces'
estimates together, frames numbered in the whole video. Pieces too short (``min_frames``)
and frames whose tracking was failing before a loss get no pose, with their reason.
More: docs/poses.md#tracking-fast-motion-and-cuts
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from recon.poses.checks.motion_checks import MotionChecks
from recon.poses.checks.prior_agreement import PriorAgreement
from recon.poses.checks.prior_agreement import joined as joined_agreement
from recon.poses.checks.scale_watch import ScaleBreak, ScaleWatch
from recon.poses.result import FrameNumbers, PoseResult, TrackingLostError, by_position, frame_spans

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Piece:
    """Frames [first, stop) of the video and their estimate (None: not tracked, why says why)."""

    first: int
    stop: int
    result: PoseResult | None
    why: str = ""


@dataclass
class _Open:
    """A piece while the video comes: its first frame, its front end (None: it lost the
    camera within min_frames and gets no pose) and where it ended (None: still going)."""

    first: int
    frontend: object | None
    stop: int | None = None
    why: str = ""


class StreamingPieces:
    """A :class:`~recon.poses.frontend.streaming.StreamingFrontend` (``add``, ``current``,
    ``finish_image``, ``finish``, ``intrinsics``; frames numbered in the whole video) that
    starts again where it loses the camera (module docstring).

    make(first, intrinsics, lens_k1): a new front end for the piece that starts at video
    frame `first`, its frames numbered from 0 (intrinsics None: searched; lens_k1 None: the
    front end's own setting). min_frames: the shortest piece kept. keep: recent frames kept
    for a restart, at least a whole loss (``max_lost + 1``); while the first piece buffers
    frames for its focal search, all of them are kept. failing: (share, lookback): a piece
    that ends where the camera was lost also gives up the frames before the loss whose
    tracking was already failing (``StreamingFrontend.finish``'s failing; never below
    min_frames); None: it keeps them. number: how what it says names video frames
    (``result.FrameNumbers``); `make` gives each piece's front end the same numbers.

    The first piece is always kept (one that loses the camera sooner hands the loss back):
    its front end is the camera's (intrinsics, lens, focal choice) for every later piece.
    """

    def __init__(self, make: Callable[[int, tuple | None, float | None], object], intrinsics, min_frames: int,
                 keep: int, failing: tuple[float, int] | None = None, number: FrameNumbers = by_position):
        self._make = make
        self._number = number
        self._min_frames = min_frames
        self._failing = failing
        self._keep = max(int(keep), 1)
        self._recent: list[tuple[int, np.ndarray]] = []
        self._pieces = [_Open(0, make(0, intrinsics, None))]
        self._loss: TrackingLostError | None = None  # the first loss started again from
        self.count = 0

    @property
    def _first(self):
        return self._pieces[0].frontend

    @property
    def intrinsics(self) -> tuple | None:
        """The camera as known now (None while the first piece's focal search waits)."""
        return self._first.intrinsics

    @property
    def focal_choice(self):
        """The first piece's focal-length choice (``StreamingFrontend.focal_choice``)."""
        return self._first.focal_choice

    def add(self, index: int, frame: np.ndarray) -> tuple[str, np.ndarray | None]:
        """Track frame `index` (in order); its status and camera-to-world pose as tracked now
        (``StreamingFrontend.add``; frames of a piece that got no pose: "lost", None)."""
        self.count += 1
        self._recent.append((index, frame))
        self._feed(index, frame)
        status = self.current(index)
        if status[0] != "buffered":
            del self._recent[:-self._keep]
        return status

    def current(self, index: int) -> tuple[str, np.ndarray | None]:
        piece = next(p for p in reversed(self._pieces) if p.first <= index)
        if piece.frontend is None:
            return "lost", None
        return piece.frontend.current(index - piece.first)

    def finish_image(self, frame: np.ndarray) -> np.ndarray:
        """``StreamingFrontend.finish_image`` (every piece works at the same size)."""
        return self._first.finish_image(frame)

    def _feed(self, index: int, frame: np.ndarray) -> None:
        self._track(lambda piece: piece.frontend.add(index - piece.first, frame))

    def _track(self, step: Callable[[_Open], object]) -> None:
        """step(the open piece) (a frame added, or its buffer tracked), starting a new piece
        where it loses the camera; nothing when the open piece gets no pose."""
        piece = self._pieces[-1]
        if piece.frontend is None:
            return
        try:
            step(piece)
        except TrackingLostError as err:
            if not err.lost or err.frame is None:
                raise
            self._restart(piece, piece.first + int(err.frame), err)

    def _restart(self, piece: _Open, at: int, loss: TrackingLostError) -> None:
        """Close `piece` where it lost the camera and track the frames since in a new one."""
        kept = at - piece.first >= self._min_frames
        if not kept and piece is self._pieces[0]:
            raise loss  # a run without restarts would have lost it here too
        self._loss = self._loss or loss
        piece.stop = at
        if kept:
            # Said by the caller with the video's frame numbers (a "lost" break of the scale watch).
            log.info("tracking lost at frame %d; tracking again from there as a new piece", self._number(at))
        else:
            piece.frontend = None
            piece.why = (f"tracking, started again after the camera was lost, lost it again within "
                         f"{self._min_frames} frames")
        again = [(i, f) for i, f in self._recent if i >= at]
        start = again[0][0] if again else self.count
        if start > at:  # frames older than what is kept (a loss inside the focal search's buffer)
            self._pieces.append(_Open(at, None, start, "lost with the camera, and no longer kept to be tracked again"))
        new = _Open(start, self._make(start, self._first.intrinsics, self._first.lens_k1))
        self._pieces.append(new)
        for i, f in again:
            if self._pieces[-1] is not new:
                break  # it lost the camera among them: the piece started there took the rest
            self._feed(i, f)

    def finish(self, frame_lookup: Callable[[int], np.ndarray], progress: bool = False) -> PoseResult:
        """The pieces closed (``StreamingFrontend.finish``; frames read back by video frame
        number) and merged (:func:`merge_pieces`); one piece: its own result. Raises
        TrackingLostError when no piece tracks, or when the first fails otherwise."""
        # A video shorter than the focal search's buffer: the first piece tracks it now, so that
        # a loss in it starts a new piece as it would have while the frames came.
        self._track(lambda piece: piece.frontend.flush())
        pieces: list[Piece] = []
        for p in self._pieces:
            stop = self.count if p.stop is None else p.stop
            if p.frontend is None:
                pieces.append(Piece(p.first, stop, None, p.why))
                continue
            first = p is self._pieces[0]
            tail = p.frontend.lost_tail() if p.stop is None else None
            if tail is not None and tail < self._min_frames and first:
                tail = None  # its own error says where it lost the camera
            end = stop if tail is None else p.first + tail
            if tail is not None:
                self._loss = self._loss or TrackingLostError.at_the_end(end, self._number)
            lost_tail = Piece(end, stop, None, "the camera was lost and not found again before the end of the video")
            if not first and end - p.first < self._min_frames:
                pieces.append(Piece(p.first, end, None, f"fewer than {self._min_frames} frames tracked after "
                                                        "tracking started again"))
                pieces += [lost_tail] if end < stop else []
                continue
            try:
                result = p.frontend.finish(lambda i, first=p.first: frame_lookup(first + i), progress,
                                           stop=end - p.first, failing=self._failing_before(p.first, end))
            except TrackingLostError as err:
                if first:
                    if self._loss is not None and not err.lost:
                        # The frames before the first loss, refused (their motion): said with the loss.
                        refused = TrackingLostError(f"{self._loss}; the frames before it: {err}",
                                                    frame=self._loss.frame, lost=True,
                                                    sfm_may_help=self._loss.sfm_may_help)
                        refused.untrusted_result = err.untrusted_result
                        raise refused from None
                    raise
                pieces.append(Piece(p.first, stop, None, f"no trajectory ({err})"))
                continue
            failed = p.first + len(result.poses)  # the frames before the loss whose tracking was failing
            pieces.append(Piece(p.first, failed, result))
            if failed < end:
                pieces.append(Piece(failed, end, None, "tracking was failing there before the camera was lost"))
            pieces += [lost_tail] if end < stop else []
        if len(pieces) == 1:
            return pieces[0].result
        pieces = _joined_untracked(pieces)
        for p in pieces:
            if p.result is None:  # said by the caller with the video's frame numbers (diagnostics["pieces"])
                log.info("frames %s get no pose: %s", frame_spans([(p.first, p.stop - 1)], self._number), p.why)
        return merge_pieces(pieces, self.count)

    def _failing_before(self, first: int, end: int) -> tuple[float, int] | None:
        """``finish``'s failing for the piece of frames [first, end) when it ends at a loss
        (its lookback never leaves it shorter than min_frames), else None."""
        if self._failing is None or end >= self.count:
            return None
        share, lookback = self._failing
        lookback = min(lookback, end - first - self._min_frames)
        return (share, lookback) if lookback > 0 else None


def _joined_untracked(pieces: list[Piece]) -> list[Piece]:
    """Consecutive pieces without a pose for the same reason as one (a run of frames each of
    which lost the camera at once)."""
    out: list[Piece] = []
    for p in pieces:
        if out and p.result is None and out[-1].result is None and out[-1].stop == p.first and out[-1].why == p.why:
            out[-1] = Piece(out[-1].first, p.stop, None, p.why)
        else:
            out.append(p)
    return out


def merge_pieces(pieces: list[Piece], count: int) -> PoseResult:
    """One estimate of frames [0, count) from consecutive pieces (module docstring): poses
    (NaN where a piece has none), keyframes, keyframe depth, per-frame states and evidence
    (frames without a pose "lost"), the scale watches with a "lost" break at the start of
    each piece after the first, the motion checks, and per piece its frames and metric
    scale, or why it has no pose (``diagnostics["pieces"]``). The first tracked piece's
    intrinsics and other settings stand for the whole."""
    tracked = [p for p in pieces if p.result is not None]
    first = tracked[0].result
    poses = np.full((count, 4, 4), np.nan)
    status, inlier = ["lost"] * count, [float("nan")] * count
    keyframes, depth, watch, checks, lost_frames, agreements = [], [], None, None, [], []
    for n, p in enumerate(tracked):
        r, names = p.result, np.arange(p.first, p.stop)
        poses[p.first:p.stop] = r.poses
        status[p.first:p.stop] = r.diagnostics.get("frame_status") or ["tracked"] * len(names)
        inlier[p.first:p.stop] = r.diagnostics.get("frame_inlier") or [float("nan")] * len(names)
        keyframes.append(p.first + np.asarray(r.keyframes, dtype=np.int64))
        if r.keyframe_depth is not None:
            depth.append(r.keyframe_depth)
        lost_frames += [p.first + i for i in r.diagnostics.get("lost_frames", [])]
        if "prior_agreement" in r.diagnostics:
            agreements.append(PriorAgreement.from_dict(r.diagnostics["prior_agreement"]).renumbered(names))
        piece_watch = ScaleWatch.from_dict(r.diagnostics["scale_watch"]).renumbered(names) \
            if "scale_watch" in r.diagnostics else ScaleWatch([], [], float("nan"), judged=False)
        piece_checks = MotionChecks.from_dict(r.diagnostics["motion_checks"]).renumbered(names) \
            if "motion_checks" in r.diagnostics else MotionChecks()
        if watch is None:
            watch, checks = piece_watch, piece_checks
            continue
        restart = ScaleBreak(before=int(tracked[n - 1].stop - 1), after=int(p.first), factor=1.0, z=0.0, kind="lost")
        watch, checks = watch.joined(piece_watch, restart), checks.joined(piece_checks)
    untracked = [i for p in pieces if p.result is None for i in range(p.first, p.stop)]
    diagnostics = {
        **first.diagnostics,
        "frame_status": status, "frame_inlier": inlier, "lost_frames": sorted(lost_frames + untracked),
        "num_keyframes": int(sum(len(k) for k in keyframes)),
        "pieces": [{"frames": [p.first, p.stop - 1], "tracked": p.result is not None,
                    "metric_scale_factor": p.result.diagnostics.get("metric_scale_factor") if p.result else None,
                    **({} if p.result else {"why": p.why})}
                   for p in pieces],
        "scale_watch": watch.to_dict(),
        "motion_checks": checks.to_dict(),
        **({"prior_agreement": joined_agreement(agreements).to_dict()} if agreements else {}),
    }
    return PoseResult(poses, first.intrinsics, np.concatenate(keyframes), float(sum(p.result.seconds for p in tracked)),
                      diagnostics, np.concatenate(depth) if len(depth) == len(tracked) else None)


__all__ = ["Piece", "StreamingPieces", "merge_pieces"]
