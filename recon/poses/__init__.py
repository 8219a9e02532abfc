"""Camera poses from video. Entry point: :func:`estimate_poses`.

The packages, by role (lower ones never import higher ones; tests/test_layers.py):
``result`` (what every estimator returns) < ``ba``, ``matching`` < ``checks`` < ``config``
(the front end's settings) < ``intrinsics``, ``given`` < ``frontend`` (the DROID-SLAM-style
dense front end) < ``sfm`` (pycolmap, the second estimator) < ``second_opinion`` (the two
compared), ``options`` (``--pose-option``) and this entry point. Conventions as everywhere
in recon: camera-to-world 4x4 poses, OpenCV camera axes, metres; intrinsics (fx, fy, cx, cy)
in pixels of the frames.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from recon.choices import POSE_METHODS
from recon.errors import ReconInputError
from recon.poses.options import (
    check_pose_config,
    check_pose_options,
    configure_frontend,
    format_pose_option,
    parse_pose_option,
    pose_option_table,
)
from recon.poses.result import PoseResult, TrackingLostError, numbered, parse_intrinsics
from recon.poses.second_opinion import doubts, second_opinion, stretches

log = logging.getLogger(__name__)

__all__ = ["POSE_METHODS", "PoseResult", "TrackingLostError", "check_pose_config", "check_pose_options",
           "estimate_poses", "format_pose_option", "parse_pose_option", "pose_option_table"]


def estimate_poses(frames, prior_depth, intrinsics=None, method: str = "auto", device: str = "cpu",
                   progress: bool = True, frame_numbers=None, **options) -> PoseResult:
    """Metric camera-to-world poses of every frame of a video.

    frames: (N, H, W, 3) uint8 RGB at working resolution. prior_depth: (N, h, w) float32
    metric depth (0 invalid), any resolution with the frames' aspect, or a callable
    ``prior(index, frame)``. intrinsics: (fx, fy, cx, cy) in pixels of `frames` (or a 3x3
    matrix), or None to estimate the focal length (principal point at the centre; reported
    in ``PoseResult.intrinsics`` and ``diagnostics["focal_search"]``). method: "frontend"
    (dense flow + BA), "sfm" (pycolmap) or "auto" (front end, then SfM when tracking is
    lost or the front end refuses its trajectory, with a logged warning and
    ``diagnostics["fallback"]``; and SfM as a second opinion where the front end refused or
    marked part of its trajectory: the two compared, ``diagnostics["second_opinion"]``,
    ``recon.poses.second_opinion``). device: where the front
    end's dense bundle adjustment runs (``ba.BAOptions.device``); DIS flow, the tracking
    bookkeeping and SfM stay on the CPU. frame_numbers: the video's frame number of each
    frame, as errors and log lines name them (default: positions); the result counts
    positions.
    options: ``FrontendConfig`` fields for the front end (``config=`` for a whole config),
    ``SfMConfig`` fields for SfM (``sfm_config=``); a field name that belongs to neither
    raises ReconInputError.

    Raises TrackingLostError (front end, or auto when SfM also fails) or ReconInputError.
    """
    from recon.poses.frontend.streaming import estimate_poses_frontend
    from recon.poses.sfm.mapper import SfMConfig, estimate_poses_sfm

    if method not in POSE_METHODS:
        raise ReconInputError(f"pose method must be one of {', '.join(POSE_METHODS)}, got {method!r}")
    intrinsics = parse_intrinsics(intrinsics)
    fe_cfg = options.pop("config", None)
    sfm_cfg = options.pop("sfm_config", None) or SfMConfig()
    check_pose_options(options)
    fe_cfg = configure_frontend(options, device, fe_cfg)
    sfm_cfg = replace(sfm_cfg, **{k: v for k, v in options.items() if k in SfMConfig.__dataclass_fields__})
    check_pose_config(sfm_cfg)
    if method == "sfm":
        return estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg,
                                  frame_numbers=frame_numbers)

    def sfm(said: str) -> PoseResult:
        # Said once: with progress bars before SfM's (which take a while), else after it.
        if progress:
            log.warning("%s", said)
        return estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg,
                                  frame_numbers=frame_numbers)

    try:
        result = estimate_poses_frontend(frames, prior_depth, intrinsics, progress=progress, config=fe_cfg,
                                         frame_numbers=frame_numbers)
    except TrackingLostError as err:
        if method == "frontend" or not (err.sfm_may_help or err.untrusted_result is not None):
            raise
        try:
            result = sfm(f"front end failed ({err}); falling back to SfM (pycolmap)")
        except TrackingLostError as sfm_err:
            raise TrackingLostError(f"no camera poses: the front end failed ({err}), and so did the SfM fallback "
                                    f"({sfm_err})", frame=err.frame) from None
        _check_sfm_focal(result, err, intrinsics, fe_cfg, frames)
        if not progress:
            log.warning("front end failed (%s); the poses are from the SfM fallback (pycolmap)", err)
        result.diagnostics["fallback"] = {"from": "frontend", "reason": str(err), "frame": err.frame}
        if err.untrusted_result is not None:
            refused = _padded(err.untrusted_result.poses, len(result.poses))
            opinion = second_opinion(refused, result.poses, f"the front end refused its trajectory: {err}", True,
                                     sfm_doubt=_sfm_doubt(result))
            result.diagnostics["second_opinion"] = opinion.to_dict()
        return result
    asked = doubts(result.diagnostics, numbered(frame_numbers)) if method == "auto" and fe_cfg.stop_untrusted else ""
    if not asked:
        return result
    try:
        other = sfm(f"the front end doubts part of its trajectory ({asked}); asking SfM (pycolmap) for a second "
                    "opinion")
    except TrackingLostError as sfm_err:
        result.diagnostics["second_opinion"] = second_opinion(result.poses, None, asked, False,
                                                              sfm_failure=str(sfm_err)).to_dict()
        return result
    opinion = second_opinion(result.poses, other.poses, asked, False, stretches(result.diagnostics,
                                                                                 len(result.poses)),
                             sfm_doubt=_sfm_doubt(other))
    kept = other if opinion.kept == "SfM" else result
    if kept is other and intrinsics is None:
        other.diagnostics["focal"] = result.diagnostics.get("focal")
    kept.diagnostics["second_opinion"] = opinion.to_dict()
    return kept


def _padded(poses: np.ndarray, count: int) -> np.ndarray:
    """(count, 4, 4) poses: the first len(poses) given, NaN after (frames not posed)."""
    out = np.full((count, 4, 4), np.nan)
    out[:len(poses)] = poses
    return out


def _sfm_doubt(result: PoseResult) -> str:
    """What SfM's own checks hold against its map ("" for nothing): its scale spread."""
    spread = result.diagnostics.get("scale_spread", {})
    if spread.get("consistent", True):
        return ""
    return f"its scale against the depth prior's varies x{spread['factor']:.2f} from frame to frame"


def _check_sfm_focal(result: PoseResult, err: TrackingLostError, intrinsics, fe_cfg, frames) -> None:
    """SfM's focal length is one estimate more where the front end searched one: said with
    the range all of them leave open, and refused where the vanishing points contradict it."""
    if err.focal_choice is None or intrinsics is not None:
        return
    choice = err.focal_choice.with_estimate("SfM bundle adjustment", result.intrinsics[0])
    why = choice.contradicted()
    if why and fe_cfg.stop_untrusted:
        raise TrackingLostError(f"no camera poses: the front end failed ({err}), and the SfM fallback's "
                                f"trajectory cannot be trusted: {why}", frame=err.frame)
    result.diagnostics["focal"] = choice.to_dict()
    log.warning(choice.warning(np.asarray(frames[0]).shape[1]))
