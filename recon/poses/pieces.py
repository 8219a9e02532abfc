"""Tracking that starts again where it lost the camera: a video tracked in pieces, each from
where the last one lost it, returned as one estimate whose pieces are apart.

Why: a hand-held video that cuts, blurs or turns away into nothing for a second loses the
front end's map. Falling back to SfM for the whole video (what a loss otherwise does)
throws away the stretch that tracked; stopping throws away the rest. Like ORB-SLAM's
Atlas, which starts a new map when tracking is lost and keeps the old one, the front end
is started again at the first lost frame (same camera: the first piece's intrinsics and
lens), as often as the video needs. The pieces' trajectories share no frame, so the
scale watch (``recon.poses.scale_watch``) marks each restart as a break of kind "lost";
the pipeline then tries to join the pieces like any stretches between breaks
(``recon.drivers.segments``) and writes those it cannot join as separate reconstructions.

:func:`track_in_pieces` runs the pieces; :func:`merge_pieces` puts their estimates
together, frames numbered in the whole video. A piece that loses the camera within
``min_frames`` of its start, or a rest of the video shorter than that, is not kept: its
frames get no pose (the quality gate leaves them out) and the next piece starts where it
lost the camera.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from recon.poses.motion_checks import MotionChecks
from recon.poses.quality import runs
from recon.poses.result import PoseResult, TrackingLostError
from recon.poses.scale_watch import ScaleBreak, ScaleWatch

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Piece:
    """Frames [first, stop) of the video and their estimate (None: not tracked)."""

    first: int
    stop: int
    result: PoseResult | None


def track_in_pieces(track: Callable[[int, int, tuple | None, float | None], PoseResult], count: int,
                    loss: TrackingLostError, intrinsics, min_frames: int) -> PoseResult:
    """The video's frames [0, count) tracked piece by piece, starting again at each loss.

    track(first, stop, intrinsics, lens_k1) tracks frames [first, stop) (intrinsics None:
    searched; lens_k1 None: the front end's own setting) and raises TrackingLostError, whose
    ``frame`` counts from `first` and whose ``lost`` says it lost the camera (rather than
    refusing the trajectory). loss: the loss of a first attempt on the whole video (its
    frame is where the first piece ends). Raises `loss` again when no piece of min_frames
    or more tracks, or the first piece's own error when it fails otherwise."""
    if loss.frame is None or loss.frame < min_frames:
        raise loss
    pieces: list[Piece] = []
    start, stop, lens = 0, int(loss.frame), None
    while start < count:
        if stop - start < min_frames:  # too short a rest to be a reconstruction of its own
            pieces.append(Piece(start, stop, None))
            start, stop = stop, count
            continue
        try:
            result = track(start, stop, intrinsics, lens)
        except TrackingLostError as err:
            if not err.lost or not err.frame:
                if not any(p.result is not None for p in pieces):
                    raise
                log.warning("frames %d-%d: no trajectory (%s)", start, count - 1, err)
                pieces.append(Piece(start, count, None))
                break
            if err.frame < min_frames:
                pieces.append(Piece(start, start + err.frame, None))
                start, stop = start + err.frame, count
                continue
            stop = start + err.frame
            continue
        if not any(p.result is not None for p in pieces):
            # The same camera throughout: the first piece's, whether given or estimated.
            intrinsics = result.intrinsics
            lens = result.diagnostics.get("lens_k1")
        pieces.append(Piece(start, stop, result))
        if stop < count:
            log.warning("tracking lost at frame %d; tracking again from there as a new piece", stop)
        start, stop = stop, count
    if not any(p.result is not None for p in pieces):
        raise loss
    for a, b in runs([i for p in pieces if p.result is None for i in range(p.first, p.stop)]):
        log.warning("frames %d-%d get no pose: tracking, started again after the camera was lost, lost it again "
                    "within %d frames", a, b, min_frames)
    return merge_pieces(pieces, count)


def merge_pieces(pieces: list[Piece], count: int) -> PoseResult:
    """One estimate of frames [0, count) from consecutive pieces (module docstring): poses
    (NaN where a piece has none), keyframes, keyframe depth, per-frame states and evidence
    (frames without a pose "lost"), the scale watches with a "lost" break at the start of
    each piece after the first, the motion checks, and per piece its frames and metric
    scale (``diagnostics["pieces"]``). The first tracked piece's intrinsics and other
    settings stand for the whole."""
    tracked = [p for p in pieces if p.result is not None]
    first = tracked[0].result
    poses = np.full((count, 4, 4), np.nan)
    status, inlier = ["lost"] * count, [float("nan")] * count
    keyframes, depth, watch, checks, lost_frames = [], [], None, None, []
    for n, p in enumerate(tracked):
        r, names = p.result, np.arange(p.first, p.stop)
        poses[p.first:p.stop] = r.poses
        status[p.first:p.stop] = r.diagnostics.get("frame_status") or ["tracked"] * len(names)
        inlier[p.first:p.stop] = r.diagnostics.get("frame_inlier") or [float("nan")] * len(names)
        keyframes.append(p.first + np.asarray(r.keyframes, dtype=np.int64))
        if r.keyframe_depth is not None:
            depth.append(r.keyframe_depth)
        lost_frames += [p.first + i for i in r.diagnostics.get("lost_frames", [])]
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
                    "metric_scale_factor": p.result.diagnostics.get("metric_scale_factor") if p.result else None}
                   for p in pieces],
        "scale_watch": watch.to_dict(),
        "motion_checks": checks.to_dict(),
    }
    return PoseResult(poses, first.intrinsics, np.concatenate(keyframes), float(sum(p.result.seconds for p in tracked)),
                      diagnostics, np.concatenate(depth) if len(depth) == len(tracked) else None)


__all__ = ["Piece", "merge_pieces", "track_in_pieces"]
