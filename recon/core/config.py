"""The typed configuration of `recon run`: one dataclass the CLI mirrors flag for flag.

Each stage reads only its own part of it (see :mod:`recon.core.stages`); the whole is checked
once by ``validate`` before any work and recorded in ``report.json`` by ``to_dict``.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from medea_core import MedeaConfig
from mvs_core import MvsConfig

from ..choices import (
    DEVICE_PATTERN,
    DEVICE_SPELLINGS,
    ON_BREAK_CHOICES,
    POSE_METHODS,
    PRIOR_ALIGN_CHOICES,
    PRIOR_CHOICES,
    REFINE_CHOICES,
    RERUN_MODES,
    STREAM_CHOICES,
)
from ..errors import ReconInputError
from ..fusion import FusionOptions
from ..geometry.camera import check_distortion
from ..poses.given.polish import PolishConfig

# A readout longer than a frame at 10 fps is not a rolling shutter but a typo.
MAX_READOUT_MS = 100.0


def device_index(name: str) -> int | None:
    """N of a --device spelled cuda:N (None for cpu, cuda and auto); ReconInputError for
    any other spelling. Only the spelling: whether the machine has that device is the
    caller's to check, on the machine that will run it."""
    match = re.fullmatch(DEVICE_PATTERN, name)
    if match is None:
        raise ReconInputError(f"--device {name}: expected {DEVICE_SPELLINGS}")
    return None if match.group(1) is None else int(match.group(1))


@dataclass
class PipelineConfig:
    """Everything `recon run` can be told; defaults suit a phone video on a CPU.

    input, output: paths. overwrite: write into a non-empty output folder.
    stride, max_frames, start_time, end_time: frame selection (see recon.io.source.Selection).
    frame_budget: the most frames a one-shot run holds in memory, counted at 640x480 (a
        frame of more pixels counts for more: recon.core.stages.budget_capacity). A one-shot run
        needs about 1.1 GB and 14 MB a frame at 640x480. why:
        docs/decisions.md#the-frame-budget. stream: "auto" streams inputs with more frames than
        the budget holds (recon.drivers.streamed: frames flow through the stages, memory flat in the
        video's length) and videos whose poses are estimated (recon.pipeline.stream_reason),
        "on" always, "off" never (then, with no stride given, the stride is raised so that
        the frames fit the budget).
    depth_frames: which tracked frames get depth and are fused in a streamed run: "motion"
        (a frame each time the camera moved depth_motion x the median depth or turned
        depth_rotation degrees since the last one), "all", or "K" (every K-th frame).
    window, window_overlap: frames per MEDeA window of a streamed run (counted at 640x480
        like frame_budget: recon.core.stages.window_frames) and frames shared by
        consecutive windows. mesh_every: re-extract the mesh for live Rerun every this many
        fused frames (0: only at the end).
    width: working width in pixels (None: the input's own); fps: frame rate of an image folder.
    intrinsics: (fx, fy, cx, cy) in pixels of the input as decoded; fov: horizontal field
        of view in degrees (used when intrinsics are not given). Given intrinsics are used as
        given: no lens is estimated on top of them (``FrontendConfig.calibrate_lens``).
    distortion: the lens of those intrinsics (or of the fov's camera), OpenCV's k1, k2, p1,
        p2[, k3]; None: a dataset's published coefficients when its calibration is used,
        else a pinhole camera. The frames are resampled into the pinhole camera as they are
        decoded (recon.io.source.FrameSource.to_pinhole).
    poses: "auto", "gt" (dataset ground truth), "estimate", or a pose file / folder
        (TUM, COLMAP, nerfstudio, 7-Scenes/ScanNet matrices, Open3D .log).
    rolling_shutter: the camera's rolling-shutter readout time in milliseconds (0: a global
        shutter). The frames are resampled to one instant each, with the angular velocity of
        the given poses or of a first estimate (then estimated again on the resampled frames):
        recon.geometry.rolling_shutter. A streamed run resamples its depth frames with given poses
        and leaves the frames as recorded with estimated ones (it tracks only once).
    pose_method: estimator, "auto" | "frontend" | "sfm".
    pose_options: fields of the estimators' configs (``recon.poses.config.FrontendConfig``,
        ``recon.poses.sfm.mapper.SfMConfig``) to change, e.g. {"keyframe_flow": 12.0}.
    on_break: what an estimated trajectory becomes where its scale breaks (the front end's
        map against the depth prior, ``recon.poses.checks.scale_watch``): "segments" (each stretch
        reconstructed on its own, ``OUT/segment_NN/``, with one summary), "stop" (the run
        stops with one line naming the frames) or "keep" (one trajectory, with a warning).
        Whatever it is, a trajectory the front end's motion checks distrust as a whole
        (``recon.poses.checks.motion_checks``) is not returned, except under "keep"; nor is one whose
        metric scale the depth prior cannot vouch for (its depth does not follow the scene's,
        ``recon.poses.checks.prior_agreement``), which "keep" returns with a warning.
    join_segments: before that, try to join the stretches on either side of each break
        (``recon.poses.checks.join``: the frames after it posed by PnP in the stretch before it, a
        similarity between the two); joined stretches are one trajectory again.
    join_through_map: where that finds nothing, join through one SfM model of views of
        both stretches (``recon.poses.sfm.map_join``: COLMAP registers each by PnP on the
        points of the others; needs pycolmap).
    prior: "fastdepth", "sensor" (a dataset's depth), "folder" (prior_path holds one
        depth map per frame, matched by name) or "hf" (prior_path is a local Hugging Face
        depth model folder; recon.priors.hf). weights: FastDepth weights location.
    prior_align: what an "hf" model that predicts affine-invariant disparity (its kind is
        read from its config, recon.priors.hf.model_kind) is fitted to, per frame, to make
        it metric: "fastdepth" (FastDepth on the same frames) or "sensor" (an RGB-D
        dataset's depth). Metric models are used as they are.
    features: give MEDeA FastDepth's encoder features (the feature-metric loss).
    adjust: run MEDeA (False fuses the raw prior). medea: MEDeA's configuration.
    medea_gate: skip MEDeA, and give the refinement the prior's depth, when given poses
        contradict the frames (recon.poses.given.pose_check, run on every run with given poses:
        one warning either way). Off by default: skipping MEDeA trades depth accuracy for
        the mesh. why: docs/decisions.md#the-gate-on-given-poses
    refine: "mvs" (multi-view stereo refinement after MEDeA, mvs_core) or "none";
        mvs: its configuration (mvs_core.MvsConfig).
    polish: polish given poses against the frames before MEDeA when refining (one-shot
        runs; recon.poses.given.polish); off: given poses are used as given.
        why: docs/decisions.md#given-poses-are-used-as-given. polish_config: its settings.
    fusion: TSDF options (voxel size, truncation, depth clipping, fragment removal, ...).
    rerun: "spawn", "save", "serve" or "off"; rerun_path: .rrd for "save" (default
        OUT/recording.rrd); rerun_max_width: images wider than this are logged downscaled.
    device: "cpu", "cuda", "cuda:N" for prior, MEDeA and fusion.
    depth_npy: also write float32 .npy depth maps; glb: also write mesh.glb.
    """

    input: Path
    output: Path
    overwrite: bool = False
    stride: int | None = None
    max_frames: int | None = None
    start_time: float | None = None
    end_time: float | None = None
    frame_budget: int = 150
    stream: str = "auto"
    depth_frames: str = "motion"
    depth_motion: float = 0.02
    depth_rotation: float = 2.0
    window: int = 48
    window_overlap: int = 8
    mesh_every: int = 200
    width: int | None = 640
    fps: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    fov: float | None = None
    distortion: tuple[float, ...] | None = None
    rolling_shutter: float = 0.0
    poses: str = "auto"
    pose_method: str = "auto"
    pose_options: dict[str, Any] = field(default_factory=dict)
    on_break: str = "segments"
    join_segments: bool = True
    join_through_map: bool = True
    prior: str = "fastdepth"
    prior_path: Path | None = None
    prior_align: str = "fastdepth"
    weights: Path | None = None
    features: bool = True
    adjust: bool = True
    medea_gate: bool = False
    medea: MedeaConfig = field(default_factory=MedeaConfig.fast)
    refine: str = "mvs"
    mvs: MvsConfig = field(default_factory=MvsConfig)
    polish: bool = False
    polish_config: PolishConfig = field(default_factory=PolishConfig)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    rerun: str = "off"
    rerun_path: Path | None = None
    rerun_max_width: int | None = 320
    device: str = "cpu"
    progress: bool = True
    depth_npy: bool = True
    glb: bool = True

    def validate(self) -> None:
        """One-line ReconInputError for options that cannot work (they come from the CLI)."""
        self._validate_prior()
        if self.refine not in REFINE_CHOICES:
            raise ReconInputError(f"refine must be one of {', '.join(REFINE_CHOICES)}, got {self.refine!r}")
        try:
            self.mvs.validate()
            if self.adjust:
                self.medea.validate()
        except ValueError as error:
            raise ReconInputError(str(error)) from None
        if self.on_break not in ON_BREAK_CHOICES:
            raise ReconInputError(f"on_break must be one of {', '.join(ON_BREAK_CHOICES)}, got {self.on_break!r}")
        if self.rerun not in RERUN_MODES:
            raise ReconInputError(f"rerun mode must be one of {', '.join(RERUN_MODES)}, got {self.rerun!r}")
        if self.fov is not None and not (0 < self.fov < 180):
            raise ReconInputError(f"field of view must be between 0 and 180 degrees, got {self.fov}")
        if self.intrinsics is not None:
            k = np.asarray(self.intrinsics, dtype=np.float64)
            if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
                raise ReconInputError(
                    f"intrinsics must be four numbers fx,fy,cx,cy with fx, fy > 0, got {self.intrinsics}")
        if self.distortion is not None:
            check_distortion(self.distortion)
        if not (0.0 <= self.rolling_shutter <= MAX_READOUT_MS):
            raise ReconInputError(f"rolling-shutter readout must be between 0 and {MAX_READOUT_MS:g} ms (one frame "
                                  f"at 10 fps), got {self.rolling_shutter:g}")
        if self.pose_method not in POSE_METHODS:
            raise ReconInputError(f"pose method must be one of {', '.join(POSE_METHODS)}, got {self.pose_method!r}")
        if self.pose_options:
            from ..poses.options import check_pose_options

            check_pose_options(self.pose_options)
        self._validate_streaming()
        self.fusion.validate()

    def _validate_streaming(self) -> None:
        """The frame budget and the streamed run's choices of depth frames and windows."""
        if self.stream not in STREAM_CHOICES:
            raise ReconInputError(f"stream must be one of {', '.join(STREAM_CHOICES)}, got {self.stream!r}")
        if not (self.depth_frames in ("motion", "all") or (self.depth_frames.isdigit() and int(self.depth_frames) > 0)):
            raise ReconInputError(
                f"depth frames must be motion, all or a positive whole number, got {self.depth_frames!r}")
        if not (self.depth_motion > 0 and self.depth_rotation > 0):
            raise ReconInputError(f"depth motion and depth rotation must be > 0, got {self.depth_motion} and "
                                  f"{self.depth_rotation}")
        if int(self.window_overlap) < 0 or int(self.window) < int(self.window_overlap) + 2:
            raise ReconInputError(f"a window needs at least 2 frames beyond its overlap: window {self.window}, "
                                  f"overlap {self.window_overlap}")
        if int(self.mesh_every) < 0:
            raise ReconInputError(f"mesh every must be >= 0 fused frames (0: only at the end), got {self.mesh_every}")
        if int(self.frame_budget) < 2:
            raise ReconInputError(f"frame budget must be >= 2, got {self.frame_budget}")

    def _validate_prior(self) -> None:
        """The prior's choices and the cheap checks of its files (an "hf" model folder: that
        transformers is installed and the folder holds config.json; not yet that it loads)."""
        if self.prior not in PRIOR_CHOICES:
            raise ReconInputError(f"prior must be one of {', '.join(PRIOR_CHOICES)}, got {self.prior!r}")
        if self.prior == "folder" and self.prior_path is None:
            raise ReconInputError("prior 'folder' needs a folder of depth maps (--prior-path)")
        if self.prior == "hf":
            if self.prior_path is None:
                raise ReconInputError("prior 'hf' needs a local Hugging Face model folder (--prior-path MODEL_DIR)")
            from ..priors.hf import check_model_folder

            check_model_folder(self.prior_path)
        if self.prior_align not in PRIOR_ALIGN_CHOICES:
            raise ReconInputError(
                f"prior alignment must be one of {', '.join(PRIOR_ALIGN_CHOICES)}, got {self.prior_align!r}")

    def to_dict(self) -> dict:
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _plain(value):
    if is_dataclass(value):
        return asdict(value)
    if isinstance(value, Path):
        return str(value)
    return value


__all__ = ["PipelineConfig"]
