"""Camera poses from video: the DROID-SLAM-style dense front end (``frontend``), the pycolmap
SfM fallback (``sfm``), pose files (``formats``) and the pieces they share.

Entry point: :func:`estimate_poses`. Conventions as everywhere in recon: camera-to-world
4x4 poses, OpenCV camera axes, metres; intrinsics (fx, fy, cx, cy) in pixels of the frames.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

from recon.errors import ReconInputError
from recon.poses.result import PoseResult, TrackingLostError, parse_intrinsics

log = logging.getLogger(__name__)

METHODS = ("auto", "frontend", "sfm")

__all__ = ["METHODS", "PoseResult", "TrackingLostError", "estimate_poses", "intrinsics_from_fov"]


def intrinsics_from_fov(fov_deg: float, width: int, height: int) -> tuple[float, float, float, float]:
    """(f, f, cx, cy) of a centred pinhole camera with horizontal field of view `fov_deg`."""
    if not 1.0 < float(fov_deg) < 179.0:
        raise ReconInputError(f"field of view must be between 1 and 179 degrees, got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(float(fov_deg)) / 2.0)
    return (f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def estimate_poses(frames, prior_depth, intrinsics=None, method: str = "auto", device: str = "cpu",
                   progress: bool = True, **options) -> PoseResult:
    """Metric camera-to-world poses of every frame of a video.

    frames: (N, H, W, 3) uint8 RGB at working resolution. prior_depth: (N, h, w) float32
    metric depth (0 invalid), any resolution with the frames' aspect, or a callable
    ``prior(index, frame)``. intrinsics: (fx, fy, cx, cy) in pixels of `frames` (or a 3x3
    matrix), or None to estimate the focal length (principal point at the centre; reported
    in ``PoseResult.intrinsics`` and ``diagnostics["focal_search"]``). method: "frontend"
    (dense flow + BA), "sfm" (pycolmap) or "auto" (front end, then SfM when tracking is
    lost, with a logged message and ``diagnostics["fallback"]``). device: accepted for
    symmetry with the pipeline; both estimators run on the CPU (the BA problems are small).
    options: ``FrontendConfig`` fields for the front end (``config=`` for a whole config),
    ``SfMConfig`` fields for SfM (``sfm_config=``); a field name that belongs to neither
    raises ReconInputError.

    Raises TrackingLostError (front end, or auto when SfM also fails) or ReconInputError.
    """
    from recon.poses.frontend import FrontendConfig, estimate_poses_frontend
    from recon.poses.sfm import SfMConfig, estimate_poses_sfm

    if method not in METHODS:
        raise ReconInputError(f"pose method must be one of {', '.join(METHODS)}, got {method!r}")
    intrinsics = parse_intrinsics(intrinsics)
    fe_cfg = options.pop("config", None) or FrontendConfig()
    sfm_cfg = options.pop("sfm_config", None) or SfMConfig()
    fe_fields, sfm_fields = set(FrontendConfig.__dataclass_fields__), set(SfMConfig.__dataclass_fields__)
    unknown = set(options) - fe_fields - sfm_fields
    if unknown:
        raise ReconInputError(f"unknown pose option(s): {', '.join(sorted(unknown))}")
    fe_cfg = replace(fe_cfg, **{k: v for k, v in options.items() if k in fe_fields})
    sfm_cfg = replace(sfm_cfg, **{k: v for k, v in options.items() if k in sfm_fields})
    if method == "sfm":
        return estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg)
    try:
        return estimate_poses_frontend(frames, prior_depth, intrinsics, progress=progress, config=fe_cfg)
    except TrackingLostError as err:
        if method == "frontend":
            raise
        message = f"front end failed ({err}); falling back to SfM (pycolmap)"
        log.warning(message)
        if progress:
            print(f"recon: {message}")
        result = estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg)
        result.diagnostics["fallback"] = {"from": "frontend", "reason": str(err), "frame": err.frame}
        return result
