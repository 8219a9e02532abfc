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


# Share of a keyframe's view its Stage I partner must cover for the pair to be scored.
# why: docs/decisions.md#keyframe-pairs-that-overlap-little
MIN_KEYFRAME_OVERLAP = 0.5


def pipeline_medea() -> MedeaConfig:
    """MEDeA as `recon run` runs it: the fast preset (MedeaConfig.fast), with Stage I scoring
    only keyframe pairs that share at least MIN_KEYFRAME_OVERLAP of the view.

    Returns:
        A new MedeaConfig.
    """
    return MedeaConfig.fast(min_pair_overlap=MIN_KEYFRAME_OVERLAP)


@dataclass
class PipelineConfig:
    """Everything `recon run` can be told; defaults suit a phone video on a CPU.

    Each field's docstring is its one description: `recon run --help` is made from it
    (recon.commands.cli_args) and so is ``presets/defaults.yaml`` (recon.core.config_file).
    """

    input: Path
    """The video file, image folder or RGB-D dataset folder to reconstruct."""
    output: Path
    """The folder that receives the results (mesh, trajectory, depth maps, report.json)."""
    overwrite: bool = False
    """Write into a non-empty output folder, removing what an earlier run of recon wrote there."""
    stride: int | None = None
    """Use every k-th frame (none: 1, raised to stay within frame_budget when not streamed).

    Frame selection: recon.io.source.Selection.
    """
    max_frames: int | None = None
    """Use at most this many frames."""
    start_time: float | None = None
    """The first second of the video to use."""
    end_time: float | None = None
    """Stop at this second of the video."""
    frame_budget: int = 150
    """The most frames a one-shot run holds in memory, counted at 640x480 (150: about 3.2 GB).

    A frame of more pixels counts for more (recon.core.stages.budget_capacity); longer inputs
    are streamed (``stream``). why: docs/running.md#memory
    """
    stream: str = "auto"
    """Stream the frames through the stages in bounded memory: auto, on or off.

    auto streams inputs with more frames than frame_budget holds, and videos whose poses are
    estimated (recon.pipeline.stream_reason; depth for the frames the camera moved to reach; run
    again at once, where SfM can be tried, if the front end loses the camera). MEDeA then runs
    on overlapping windows and the mesh grows as it goes (recon.drivers.streamed). off gives
    every frame depth and raises the stride, when none is given, to fit the budget.
    """
    depth_frames: str = "motion"
    """Which tracked frames of a streamed run get depth and are fused: motion, all, or every K-th.

    motion: a frame each time the camera moved depth_motion x the median depth or turned
    depth_rotation degrees since the last one (at least depth_frames_min frames over the
    input); frames the pose front end had no pose for yet are chosen once it has.
    """
    depth_motion: float = 0.02
    """Streamed runs, depth_frames motion: the camera's movement that takes a frame, as a
    fraction of the median depth."""
    depth_rotation: float = 2.0
    """Streamed runs, depth_frames motion: the turn in degrees that takes a frame."""
    depth_frames_min: int = 30
    """Streamed runs, depth_frames motion: at least this many depth frames over the input (a
    frame is also taken count // depth_frames_min frames after the last one; 0: motion alone).

    A short or slow clip then still gives the refinement its source views.
    why: docs/decisions.md#depth-frames-of-a-streamed-run
    """
    window: int = 48
    """Frames per MEDeA window of a streamed run, counted at 640x480 like frame_budget.

    recon.core.stages.window_frames.
    """
    window_overlap: int = 8
    """Frames shared by consecutive windows of a streamed run."""
    mesh_every: int = 200
    """Re-extract the mesh for live Rerun every this many fused frames of a streamed run (0: only at the end)."""
    width: int | None = 640
    """The working width in pixels, aspect kept (none, or 0 on the command line: the input's own)."""
    fps: float | None = None
    """The frame rate of an image folder (none: 30), for start_time and end_time."""
    intrinsics: tuple[float, float, float, float] | None = None
    """Pinhole intrinsics fx, fy, cx, cy in pixels of the input as decoded (pixel centres at integers).

    Given intrinsics are used as given: no lens is estimated on top of them
    (``FrontendConfig.calibrate_lens``).
    """
    fov: float | None = None
    """The horizontal field of view in degrees, used when the intrinsics are not given."""
    distortion: tuple[float, ...] | None = None
    """The lens of the intrinsics or fov, OpenCV's k1, k2, p1, p2[, k3] (none: a dataset's
    published coefficients with its calibration, else none).

    The frames are resampled into the pinhole camera as they are decoded, before any other
    stage (recon.io.source.FrameSource.to_pinhole).
    """
    rolling_shutter: float = 0.0
    """The camera's rolling-shutter readout time in milliseconds (0: a global shutter; phones and webcams: 10-30).

    The frames are resampled to one instant each, with the angular velocity of the given
    poses or of a first estimate (then estimated again on the resampled frames, so such a
    video is not streamed by stream auto): recon.geometry.rolling_shutter. A streamed run
    resamples its depth frames with given poses and leaves the frames as recorded with
    estimated ones (it tracks only once).
    """
    poses: str = "auto"
    """Where the poses come from: auto (a dataset's ground truth, else estimated), gt,
    estimate, or a pose file or folder.

    Pose files: TUM, COLMAP, nerfstudio transforms.json, per-frame 4x4 matrices (7-Scenes,
    ScanNet), Open3D .log.
    """
    pose_method: str = "auto"
    """The pose estimator: auto, frontend or sfm."""
    pose_options: dict[str, Any] = field(default_factory=dict)
    """Settings of the pose estimators by name, e.g. {"keyframe_flow": 12.0}.

    The fields of ``recon.poses.config.FrontendConfig`` and
    ``recon.poses.sfm.mapper.SfMConfig``; ``recon run --pose-option list`` prints them.
    """
    on_break: str = "segments"
    """Where an estimated trajectory's scale breaks or the camera is lost: segments, stop or keep.

    segments: each stretch reconstructed on its own (``OUT/segment_NN/``, one summary);
    stop: the run stops with one line naming the frames (exit 2); keep: one trajectory, with
    a warning (recon.poses.checks.scale_watch). Whatever it is, a trajectory the front end's motion
    checks distrust as a whole (recon.poses.checks.motion_checks) is not returned, except under
    keep; nor is one whose metric scale the depth prior cannot vouch for (its depth does not
    follow the scene's, recon.poses.checks.prior_agreement), which keep returns with a warning.
    """
    join_segments: bool = True
    """Try to join the stretches on either side of a scale break before on_break applies.

    recon.poses.checks.join: the frames after it posed by PnP in the stretch before it, a
    similarity between the two; joined stretches are one trajectory again.
    """
    join_through_map: bool = True
    """Where join_segments finds nothing, join through one SfM model of views of both stretches.

    recon.poses.sfm.map_join: COLMAP registers each by PnP on the points of the others; needs
    pycolmap.
    """
    prior: str = "fastdepth"
    """The depth prior: fastdepth (the network), sensor (an RGB-D dataset's depth), folder or hf (prior_path).

    folder: prior_path holds one depth map per frame, matched by name; hf: prior_path is a
    local Hugging Face depth model folder (recon.priors.hf; needs transformers).
    """
    prior_path: Path | None = None
    """The prior's files: a folder of depth maps (prior folder) or a Hugging Face model folder (prior hf).

    Depth maps: .npy/.png/.exr/.tiff in metres (16-bit PNG in millimetres; 0, NaN and inf:
    no depth). A model folder: config.json, weights, preprocessor_config.json, as
    save_pretrained writes them; nothing is downloaded.
    """
    prior_align: str = "fastdepth"
    """What an hf model predicting affine-invariant disparity is fitted to per frame: fastdepth or sensor.

    Its kind is read from its config (recon.priors.hf.model_kind); metric models are used as
    they are.
    """
    weights: Path | None = None
    """The FastDepth weights (model.json, .npz or a folder; none: $RECON_WEIGHTS, then the packaged model)."""
    features: bool = True
    """Give MEDeA the prior's encoder features (the feature-metric loss)."""
    adjust: bool = True
    """Run MEDeA (false: fuse the raw depth prior)."""
    medea_gate: bool = False
    """Skip MEDeA, and refine from the prior's depth, when the given poses contradict the frames.

    Every run with given poses checks them (recon.poses.given.pose_check) and warns either way.
    why: docs/poses.md#given-poses
    """
    scale_prior: bool = True
    """With given poses, search one factor on the prior against them before MEDeA (``medea.scale_search``).

    Given poses carry their own scale (a tracker's metres, an SfM model's units), which the
    prior's need not match: an indoor network predicts a door handle 0.3 m away five times
    too far. Estimated poses take their scale from the prior, so nothing is searched then.
    why: docs/decisions.md#the-priors-scale-under-given-poses
    """
    medea: MedeaConfig = field(default_factory=pipeline_medea)
    """MEDeA's settings (medea_core.MedeaConfig; the fast preset, Stage I on overlapping pairs: pipeline_medea)."""
    refine: str = "mvs"
    """The multi-view stereo refinement after MEDeA: mvs, or none (MEDeA's depth, the paper's pipeline).

    mvs: per-pixel depth from the frames around MEDeA's depth, with a confidence; only the
    pixels it reconstructs are fused (mvs_core).
    """
    mvs: MvsConfig = field(default_factory=MvsConfig)
    """The refinement's settings (mvs_core.MvsConfig)."""
    polish: bool = False
    """Polish given poses against the frames before MEDeA when refining (one-shot runs; off: used as given).

    recon.poses.given.polish. why: docs/poses.md#given-poses
    """
    polish_config: PolishConfig = field(default_factory=PolishConfig)
    """The polish's settings (recon.poses.given.polish.PolishConfig)."""
    fusion: FusionOptions = field(default_factory=FusionOptions)
    """TSDF fusion's settings (recon.fusion.FusionOptions)."""
    rerun: str = "off"
    """Rerun inspection: spawn, save, serve or off."""
    rerun_path: Path | None = None
    """The .rrd file of rerun save (none: OUT/recording.rrd)."""
    rerun_max_width: int | None = 320
    """Images wider than this are logged to Rerun downscaled."""
    device: str = "cpu"
    """The torch device of prior, MEDeA and fusion: cpu, cuda or cuda:N."""
    progress: bool = True
    """Show progress bars."""
    depth_npy: bool = True
    """Also write float32 .npy depth maps beside the 16-bit PNGs."""
    glb: bool = True
    """Also write mesh.glb."""

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
        if self.depth_frames_min < 0:
            raise ReconInputError(f"depth_frames_min must be >= 0, got {self.depth_frames_min}")
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
