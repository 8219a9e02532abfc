"""Camera poses from video: the DROID-SLAM-style dense front end (``frontend``), the pycolmap
SfM fallback (``sfm``), pose files (``formats``) and the pieces they share.

Entry point: :func:`estimate_poses`. Conventions as everywhere in recon: camera-to-world
4x4 poses, OpenCV camera axes, metres; intrinsics (fx, fy, cx, cy) in pixels of the frames.
The settings the command line can change (``--pose-option``) and their checks are in
:mod:`recon.poses.options`.
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
from recon.poses.result import PoseResult, TrackingLostError, parse_intrinsics

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
    lost, with a logged warning and ``diagnostics["fallback"]``). device: where the front
    end's dense bundle adjustment runs (``ba.BAOptions.device``); DIS flow, the tracking
    bookkeeping and SfM stay on the CPU. frame_numbers: the video's frame number of each
    frame, as errors and log lines name them (default: positions); the result counts
    positions.
    options: ``FrontendConfig`` fields for the front end (``config=`` for a whole config),
    ``SfMConfig`` fields for SfM (``sfm_config=``); a field name that belongs to neither
    raises ReconInputError.

    Raises TrackingLostError (front end, or auto when SfM also fails) or ReconInputError.
    """
    from recon.poses.frontend import estimate_poses_frontend
    from recon.poses.sfm import SfMConfig, estimate_poses_sfm

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
    try:
        return estimate_poses_frontend(frames, prior_depth, intrinsics, progress=progress, config=fe_cfg,
                                       frame_numbers=frame_numbers)
    except TrackingLostError as err:
        if method == "frontend" or not err.sfm_may_help:
            raise
        # Said once: with progress bars before SfM's (which take a while), else after SfM
        # succeeded (when it fails too, its error says both).
        if progress:
            log.warning("front end failed (%s); falling back to SfM (pycolmap)", err)
        try:
            result = estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg,
                                        frame_numbers=frame_numbers)
        except TrackingLostError as sfm_err:
            raise TrackingLostError(f"no camera poses: the front end failed ({err}), and so did the SfM fallback "
                                    f"({sfm_err})", frame=err.frame) from None
        choice = None
        if err.focal_choice is not None and intrinsics is None:
            # SfM's focal length is one estimate more: said with the range all of them leave open.
            choice = err.focal_choice.with_estimate("SfM bundle adjustment", result.intrinsics[0])
            why = choice.contradicted()
            if why and fe_cfg.stop_untrusted:
                raise TrackingLostError(f"no camera poses: the front end failed ({err}), and the SfM fallback's "
                                        f"trajectory cannot be trusted: {why}", frame=err.frame)
        if not progress:
            log.warning("front end failed (%s); the poses are from the SfM fallback (pycolmap)", err)
        result.diagnostics["fallback"] = {"from": "frontend", "reason": str(err), "frame": err.frame}
        if choice is not None:
            result.diagnostics["focal"] = choice.to_dict()
            log.warning(choice.warning(np.asarray(frames[0]).shape[1]))
        return result

