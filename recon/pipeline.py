"""The whole reconstruction, as named stages over one typed configuration.

This module owns the glue from an input (video, image folder, RGB-D dataset folder) to the
output folder: which stage runs when, what each stage hands to the next, the choice of
camera intrinsics and poses, per-stage timings and ``report.json``. The stages themselves
live elsewhere (readers in :mod:`recon.io`, priors in :mod:`recon.priors`, pose estimation
in :mod:`recon.poses`, MEDeA in :mod:`recon.medea`, fusion in :mod:`recon.fusion`, writers
in :mod:`recon.export`, Rerun logging in :mod:`viewer`).

Stages, in order (each timed in ``PipelineResult.seconds`` under its name):

``decode``   open the input, select and resize frames (stored at working resolution);
``prior``    per-frame metric depth (FastDepth by default; sensor depth; a depth folder);
``poses``    camera-to-world poses: a pose file, the dataset's ground truth, or estimated;
``medea``    MEDeA multi-view depth adjustment (skipped with ``adjust=False``);
``refine``   per-pixel multi-view stereo around MEDeA's depth, with a confidence per pixel
             (``refine="mvs"``, :mod:`recon.refine`; ``"none"`` keeps the paper's pipeline);
``fusion``   TSDF fusion of the final depth with colour (only the pixels the refinement
             reconstructed, when it ran), marching cubes, clean-up;
``export``   mesh.ply, mesh.glb, trajectory.txt, intrinsics.json, depth maps;
``logging``  the Rerun recording (frames, depths, cameras, trajectory, mesh, losses).

``report.json`` is written last: inputs, options, versions, timings, MEDeA loss summary.

Given poses (a dataset's ground truth, a pose file) are polished against the frames in the
``poses`` stage when the refinement runs (:mod:`recon.poses.polish`): multi-view stereo
needs the sub-pixel agreement that given poses rarely have for the colour camera.

Intrinsics, first that applies: ``intrinsics`` given (pixels of the input as decoded),
``fov`` given, the dataset's calibration, the pose file's, the pose estimator's estimate,
and finally a camera with NYU Depth v2's field of view (~63 degrees horizontal; a note is
printed). Poses ``"auto"``: a dataset's ground truth when it has one, else estimation.
"""

from __future__ import annotations

import logging
import math
import platform
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from medea_core import MedeaConfig

from .errors import ReconInputError
from .export import OutputFolder, atomic_path, export_reconstruction
from .export.writers import REPORT_JSON, frame_name
from .fusion import FusionOptions
from viewer.output_folder import RECORDING

from .io.frames import DatasetSource, FrameBatch, FrameSource, ImageFolderSource, open_source, resize_intrinsics
from .lens import undistort_features, undistort_images, worth_undistorting
from .poses.polish import PolishConfig
from .refine import REFINE_CHOICES, default_min_confidence, fusion_confidence, refine_summary
from mvs_core import MvsConfig

log = logging.getLogger(__name__)

STAGES = ("decode", "prior", "poses", "medea", "refine", "fusion", "export", "logging")
POSE_CHOICES = ("auto", "gt", "estimate")
PRIOR_CHOICES = ("fastdepth", "sensor", "folder")
RERUN_MODES = ("spawn", "save", "serve", "off")


@dataclass
class PipelineConfig:
    """Everything `recon run` can be told; defaults suit a phone video on a CPU.

    input, output: paths. overwrite: write into a non-empty output folder.
    stride, max_frames, start_time, end_time: frame selection (see recon.io.frames).
    frame_budget: when no stride is given and the input has more frames than this, the
        stride is raised so that at most this many are used (memory and time grow with
        the frame count; every stage needs all frames at once).
    width: working width in pixels (None: the input's own); fps: frame rate of an image folder.
    intrinsics: (fx, fy, cx, cy) in pixels of the input as decoded; fov: horizontal field
        of view in degrees (used when intrinsics are not given).
    poses: "auto", "gt" (dataset ground truth), "estimate", or a pose file / folder
        (TUM, COLMAP, nerfstudio, 7-Scenes/ScanNet matrices, Open3D .log).
    pose_method: estimator, "auto" | "frontend" | "sfm".
    pose_options: fields of the estimators' configs (``recon.poses.frontend.FrontendConfig``,
        ``recon.poses.sfm.SfMConfig``) to change, e.g. {"keyframe_flow": 12.0}.
    prior: "fastdepth", "sensor" (a dataset's depth) or "folder" (prior_path holds one
        depth map per frame, matched by name). weights: FastDepth weights location.
    features: give MEDeA FastDepth's encoder features (the feature-metric loss).
    adjust: run MEDeA (False fuses the raw prior). medea: MEDeA's configuration.
    refine: "mvs" (multi-view stereo refinement after MEDeA, mvs_core) or "none";
        mvs: its configuration (mvs_core.MvsConfig).
    polish: polish given poses against the frames before MEDeA when refining
        (recon.poses.polish); polish_config: its settings.
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
    frame_budget: int = 600
    width: int | None = 640
    fps: float | None = None
    intrinsics: tuple[float, float, float, float] | None = None
    fov: float | None = None
    poses: str = "auto"
    pose_method: str = "auto"
    pose_options: dict[str, Any] = field(default_factory=dict)
    prior: str = "fastdepth"
    prior_path: Path | None = None
    weights: Path | None = None
    features: bool = True
    adjust: bool = True
    medea: MedeaConfig = field(default_factory=MedeaConfig.fast)
    refine: str = "mvs"
    mvs: MvsConfig = field(default_factory=MvsConfig)
    polish: bool = True
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
        if self.prior not in PRIOR_CHOICES:
            raise ReconInputError(f"prior must be one of {', '.join(PRIOR_CHOICES)}, got {self.prior!r}")
        if self.prior == "folder" and self.prior_path is None:
            raise ReconInputError("prior 'folder' needs a folder of depth maps (--prior-path)")
        if self.refine not in REFINE_CHOICES:
            raise ReconInputError(f"refine must be one of {', '.join(REFINE_CHOICES)}, got {self.refine!r}")
        try:
            self.mvs.validate()
        except ValueError as error:
            raise ReconInputError(str(error)) from None
        if self.rerun not in RERUN_MODES:
            raise ReconInputError(f"rerun mode must be one of {', '.join(RERUN_MODES)}, got {self.rerun!r}")
        if self.fov is not None and not (0 < self.fov < 180):
            raise ReconInputError(f"field of view must be between 0 and 180 degrees, got {self.fov}")
        if self.intrinsics is not None:
            k = np.asarray(self.intrinsics, dtype=np.float64)
            if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
                raise ReconInputError(f"intrinsics must be four numbers fx,fy,cx,cy with fx, fy > 0, got {self.intrinsics}")
        if self.pose_options:
            from .poses import check_pose_options

            check_pose_options(self.pose_options)
        if int(self.frame_budget) < 2:
            raise ReconInputError(f"frame budget must be >= 2, got {self.frame_budget}")
        self.fusion.validate()

    def to_dict(self) -> dict:
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _plain(value):
    if is_dataclass(value):
        return asdict(value)
    if isinstance(value, Path):
        return str(value)
    return value


@dataclass
class PipelineResult:
    """What a run produced (everything also on disk in ``output``).

    frames: the selected frames at working size; prior_depth, depth: (N, H, W) metres
    (depth is the final depth: refined, else MEDeA-adjusted, else the prior);
    adjusted_depth: MEDeA's (the prior when adjust=False); poses (N, 4, 4) camera-to-world;
    intrinsics (fx, fy, cx, cy) at working size; fusion: FusionResult; medea: MedeaResult
    or None; refined: mvs_core.RefineResult or None; seconds: {stage: wall seconds};
    files: {label: path}; report: what report.json holds.
    """

    output: Path
    frames: FrameBatch
    prior_depth: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    fusion: object
    medea: object
    seconds: dict[str, float]
    files: dict[str, Path]
    report: dict
    rerun_url: str | None = None
    adjusted_depth: np.ndarray | None = None
    refined: object = None

    @property
    def seconds_per_frame(self) -> dict[str, float]:
        n = max(1, len(self.frames))
        return {stage: s / n for stage, s in self.seconds.items()}


# --------------------------------------------------------------------------- stages


def select_frames(config: PipelineConfig) -> FrameSource:
    """Open the input with the selection, raising the stride when over the frame budget."""
    def open_with(stride):
        return open_source(
            config.input, stride=stride, max_frames=config.max_frames, start_time=config.start_time,
            end_time=config.end_time, width=config.width, min_frames=2, fps=config.fps,
        )

    source = open_with(1 if config.stride is None else config.stride)
    if config.stride is None and config.max_frames is None and source.count > config.frame_budget:
        stride = math.ceil(source.count / config.frame_budget)
        print(f"note: {source.count} frames exceed the frame budget of {config.frame_budget}; using every "
              f"{stride}th frame (set --stride or --max-frames to choose)", file=sys.stderr)
        source = open_with(stride)
    return source


def decode(source: FrameSource, progress: bool = True) -> FrameBatch:
    """All selected frames at working size (decoded one at a time, stored small)."""
    from tqdm.auto import tqdm

    indices, times, images = [], [], []
    total = source.count if source.count > 0 else None
    for frame in tqdm(source, total=total, desc="decode", unit="frame", disable=not progress, leave=False):
        indices.append(frame.index)
        times.append(frame.timestamp)
        images.append(frame.rgb)
    if len(images) < 2:
        raise ReconInputError(f"{source.path}: needs at least 2 frames, got {len(images)} ({source.selection.describe()})")
    return FrameBatch(np.asarray(indices, np.int64), np.asarray(times, np.float64), np.stack(images))


def frame_names(source: FrameSource, frames: FrameBatch) -> list[str]:
    """Per-frame names used for depth files (and to match a depth-folder prior)."""
    if isinstance(source, ImageFolderSource):
        return [source.files[i].stem for i in frames.indices]
    if isinstance(source, DatasetSource):
        return [Path(p).stem for p in source.dataset.rgb_paths]
    return [frame_name(i) for i in frames.indices]


def fov_intrinsics(fov_degrees: float, width: int, height: int) -> tuple[float, float, float, float]:
    """Square-pixel intrinsics with horizontal field of view `fov_degrees`, centred."""
    f = (width / 2.0) / math.tan(math.radians(fov_degrees) / 2.0)
    return (f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def given_intrinsics(config: PipelineConfig, source: FrameSource) -> tuple[tuple | None, str]:
    """Intrinsics at working size known before poses: (values or None, where they came from)."""
    w, h = source.size
    if config.intrinsics is not None:
        return resize_intrinsics(config.intrinsics, source.native_size, source.size), "given"
    if config.fov is not None:
        return fov_intrinsics(config.fov, w, h), f"fov {config.fov:g} deg"
    if source.intrinsics is not None:
        return tuple(source.intrinsics), "dataset calibration"
    return None, "unknown"


def default_intrinsics(width: int, height: int) -> tuple[float, float, float, float]:
    """The fallback camera: NYU Depth v2's field of view (what FastDepth was trained on)."""
    from .priors.fastdepth import assumed_intrinsics

    fx, fy, _, _ = assumed_intrinsics(height, width)
    return (float(fx), float(fy), (width - 1) / 2.0, (height - 1) / 2.0)


def depth_prior(config: PipelineConfig, source: FrameSource, frames: FrameBatch, names: list[str], intrinsics):
    """PriorOutput for the frames: depth (N, H, W) metres at working size, optional features."""
    from .priors import make_prior

    common = dict(device=config.device, progress=config.progress)
    if config.prior == "fastdepth":
        prior = make_prior("fastdepth", weights=config.weights, features=config.features and config.adjust, **common)
    elif config.prior == "sensor":
        depth = source.load_depth() if isinstance(source, DatasetSource) else None
        if depth is None:
            raise ReconInputError(f"{config.input}: --prior sensor needs an RGB-D dataset folder with depth")
        prior = make_prior("sensor", depth=depth, source=str(config.input), **common)
    else:
        prior = make_prior("folder", path=config.prior_path, frame_names=names, **common)
    output = prior(frames.rgb, intrinsics)
    if output.kind != "metric":
        raise ReconInputError(f"depth prior {config.prior} gave {output.kind} depth; the pipeline needs metric depth")
    return output


def _matched_pose_file(data, source: FrameSource, frames: FrameBatch):
    """(poses (N, 4, 4), intrinsics at working size or None) of a read pose file (PoseData),
    matched to the frames.

    Matching: by frame name when the file names frames (COLMAP, nerfstudio, matrices),
    else by source frame index when the file has one pose per input frame, else by
    position when it has one per selected frame, else by timestamp (TUM).
    """
    from .poses.formats import interpolate_poses

    path = data.path
    n_total = {ImageFolderSource: lambda s: len(s.files), DatasetSource: lambda s: len(s.full)}.get(
        type(source), lambda s: getattr(s, "frame_count_meta", 0))(source)
    poses = None
    if data.names is not None:
        lookup = {Path(str(n)).stem: k for k, n in enumerate(data.names)}
        keys = frame_names(source, frames)
        if all(k in lookup for k in keys):
            poses = data.poses[[lookup[k] for k in keys]]
    if poses is None and len(data) == n_total and frames.indices.max() < len(data):
        poses = data.poses[frames.indices]
    if poses is None and len(data) == len(frames):
        poses = data.poses
    if poses is None and data.timestamps is not None:
        stamps = frames.timestamps + (data.timestamps.min() if data.timestamps.min() > 1e6 else 0.0)
        poses, valid = interpolate_poses(stamps, data.timestamps, data.poses)
        if not valid.all():
            raise ReconInputError(
                f"{path}: no pose near the timestamp of frame {int(frames.indices[np.argmin(valid)])} "
                f"({len(data)} poses for {len(frames)} frames)"
            )
    if poses is None:
        raise ReconInputError(
            f"{path}: {len(data)} poses cannot be matched to the {len(frames)} selected frames "
            f"(need one per input frame, one per selected frame, frame names or timestamps)"
        )
    bad = ~np.isfinite(poses).all(axis=(1, 2))
    if bad.any():
        raise ReconInputError(f"{path}: invalid pose for frame {int(frames.indices[np.argmax(bad)])}")
    intrinsics = None
    if data.intrinsics is not None and data.intrinsics.get("width"):
        k = data.intrinsics
        native = (int(k["width"]), int(k["height"]))
        intrinsics = resize_intrinsics((k["fx"], k["fy"], k["cx"], k["cy"]), native, source.size)
    return poses, intrinsics


@dataclass
class PoseStage:
    poses: np.ndarray
    intrinsics: tuple | None
    source: str
    info: dict = field(default_factory=dict)
    keep: np.ndarray | None = None  # frames kept (ground truth may lack poses for some)
    lens_k1: float = 0.0  # radial term the poses were estimated with (recon.lens)
    dropped_note: str = ""  # why frames were left out, said once when keep is set


def plan_poses(config: PipelineConfig, source: FrameSource):
    """Where poses will come from, checked before any heavy work: "gt", "estimate" or the
    read pose file (PoseData). Raises ReconInputError when that source cannot work."""
    from .poses.formats import read_poses

    choice = config.poses
    has_gt = isinstance(source, DatasetSource) and source.poses is not None
    if choice == "auto":
        choice = "gt" if has_gt else "estimate"
    if choice == "gt" and not has_gt:
        raise ReconInputError(f"{config.input}: --poses gt needs a dataset folder with ground-truth poses")
    if choice == "estimate":
        _pose_estimator()
    return choice if choice in ("gt", "estimate") else read_poses(Path(choice))


def _pose_estimator():
    try:
        from .poses import estimate_poses
    except ImportError:
        raise ReconInputError(
            "pose estimation not available; pass --poses FILE or a dataset with ground-truth poses"
        ) from None
    return estimate_poses


def camera_poses(config: PipelineConfig, plan, source: FrameSource, frames: FrameBatch, prior_depth, intrinsics) -> PoseStage:
    """Poses of the selected frames from the planned source (see plan_poses)."""
    if plan == "gt":
        valid = np.isfinite(source.poses).all(axis=(1, 2))
        if valid.sum() < 2:
            raise ReconInputError(f"{config.input}: fewer than 2 selected frames have a ground-truth pose")
        return PoseStage(source.poses, None, "dataset ground truth", keep=None if valid.all() else np.flatnonzero(valid),
                         dropped_note=f"{len(valid) - valid.sum()} frames have no ground-truth pose and are left out")
    if plan == "estimate":
        return estimated_poses(config, frames, prior_depth, intrinsics)
    poses, file_intrinsics = _matched_pose_file(plan, source, frames)
    return PoseStage(poses, file_intrinsics, f"file {plan.path}")


def estimated_poses(config: PipelineConfig, frames: FrameBatch, prior_depth, intrinsics) -> PoseStage:
    """Poses estimated from the frames, through the quality gate (recon.poses.quality):
    frames whose pose the images do not back are left out, named in report.json."""
    from .poses.quality import gate_trajectory

    result = _pose_estimator()(
        frames.rgb, prior_depth, intrinsics=intrinsics, method=config.pose_method, device=config.device,
        progress=config.progress, **config.pose_options,
    )
    gate = gate_trajectory(result)
    info = {"keyframes": len(result.keyframes), "seconds": result.seconds,
            "diagnostics": {k: v for k, v in result.diagnostics.items() if np.ndim(v) == 0 or len(v) < 50},
            "frame_status": list(result.diagnostics.get("frame_status", [])),
            "quality": gate.summary([int(i) for i in frames.indices])}
    keep, note = None, ""
    if gate.dropped:
        keep = np.flatnonzero(gate.keep)
        spans = ", ".join(f"{a}-{b}" if a != b else f"{a}" for a, b in info["quality"]["dropped_ranges"][:5])
        note = (f"{len(gate.dropped)} of {len(frames)} frames have no pose the images back "
                f"(video frames {spans}) and are left out of depth and fusion (report.json: poses.quality)")
    return PoseStage(np.asarray(result.poses, np.float64), tuple(result.intrinsics), "estimated", info, keep=keep,
                     lens_k1=float(result.diagnostics.get("lens_k1", 0.0)), dropped_note=note)


def tracking_states(stage: PoseStage, frames: FrameBatch) -> list[tuple[int, str, np.ndarray]] | None:
    """[(video frame, tracking state, camera-to-world pose)] of every frame of an estimate,
    "dropped: <why>" for those the quality gate left out; None for given poses."""
    status = stage.info.get("frame_status")
    if not status:
        return None
    why = {d["frame"]: d["reason"] for d in stage.info.get("quality", {}).get("dropped_frames", [])}
    return [(int(i), f"dropped: {why[int(i)]}" if int(i) in why else state, stage.poses[k])
            for k, (i, state) in enumerate(zip(frames.indices, status))]


def adjust_depth(config: PipelineConfig, frames: FrameBatch, prior, poses, intrinsics):
    """MEDeA on the sequence: (adjusted depth (N, H, W) float32, MedeaResult)."""
    from .medea import adjust_sequence

    features = prior.features if config.features else None
    result = adjust_sequence(frames.rgb, prior.depth, poses, intrinsics, features, config.medea, config.progress)
    return result.depth.numpy().astype(np.float32, copy=False), result


def polished_poses(config: PipelineConfig, stage: PoseStage, frames: FrameBatch, prior_depth, intrinsics) -> PoseStage:
    """The given poses polished against the frames (recon.poses.polish), the lens with them."""
    from .poses.polish import polish_poses

    result = polish_poses(frames.rgb, prior_depth, stage.poses, intrinsics, config.polish_config, config.progress)
    info = {**stage.info, "polish": result.info}
    source = f"{stage.source}, polished against the frames" if result.info.get("polished") else stage.source
    return replace(stage, poses=result.poses, source=source, info=info, lens_k1=result.lens_k1)


def refine_stage(config: PipelineConfig, frames: FrameBatch, depth, poses, intrinsics):
    """Multi-view stereo refinement of the adjusted depth: mvs_core.RefineResult."""
    from .refine import refine_sequence

    mvs = replace(config.mvs, device=config.device)
    return refine_sequence(frames.rgb, depth, poses, intrinsics, mvs, config.progress)


def medea_summary(result) -> dict:
    """Per stage: epochs run, whether it stopped early, first and last epoch losses."""
    if result is None:
        return {}
    out = {"keyframes": int(len(result.keyframes)), "seconds": dict(result.seconds), "stages": {}}
    for name, history in result.history.items():
        losses = {term: [float(v) for v in values] for term, values in history.losses.items()}
        out["stages"][name] = {
            "epochs": int(history.epochs),
            "stopped_early": bool(history.stopped_early),
            "first": {t: v[0] for t, v in losses.items() if v},
            "last": {t: v[-1] for t, v in losses.items() if v},
        }
    return out


def log_to_rerun(logger, frames: FrameBatch, prior_depth, depth, poses, intrinsics, mesh, medea_result, progress=True,
                 refined=None, tracking=None):
    """Every frame (RGB, prior, adjusted and refined depth, confidence, camera, trajectory),
    the mesh, the losses. depth: MEDeA's (or the prior when MEDeA was skipped); refined:
    the refinement's RefineResult or None; tracking: [(video frame, state, pose)] of every
    selected frame, dropped ones included (see tracking_states), or None."""
    from tqdm.auto import tqdm

    for index, state, pose in tracking or []:
        logger.log_tracking(index, state, pose)
    for k in tqdm(range(len(frames)), desc="rerun logging", unit="frame", disable=not progress, leave=False):
        extra = {} if refined is None else {"refined_depth": refined.depth[k].numpy(),
                                            "confidence": refined.confidence[k].numpy()}
        logger.log_frame(int(frames.indices[k]), frames.rgb[k], prior_depth[k], depth[k], poses[k], intrinsics,
                         timestamp=float(frames.timestamps[k]), **extra)
    if mesh is not None and len(mesh.triangles):
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colors)
    if medea_result is not None:
        logger.log_losses(medea_result.history)


def versions() -> dict:
    import open3d
    import rerun
    import torch

    from . import __version__

    return {"recon": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "torch": torch.__version__, "open3d": open3d.__version__, "rerun": rerun.__version__}


# --------------------------------------------------------------------------- driver


class _Timer:
    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start


def run_pipeline(config: PipelineConfig, on_stage: Callable[[str], None] | None = None) -> PipelineResult:
    """Run every stage (module docstring) and write the output folder; returns what was made.

    The input is opened and the output folder checked before any heavy work, so bad input
    or a non-empty output folder fail at once, with nothing written. An output folder this
    run created is removed again if the run fails before writing anything into it.
    """
    created = not Path(config.output).exists()
    try:
        return _run_stages(config, on_stage)
    except BaseException:
        if created and Path(config.output).is_dir():
            _remove_if_empty(Path(config.output))
        raise


def _remove_if_empty(folder: Path) -> None:
    """rmdir `folder` and its empty subfolders; anything holding a file stays."""
    for sub in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(sub.iterdir()):
            sub.rmdir()
    if not any(folder.iterdir()):
        folder.rmdir()


def _run_stages(config: PipelineConfig, on_stage) -> PipelineResult:
    from .fusion import fuse

    config.validate()
    say = on_stage or (lambda _: None)
    timer = _Timer()
    with timer.stage("decode"):
        source = select_frames(config)
        out = OutputFolder(config.output, config.overwrite)
        pose_plan = plan_poses(config, source)

    say(f"input: {source.description}")
    with timer.stage("decode"):
        frames = decode(source, config.progress)
    names = frame_names(source, frames)
    intrinsics, intrinsics_from = given_intrinsics(config, source)

    say(f"depth prior: {config.prior}")
    with timer.stage("prior"):
        prior = depth_prior(config, source, frames, names, intrinsics)

    say(f"poses: {config.poses}")
    with timer.stage("poses"):
        pose_stage = camera_poses(config, pose_plan, source, frames, prior.depth, intrinsics)
    poses, prior_depth, features = pose_stage.poses, prior.depth, prior.features
    tracking = tracking_states(pose_stage, frames)
    if pose_stage.keep is not None:
        log.warning(pose_stage.dropped_note)
        keep = pose_stage.keep
        frames = FrameBatch(frames.indices[keep], frames.timestamps[keep], frames.rgb[keep])
        names = [names[k] for k in keep]
        poses, prior_depth = poses[keep], prior_depth[keep]
        features = None if features is None else features[keep]
        prior.depth, prior.features = prior_depth, features
    if intrinsics is None and pose_stage.intrinsics is not None:
        intrinsics, intrinsics_from = pose_stage.intrinsics, f"poses ({pose_stage.source})"
    if intrinsics is None:
        w, h = source.size
        intrinsics, intrinsics_from = default_intrinsics(w, h), "assumed (NYU field of view)"
        print("note: camera intrinsics unknown; assuming NYU Depth v2's field of view "
              "(pass --intrinsics or --fov for a better mesh)", file=sys.stderr)
    intrinsics = tuple(float(v) for v in intrinsics)
    estimated = isinstance(pose_plan, str) and pose_plan == "estimate"
    if not estimated and config.refine != "none" and config.polish:
        say("polishing the given poses against the frames")
        with timer.stage("poses"):
            pose_stage = polished_poses(config, pose_stage, frames, prior_depth, intrinsics)
        poses = pose_stage.poses
    undistorted = worth_undistorting(intrinsics, source.size, pose_stage.lens_k1)
    if undistorted:
        # The poses belong to the pinhole camera of the estimated lens: so must the images.
        k1 = pose_stage.lens_k1
        say(f"undistorting frames and prior (lens k1 {k1:+.4f})")
        with timer.stage("poses"):
            frames = FrameBatch(frames.indices, frames.timestamps, undistort_images(frames.rgb, intrinsics, k1))
            prior_depth = undistort_images(prior_depth, intrinsics, k1, nearest=True)
            if features is not None:
                features = undistort_features(features, intrinsics, source.size, k1)
            prior.depth, prior.features = prior_depth, features

    medea_result = None
    if config.adjust:
        say("MEDeA depth adjustment")
        with timer.stage("medea"):
            depth, medea_result = adjust_depth(config, frames, prior, poses, intrinsics)
    else:
        depth = prior_depth
        timer.seconds["medea"] = 0.0
    adjusted = depth

    refined = None
    if config.refine == "mvs":
        say("multi-view stereo refinement")
        with timer.stage("refine"):
            refined = refine_stage(config, frames, depth, poses, intrinsics)
        depth = refined.depth.numpy()
        unsupported = np.flatnonzero(refined.unsupported.numpy())
        if len(unsupported):
            log.warning("the refinement reconstructed less than %.0f%% of the pixels of %d of %d frames (first: frame "
                        "%d): the frames do not confirm their depth (too little parallax or texture), so their MEDeA "
                        "depth is fused whole", 100 * config.mvs.min_frame_share, len(unsupported), len(frames),
                        int(frames.indices[unsupported[0]]))
    else:
        timer.seconds["refine"] = 0.0

    say("TSDF fusion")
    fusion_options = FusionOptions(**{**asdict(config.fusion), "device": config.device, "progress": config.progress})
    with timer.stage("fusion"):
        confidence = None if refined is None else fusion_confidence(refined)
        if fusion_options.min_confidence is None:
            fusion_options.min_confidence = default_min_confidence(estimated)
        fused = fuse(depth, frames.rgb, poses, intrinsics, fusion_options, confidence=confidence)

    if fused.mesh.has_vertex_colors():  # TSDF colour averages can overshoot 1 by rounding
        fused.mesh.vertex_colors = type(fused.mesh.vertex_colors)(np.clip(np.asarray(fused.mesh.vertex_colors), 0, 1))
    say("export")
    with timer.stage("export"):
        files = export_reconstruction(
            out, mesh=fused.mesh, poses=poses, timestamps=frames.timestamps, intrinsics=intrinsics,
            size=source.size, depth=depth, frame_names=names, point_cloud=fused.point_cloud, glb=config.glb,
            depth_npy=config.depth_npy,
        )

    rerun_url = None
    with timer.stage("logging"):
        if config.rerun != "off":
            say(f"rerun: {config.rerun}")
            rerun_url, rec_path = _log_recording(config, out, frames, prior_depth, adjusted, poses, intrinsics,
                                                 fused.mesh, medea_result, refined, tracking)
            if rec_path is not None:
                files["recording"] = rec_path

    mesh = fused.mesh
    report = {
        "input": {"path": str(config.input), "kind": source.kind, "description": source.description,
                  "native_size": list(source.native_size), "fps": source.fps},
        "frames": {"count": len(frames), "indices": frames.indices.tolist(), "names": names,
                   "working_size": list(source.size)},
        "intrinsics": {"values": list(intrinsics), "source": intrinsics_from},
        "poses": {"source": pose_stage.source, **pose_stage.info, "lens_k1": pose_stage.lens_k1,
                  "frames_undistorted": undistorted},
        "prior": {"name": config.prior, "kind": prior.kind, "info": prior.info,
                  "features": None if features is None else list(features.shape[1:])},
        "medea": medea_summary(medea_result),
        "refine": {"method": config.refine, **refine_summary(refined)},
        "fusion": {"min_confidence": fusion_options.min_confidence if refined is not None else None,
                   "voxel_size": fused.voxel_size, "trunc": fused.trunc, "max_depth": fused.max_depth,
                   "frames_fused": fused.frames_fused, "block_estimate": fused.block_estimate,
                   "blocks_used": fused.blocks_used, "fragments_removed": fused.fragments_removed,
                   "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)},
        "options": config.to_dict(),
        "versions": versions(),
        "seconds": dict(timer.seconds),
        "seconds_per_frame": {k: v / len(frames) for k, v in timer.seconds.items()},
        "files": {k: str(Path(v).relative_to(out.path)) for k, v in files.items()},
    }
    files["report"] = out.write_json(REPORT_JSON, report)
    return PipelineResult(
        output=out.path, frames=frames, prior_depth=prior_depth, depth=depth, poses=poses, intrinsics=intrinsics,
        fusion=fused, medea=medea_result, seconds=dict(timer.seconds), files=files, report=report, rerun_url=rerun_url,
        adjusted_depth=adjusted, refined=refined,
    )


def _log_recording(config, out: OutputFolder, frames, prior_depth, depth, poses, intrinsics, mesh, medea_result,
                   refined=None, tracking=None):
    """Log to Rerun in the configured mode: (server URL or None, .rrd path or None).

    A saved recording goes to a temporary name first, like every other output file.
    """
    from viewer import RerunLogger

    def log(logger):
        log_to_rerun(logger, frames, prior_depth, depth, poses, intrinsics, mesh, medea_result, config.progress,
                     refined, tracking)

    if config.rerun == "save":
        if config.rerun_path is None:
            with out.atomic(RECORDING) as tmp:
                with RerunLogger("save", tmp, max_width=config.rerun_max_width) as logger:
                    log(logger)
            return None, out.path_for(RECORDING)
        with atomic_path(config.rerun_path, overwrite=config.overwrite) as tmp:
            with RerunLogger("save", tmp, max_width=config.rerun_max_width) as logger:
                log(logger)
        return None, Path(config.rerun_path)
    logger = RerunLogger(config.rerun, max_width=config.rerun_max_width)
    log(logger)
    logger.close()
    return logger.url, None


def format_summary(result: PipelineResult) -> str:
    """The closing summary `recon run` prints: frames, time per stage, mesh, files."""
    n = len(result.frames)
    total = sum(result.seconds.values())
    lines = [f"{'stage':<10}{'seconds':>10}{'s/frame':>10}"]
    for stage in STAGES:
        if stage in result.seconds:
            s = result.seconds[stage]
            lines.append(f"{stage:<10}{s:>10.1f}{s / n:>10.3f}")
    lines.append(f"{'total':<10}{total:>10.1f}{total / n:>10.3f}")
    mesh = result.fusion.mesh
    h, w = result.depth.shape[1:]
    lines.append(
        f"{n} frames at {w}x{h}; mesh {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles "
        f"(voxel {result.fusion.voxel_size * 1000:.1f} mm)"
    )
    lines.append(f"output: {result.output}")
    for label, path in result.files.items():
        lines.append(f"  {label:<12}{path}")
    if result.rerun_url:
        lines.append(f"rerun: {result.rerun_url}")
    return "\n".join(lines)


__all__ = [
    "PipelineConfig",
    "PipelineResult",
    "RECORDING",
    "STAGES",
    "adjust_depth",
    "camera_poses",
    "decode",
    "default_intrinsics",
    "depth_prior",
    "format_summary",
    "fov_intrinsics",
    "given_intrinsics",
    "log_to_rerun",
    "medea_summary",
    "plan_poses",
    "run_pipeline",
    "select_frames",
]
