"""Camera poses from video: the DROID-SLAM-style dense front end (``frontend``), the pycolmap
SfM fallback (``sfm``), pose files (``formats``) and the pieces they share.

Entry point: :func:`estimate_poses`. Conventions as everywhere in recon: camera-to-world
4x4 poses, OpenCV camera axes, metres; intrinsics (fx, fy, cx, cy) in pixels of the frames.
"""

from __future__ import annotations

import logging
import math
from dataclasses import fields, replace

from recon.errors import ReconInputError
from recon.options import scalar_fields, split_option, type_name, typed_value
from recon.poses.result import PoseResult, TrackingLostError, parse_intrinsics

log = logging.getLogger(__name__)

METHODS = ("auto", "frontend", "sfm")

__all__ = ["METHODS", "PoseResult", "TrackingLostError", "check_pose_config", "check_pose_options", "estimate_poses",
           "format_pose_option", "intrinsics_from_fov", "parse_pose_option", "pose_option_table"]


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
    check_pose_options(options)
    fe_fields, sfm_fields = set(FrontendConfig.__dataclass_fields__), set(SfMConfig.__dataclass_fields__)
    fe_cfg = replace(fe_cfg, **{k: v for k, v in options.items() if k in fe_fields})
    sfm_cfg = replace(sfm_cfg, **{k: v for k, v in options.items() if k in sfm_fields})
    check_pose_config(fe_cfg)
    check_pose_config(sfm_cfg)
    if method == "sfm":
        return estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg)
    try:
        return estimate_poses_frontend(frames, prior_depth, intrinsics, progress=progress, config=fe_cfg)
    except TrackingLostError as err:
        if method == "frontend":
            raise
        if progress:  # said before SfM's own progress bars, which take a while
            print(f"recon: front end failed ({err}); falling back to SfM (pycolmap)")
        try:
            result = estimate_poses_sfm(frames, prior_depth, intrinsics, progress=progress, config=sfm_cfg)
        except TrackingLostError as sfm_err:
            raise TrackingLostError(f"no camera poses: the front end failed ({err}), and so did the SfM fallback "
                                    f"({sfm_err})", frame=err.frame) from None
        if not progress:  # said once, by the error above, when SfM fails too
            log.warning("front end failed (%s); the poses are from the SfM fallback (pycolmap)", err)
        result.diagnostics["fallback"] = {"from": "frontend", "reason": str(err), "frame": err.frame}
        return result


def _option_fields() -> dict[str, tuple[str, object, object]]:
    """{name: (owner, type, default)} of the scalar fields of FrontendConfig and SfMConfig
    (a name both have, such as calibrate_lens, sets both)."""
    from recon.poses.frontend import FrontendConfig
    from recon.poses.sfm import SfMConfig

    table: dict[str, tuple[str, object, object]] = {}
    for cls in (FrontendConfig, SfMConfig):
        for name, (kind, default) in scalar_fields(cls).items():
            owner = table[name][0] + ", " + cls.__name__ if name in table else cls.__name__
            table[name] = (owner, kind, default)
    return table


# Ranges of the estimators' numeric settings (FrontendConfig, then SfMConfig; see their
# docstrings): outside them a setting makes no sense or breaks the estimator. Settings not
# listed take any finite value. None is not checked here: the command line gives None only
# to fields that may be None (``parse_pose_option``), Python callers are trusted with it.
_AT_LEAST_ONE = (">= 1", lambda v: v >= 1)
_AT_LEAST_ZERO = (">= 0", lambda v: v >= 0)
_POSITIVE = ("> 0", lambda v: v > 0)
_FRACTION = ("in [0, 1]", lambda v: 0 <= v <= 1)
_RANGES = {
    **dict.fromkeys(("ba_stride", "temporal_radius", "window", "calib_stride", "calib_flow_stride", "calib_iters",
                     "align_chunk", "torch_threads"), _AT_LEAST_ONE),
    **dict.fromkeys(("proximity_edges", "proximity_nms", "final_proximity_edges", "window_iters", "global_iters",
                     "prior_weight", "calibrate_after", "calibrate_iters", "max_lost", "reloc_candidates"), _AT_LEAST_ZERO),
    **dict.fromkeys(("keyframe_flow", "keyframe_max_flow", "proximity_max_flow", "calib_tol"), _POSITIVE),
    **dict.fromkeys(("proximity_min_overlap", "min_edge_weight", "lost_inlier", "min_registered"), _FRACTION),
    **dict.fromkeys(("min_match_correlation", "min_local_correlation"), ("in [-1, 1]", lambda v: -1 <= v <= 1)),
    "seed_min_flow": (">= 0", lambda v: v >= 0),
    "calib_keyframes": (">= 2", lambda v: v >= 2),
    **dict.fromkeys(("max_keyframes", "keyframe_stride", "max_num_features", "overlap", "num_threads"), _AT_LEAST_ONE),
    "correction_grid": ("two numbers >= 1", lambda v: len(v) == 2 and min(v) >= 1),
    "mapper": ("'incremental' or 'global'", lambda v: v in ("incremental", "global")),
    "keyframe_motion": _POSITIVE,
    "loop_candidates": _AT_LEAST_ONE,
    "loop_words": (">= 2", lambda v: v >= 2),
    "loop_matching": ("'retrieval', 'exhaustive' or 'none'", lambda v: v in ("retrieval", "exhaustive", "none")),
}


def _check_value(name: str, value) -> None:
    """ReconInputError when a scalar setting is outside its range; None, booleans and nested
    configs pass (see _RANGES)."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float, tuple, str)):
        return
    numbers = value if isinstance(value, tuple) else (value,)
    finite = all(isinstance(v, str) or math.isfinite(v) for v in numbers)
    rule = _RANGES.get(name)
    if not finite or (rule is not None and not rule[1](value)):
        raise ReconInputError(f"pose option {name} must be {rule[0] if rule else 'finite'}, got {value!r}")


def check_pose_config(config) -> None:
    """ReconInputError naming the first setting of a FrontendConfig or SfMConfig (and the
    FrontendConfig inside an SfMConfig) outside its range."""
    from recon.poses.frontend import FrontendConfig

    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, FrontendConfig):
            check_pose_config(value)
        else:  # flow and BA settings (nested configs) are set in Python and not checked here
            _check_value(f.name, value)


def check_pose_options(options: dict) -> None:
    """ReconInputError naming the keys of `options` that are no field of FrontendConfig or
    SfMConfig (nested configs such as ``flow`` included; the command line sets scalars only)."""
    from recon.poses.frontend import FrontendConfig
    from recon.poses.sfm import SfMConfig

    unknown = set(options) - set(FrontendConfig.__dataclass_fields__) - set(SfMConfig.__dataclass_fields__)
    if unknown:
        raise ReconInputError(
            f"unknown pose option(s): {', '.join(sorted(unknown))} (`--pose-option list` shows the options)"
        )
    for name, value in options.items():
        _check_value(name, value)


def parse_pose_option(text: str) -> tuple[str, object]:
    """KEY=VALUE from the command line as (key, value typed like the field), for a scalar
    field of FrontendConfig or SfMConfig: numbers, true/false, none where the field may be
    None, comma-separated numbers for tuples. Raises ReconInputError."""
    key, raw = split_option(text, "pose option")
    settable = _option_fields()
    if key not in settable:
        check_pose_options({key: None})
        raise ReconInputError(f"pose option {key} is a nested config; set its fields in Python (recon.poses.estimate_poses)")
    kind = settable[key][1]
    try:
        value = typed_value(raw, kind)
    except ValueError:
        raise ReconInputError(f"pose option {key}: {raw!r} is not a valid {type_name(kind)}") from None
    check_pose_options({key: value})
    return key, value


def format_pose_option(key: str, value) -> str:
    """KEY=VALUE as parse_pose_option reads it back (for commands echoed to the user)."""
    if isinstance(value, tuple):
        text = ",".join(str(v) for v in value)
    else:
        text = str(value).lower() if value is None or isinstance(value, bool) else str(value)
    return f"{key}={text}"


def pose_option_table() -> str:
    """The pose options (`--pose-option KEY=VALUE`) with type, default and owner, a line each."""
    rows = [(name, type_name(kind), repr(default), owner) for name, (owner, kind, default) in sorted(_option_fields().items())]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    return "\n".join(f"{n:<{widths[0]}}  {t:<{widths[1]}}  {d:<{widths[2]}}  {o}" for n, t, d, o in rows)
