"""The streamed pipeline: a long video flows through the stages in memory that does not grow
with its length.

Two passes, as in DROID-SLAM (tracking front end, then the backend's global optimisation
before the dense map is trusted):

``track``  frames are decoded in order, given their prior in small batches and tracked one
           at a time (the streaming front end, :class:`recon.poses.frontend.StreamingFrontend`,
           or the given poses); each frame goes to a :class:`~recon.io.frame_store.FrameStore`
           on disk, and the frames that will get depth, chosen by motion as they come
           (:class:`recon.stream_plan.MotionSelector`), with their prior and features. The
           viewer shows each frame, its camera and the trajectory as it is tracked. At the
           end the estimate is closed (global BA, non-keyframes, metric scale) and passes
           the quality gate, exactly as in the one-shot run.
``depth``  the depth frames, in overlapping windows (:func:`recon.stream_plan.plan_windows`),
           each window a :class:`~recon.sequence.Sequence` read back from the store: MEDeA
           (the paper's pairs inside the window), anchored to the scale of the surface
           already fused where the window's cameras see it (else to the frames the previous
           window finished: :func:`_anchor`), then the refinement of its new frames (the
           shared ones are source views only, with the sweep the window before left them);
           each finished frame's depth is written to disk, integrated into one TSDF volume
           (:class:`~recon.fusion.TsdfVolume`) and logged, and the mesh is re-extracted for
           the viewer every ``mesh_every`` frames.

What stays in memory: poses and a few numbers per frame, the front end's keyframes, one
window of frames, the TSDF volume (the size of the scene, not of the video). Depth waits
for the trajectory to be closed because fusing frames at poses the global BA later moves
would bend the mesh.
"""

from __future__ import annotations

import logging
import time
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .config import PipelineConfig
from .errors import ReconInputError
from .io.frame_store import FrameStore
from .io.output_folder import DEPTH_DIR, RECORDING, REPORT_JSON, OutputFolder, atomic_path
from .io.pose_matching import frame_names, match_pose_file
from .io.source import FrameSource
from .lens import worth_undistorting
from .sequence import Sequence
from .stages import PosePlan, default_intrinsics, gate_estimate, ground_truth_kept, prior_function
from .stream_plan import MotionSelector, anchor_factor, anchor_pixels, parse_depth_frames, plan_windows

log = logging.getLogger(__name__)

# Share of a window's pixels the fused surface must cover to anchor the window's scale.
SURFACE_ANCHOR_MIN_COVER = 0.02
# Frames of a window, spread over it, into which the fused surface is rendered for the
# anchor: 8 at half size gave the factors of all 48 within 0.003 on 7-Scenes, and each ray
# cast costs ~0.1 s on 2 cores (rendering every frame made fusion 2x slower).
SURFACE_ANCHOR_VIEWS = 8

# Frames given their prior at once (FastDepth runs faster on a batch than frame by frame).
PRIOR_BATCH = 8
# Depth values kept per depth frame (a pixel lattice) to size the TSDF volume, and in all.
_SAMPLE_STEP = 16
_SAMPLE_MAX = 400_000


@dataclass
class TrackedVideo:
    """What the tracking pass leaves: per frame (position in the selection) its source
    index, timestamp, name, camera-to-world pose (NaN when it has none) and whether it got
    depth; the camera; the lens term; the pose report; a sample of prior depth values."""

    indices: np.ndarray
    timestamps: np.ndarray
    names: list[str]
    poses: np.ndarray
    depth_frame: np.ndarray
    intrinsics: tuple[float, float, float, float]
    intrinsics_from: str
    size: tuple[int, int]
    lens_k1: float = 0.0
    pose_source: str = ""
    pose_info: dict = field(default_factory=dict)
    depth_sample: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    prior_info: dict = field(default_factory=dict)
    feature_shape: list | None = None


@dataclass
class StreamResult:
    """What a streamed run produced (everything also on disk in ``output``): the counts, the
    trajectory of the tracked frames, the fusion figures, seconds per stage, files, report."""

    output: Path
    frames_tracked: int
    depth_frames: int
    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    fusion: object
    seconds: dict[str, float]
    files: dict[str, Path]
    report: dict
    rerun_url: str | None = None

    @property
    def seconds_per_frame(self) -> dict[str, float]:
        n = max(1, self.frames_tracked)
        return {stage: s / n for stage, s in self.seconds.items()}


class StageClock:
    """Wall seconds per stage name, summed over the many blocks of a streamed run."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start


# --------------------------------------------------------------------------- entry point


def run_streamed(config: PipelineConfig, source: FrameSource, out: OutputFolder, pose_plan: PosePlan,
                 given: tuple[tuple | None, str], say: Callable[[str], None]) -> StreamResult:
    """Both passes (module docstring) into ``out``; given: (intrinsics or None, their source)."""
    clock = StageClock()
    with ExitStack() as stack:
        store = stack.enter_context(FrameStore())
        logger, rec_path = _open_logger(config, out, stack)
        say("tracking (streamed)")
        video = track_video(config, source, pose_plan, given, store, logger, clock)
        say(f"depth: {int(video.depth_frame.sum())} of {len(video.indices)} frames in windows of {config.window}")
        volume, windows = depth_windows(config, video, pose_plan, store, out, logger, clock)
        say("export")
        result = _finish(config, source, out, video, volume, windows, clock, logger, store.bytes_written)
        url = logger.url if logger is not None else None
    if rec_path is not None:
        result.files["recording"] = rec_path
    result.rerun_url = url
    result.files["report"] = out.write_json(REPORT_JSON, _with_files(result.report, result.files, out))
    return result


def _open_logger(config: PipelineConfig, out: OutputFolder, stack: ExitStack):
    """(RerunLogger or None, final .rrd path or None); a saved recording is written under a
    temporary name and renamed when the run ends well."""
    if config.rerun == "off":
        return None, None
    from viewer import RerunLogger

    if config.rerun == "save":
        final = out.path_for(RECORDING) if config.rerun_path is None else Path(config.rerun_path)
        tmp = stack.enter_context(out.atomic(RECORDING) if config.rerun_path is None
                                  else atomic_path(config.rerun_path, overwrite=config.overwrite))
        logger = stack.enter_context(RerunLogger("save", tmp, max_width=config.rerun_max_width))
        return logger, final
    logger = RerunLogger(config.rerun, max_width=config.rerun_max_width)
    stack.callback(logger.close)
    return logger, None


# --------------------------------------------------------------------------- pass 1: track


def track_video(config: PipelineConfig, source: FrameSource, plan: PosePlan, given, store: FrameStore, logger,
                clock: StageClock) -> TrackedVideo:
    """Decode, prior, track (module docstring); every frame parked in ``store``."""
    from tqdm.auto import tqdm

    loop = _TrackLoop(config, source, plan, given, store, logger, clock)
    total = source.count if source.count > 0 else None
    with tqdm(total=total, desc="tracking", unit="frame", disable=not config.progress) as bar:
        for batch in _batches(source, clock):
            loop.add(batch)
            bar.update(len(batch))
    return loop.close()


def _median_depth(depth: np.ndarray) -> float:
    valid = depth[depth > 0]
    return float(np.median(valid)) if valid.size else 0.0


class _TrackLoop:
    """The tracking pass's state: per-frame records (small), the poser, the depth-frame rule."""

    def __init__(self, config: PipelineConfig, source: FrameSource, plan: PosePlan, given, store: FrameStore,
                 logger, clock: StageClock):
        self.config, self.source, self.store, self.logger, self.clock = config, source, store, logger, clock
        self.intrinsics, self.intrinsics_from = given
        self.prior = prior_function(source, config.prior, path=config.prior_path, weights=config.weights,
                                    features=config.features and config.adjust, align=config.prior_align,
                                    device=config.device, progress=False)
        self.poser = _Poser(config, source, plan, self.intrinsics, store)
        if not plan.estimated and config.refine != "none" and config.polish:
            log.warning("streamed runs do not polish given poses against the frames (that needs every frame at "
                        "once); the refinement uses the poses as given")
        self.select = MotionSelector(config.depth_motion, config.depth_rotation,
                                     parse_depth_frames(config.depth_frames))
        self.names_of = _frame_namer(source)
        self.indices, self.stamps, self.names, self.live, self.chosen, self.sample = [], [], [], [], [], []
        self.prior_info, self.feature_shape = {}, None

    def add(self, batch: Sequence) -> None:
        """Prior, poses and depth-frame choice of a batch of frames; each frame parked."""
        positions = np.arange(len(self.indices), len(self.indices) + len(batch))
        batch = batch.with_(names=self.names_of(batch.indices, positions), intrinsics=self.intrinsics)
        if self.poser.estimating:
            # The front end needs every frame's prior; the depth frames are chosen on its
            # live poses. A frame without a pose yet (the focal search still buffering)
            # keeps its prior: the motion rule cannot judge it.
            out = self._prior(batch, positions)
            with self.clock.stage("poses"):
                poses = self.poser.batch(positions, batch, out.depth)
            take = np.array([self.select(pose, _median_depth(out.depth[k])) if np.isfinite(pose).all() else True
                             for k, pose in enumerate(poses)], bool)
            rows = np.arange(len(batch))
        else:
            # Given poses: only the depth frames need a prior.
            with self.clock.stage("poses"):
                poses = self.poser.batch(positions, batch, None)
            take = np.array([self.select(pose) for pose in poses], bool)
            rows = np.flatnonzero(take)
            out = self._prior(batch.take(rows), positions[rows]) if len(rows) else None
            if out is not None:
                self.select.depth = _median_depth(out.depth[-1]) or self.select.depth
        with self.clock.stage("store"):
            # A frame's colour is read again only if it gets depth; the front end's finish
            # needs the others' grey image at its flow size, 1/48 of the bytes.
            for k, position in enumerate(positions):
                if take[k]:
                    self.store.put(position, rgb=batch.rgb[k])
                elif self.poser.estimating:
                    self.store.put(position, grey=self.poser.frontend.finish_image(batch.rgb[k]))
            for row, k in enumerate(rows):
                if take[k]:
                    self.store.put(positions[k], prior=out.depth[row],
                                   features=None if out.features is None else out.features[row])
                    self.sample.append(out.depth[row][::_SAMPLE_STEP, ::_SAMPLE_STEP].ravel())
        self.indices += [int(i) for i in batch.indices]
        self.stamps += [float(t) for t in batch.timestamps]
        self.names += list(batch.names)
        self.live += list(poses)
        self.chosen += list(take)
        self._log(batch, poses)

    def _prior(self, batch: Sequence, positions: np.ndarray):
        with self.clock.stage("prior"):
            out = self.prior(batch, positions)
        self.prior_info = out.info
        self.feature_shape = None if out.features is None else list(out.features.shape[1:])
        return out

    def _log(self, batch: Sequence, poses: np.ndarray) -> None:
        if self.logger is None:
            return
        with self.clock.stage("logging"):
            camera = self.poser.intrinsics or self.intrinsics
            for k, pose in enumerate(poses):
                self.logger.log_frame(int(batch.indices[k]), batch.rgb[k],
                                      pose=pose if np.isfinite(pose).all() else None, intrinsics=camera,
                                      timestamp=float(batch.timestamps[k]))

    def close(self) -> TrackedVideo:
        """Close the poses (global BA, gate) and return what the depth pass needs."""
        if len(self.indices) < 2:
            raise ReconInputError(f"{self.source.path}: needs at least 2 frames, got {len(self.indices)} "
                                  f"({self.source.selection.describe()})")
        indices, stamps = np.asarray(self.indices, np.int64), np.asarray(self.stamps, np.float64)
        with self.clock.stage("poses"):
            closed = self.poser.close(self.store, indices, stamps, np.asarray(self.live))
        keep = np.isfinite(closed.poses).all(axis=(1, 2))
        if closed.dropped_note:
            log.warning(closed.dropped_note)
        camera, camera_from = closed.intrinsics, closed.intrinsics_from
        if camera is None:
            camera, camera_from = default_intrinsics(*self.source.shape), "assumed (NYU field of view)"
            log.warning("camera intrinsics unknown; assuming NYU Depth v2's field of view "
                        "(pass --intrinsics or --fov for a better mesh)")
        values = np.concatenate(self.sample) if self.sample else np.zeros(0, np.float32)
        values = values[values > 0]
        if len(values) > _SAMPLE_MAX:
            values = values[np.linspace(0, len(values) - 1, _SAMPLE_MAX).astype(np.int64)]
        return TrackedVideo(
            indices=indices, timestamps=stamps, names=self.names, poses=closed.poses,
            depth_frame=np.asarray(self.chosen, bool) & keep, intrinsics=tuple(float(v) for v in camera),
            intrinsics_from=self.intrinsics_from if self.intrinsics is not None else camera_from,
            size=tuple(self.source.shape), lens_k1=closed.lens_k1, pose_source=closed.source,
            pose_info=closed.info, depth_sample=values, prior_info=self.prior_info, feature_shape=self.feature_shape,
        )


def _frame_namer(source: FrameSource) -> Callable[[np.ndarray, np.ndarray], list[str]]:
    """names(indices, positions) of a batch: a dataset's names cover all its selected frames
    at once (recon.io.pose_matching.frame_names), other sources name frames by index."""
    from .io.frames import DatasetSource

    if isinstance(source, DatasetSource):
        every = frame_names(source, None)
        return lambda indices, positions: [every[int(p)] for p in positions]
    return lambda indices, positions: frame_names(source, indices)


def _batches(source: FrameSource, clock: StageClock) -> Iterator[Sequence]:
    """The selected frames, PRIOR_BATCH at a time, as Sequences (decode time on the clock)."""
    frames = iter(source)
    while True:
        with clock.stage("decode"):
            chunk = [f for _, f in zip(range(PRIOR_BATCH), frames)]
        if not chunk:
            return
        yield Sequence(np.asarray([f.index for f in chunk], np.int64), np.asarray([f.timestamp for f in chunk]),
                       np.stack([f.rgb for f in chunk]), [""] * len(chunk))


@dataclass
class _Closed:
    poses: np.ndarray
    intrinsics: tuple | None
    intrinsics_from: str
    source: str
    info: dict
    lens_k1: float = 0.0
    dropped_note: str = ""


class _Poser:
    """Poses frame by frame during tracking: the streaming front end, the dataset's ground
    truth or a pose file, then closed once every frame is in."""

    def __init__(self, config: PipelineConfig, source: FrameSource, plan: PosePlan, intrinsics, store: FrameStore):
        self.plan, self.source, self.config, self.store = plan, source, config, store
        self.estimating = plan.estimated
        self.intrinsics = intrinsics
        self.file_intrinsics = None
        self.frontend = None
        self.recent_prior: dict[int, np.ndarray] = {}
        if self.estimating:
            from .poses.frontend import StreamingFrontend

            if config.pose_method == "sfm":
                raise ReconInputError("--pose-method sfm needs every frame at once: run it with --stream off")
            self.frontend = StreamingFrontend(intrinsics, self._prior,
                                              _frontend_config(config.pose_options, config.device))

    def _prior(self, position: int, frame) -> np.ndarray:
        # Recent frames from memory; older ones (frames buffered for the focal search,
        # which have no pose yet and so keep their prior) from the store.
        if position in self.recent_prior:
            return self.recent_prior[position]
        return self.store.get(position, "prior")

    def batch(self, positions, seq: Sequence, prior_depth: np.ndarray) -> np.ndarray:
        """(B, 4, 4) camera-to-world poses of a batch as known now (NaN where none)."""
        if self.plan.kind == "gt":
            return np.asarray(self.source.poses[positions], np.float64)
        if self.plan.kind == "file":
            poses, self.file_intrinsics = match_pose_file(self.plan.data, self.source, seq.indices, seq.timestamps)
            return np.asarray(poses, np.float64)
        out = []
        for k, position in enumerate(positions):
            self.recent_prior[int(position)] = prior_depth[k]
            _, pose = self.frontend.add(int(position), seq.rgb[k])
            out.append(np.full((4, 4), np.nan) if pose is None else pose)
        # The tracker asks for a frame's prior when it tracks it or promotes it to a
        # keyframe one frame later: a short history is enough.
        for old in [p for p in self.recent_prior if p < positions[0] - 2 * PRIOR_BATCH]:
            del self.recent_prior[old]
        return np.asarray(out, np.float64)

    def close(self, store: FrameStore, indices, timestamps, live: np.ndarray) -> _Closed:
        """Final poses of every frame (NaN for frames left out) and what the report says."""
        if self.plan.kind == "gt":
            _, note = ground_truth_kept(self.source)
            return _Closed(live, self.intrinsics, "unknown", "dataset ground truth", {}, dropped_note=note)
        if self.plan.kind == "file":
            intr = self.intrinsics or self.file_intrinsics
            return _Closed(live, intr, "poses (file)", f"file {self.plan.data.path}", {})
        return self._close_estimate(store, indices)

    def _close_estimate(self, store: FrameStore, indices) -> _Closed:
        result = self.frontend.finish(
            lambda position: store.get(position, "rgb" if store.has(position, "rgb") else "grey"),
            self.config.progress)
        kept, info, note = gate_estimate(result, indices)
        poses = np.asarray(result.poses, np.float64).copy()
        poses[~kept] = np.nan
        return _Closed(poses, tuple(result.intrinsics), "poses (estimated)",
                       "estimated (streamed front end)", info, float(result.diagnostics.get("lens_k1", 0.0)), note)


def _frontend_config(options: dict, device: str = "cpu"):
    from .poses.frontend import FrontendConfig
    from .poses.options import configure_frontend

    unknown = sorted(set(options) - set(FrontendConfig.__dataclass_fields__))
    if unknown:
        raise ReconInputError(f"streamed runs use the front end, which has no option {', '.join(unknown)}")
    return configure_frontend(options, device)


# --------------------------------------------------------------------------- pass 2: depth


@dataclass
class _WindowRecord:
    frames: int
    new: int
    anchor: float
    anchored_to: str
    medea_epochs: dict
    refined_share: float | None
    refined_frames: int = 0


def depth_windows(config: PipelineConfig, video: TrackedVideo, plan: PosePlan, store: FrameStore,
                  out: OutputFolder, logger, clock: StageClock):
    """MEDeA, refinement, depth files and fusion window by window: (volume, window records)."""
    import torch
    from tqdm.auto import tqdm

    from .export import write_depth_frame
    from .fusion import FusionOptions
    from .refine import default_min_confidence, fusion_confidence
    from .stages import adjust_with_medea, refine_depth

    positions = np.flatnonzero(video.depth_frame)
    if len(positions) < 2:
        raise ReconInputError(f"only {len(positions)} frames have a pose and moved enough to get depth; "
                              "lower --depth-frames or check the poses")
    windows = plan_windows(len(positions), int(config.window), int(config.window_overlap))
    options = FusionOptions(**{**asdict(config.fusion), "device": config.device, "progress": False})
    if options.min_confidence is None:
        options.min_confidence = default_min_confidence(plan.estimated)
    undistort = worth_undistorting(video.intrinsics, video.size, video.lens_k1)
    volume, records, finished, swept, fused = None, [], {}, {}, 0
    bar = tqdm(total=len(positions), desc="depth and fusion", unit="frame", disable=not config.progress)
    for window in windows:
        pos = positions[window.start:window.stop]
        with clock.stage("store"):
            seq = _window_sequence(video, store, pos, undistort)
        with clock.stage("medea"):
            if config.adjust:
                adjusted, medea = adjust_with_medea(seq, config.medea, config.features, progress=False)
            else:
                adjusted, medea = seq.prior_depth, None
        with clock.stage("fusion"):  # the fused surface is rendered into the window
            factor, anchored_to = _anchor(volume, seq, adjusted, [finished[p] for p in pos[:window.shared]])
        adjusted = adjusted * np.float32(factor)
        # first: the window's first row that `final` and `confidence` hold (the shared frames,
        # already fused, are matched against but not refined again).
        refined, final, confidence, first = None, adjusted, None, 0
        if config.refine == "mvs":
            with clock.stage("refine"):
                known = [swept.get(int(p)) for p in pos[:window.shared]]
                first = window.shared if known and all(k is not None for k in known) else 0
                refined = refine_depth(seq, adjusted, config.mvs, config.device, progress=False,
                                       known=torch.stack(known) if first else None)
                final, confidence = refined.depth.numpy(), fusion_confidence(refined)
                swept = {int(p): refined.swept[k - first] for k, p in enumerate(pos)
                         if k >= max(first, len(pos) - config.window_overlap)}
        finished = {int(p): adjusted[k] for k, p in enumerate(pos) if k >= len(pos) - config.window_overlap}
        with clock.stage("fusion"):
            if volume is None:
                volume = _open_volume(video, final, adjusted, seq, options)
        for k in range(window.shared, len(pos)):
            depth_k = final[k - first]
            with clock.stage("export"):
                write_depth_frame(out, seq.names[k], depth_k, config.depth_npy)
            with clock.stage("fusion"):
                d = depth_k if confidence is None else np.where(confidence[k - first] >= options.min_confidence,
                                                                depth_k, 0)
                fused += volume.integrate(d, seq.poses[k], seq.intrinsics, seq.rgb[k])
            if logger is not None:
                with clock.stage("logging"):
                    logger.log_depth(int(seq.indices[k]), seq.prior_depth[k], adjusted[k],
                                     None if refined is None else depth_k,
                                     None if refined is None else refined.confidence[k - first].numpy())
                    if config.mesh_every and fused and fused % int(config.mesh_every) == 0:
                        _log_mesh(logger, volume, options, int(seq.indices[k]))
            bar.update(1)
        if logger is not None and medea is not None and not records:
            logger.log_losses(medea.history)
        records.append(_WindowRecord(len(pos), len(pos) - window.shared, factor, anchored_to, _epochs(medea),
                                     None if refined is None else float(refined.reconstructed.float().mean()),
                                     0 if refined is None else len(pos) - first))
    bar.close()
    return (volume, options), records


def _anchor(volume, seq: Sequence, adjusted: np.ndarray, shared: list[np.ndarray]) -> tuple[float, str]:
    """(scale factor for a window's adjusted depth (N, H, W), what it was fitted to).

    Where the volume already holds surfaces in view, the factor brings the window to the
    fused surface rendered into all its frames: a camera that comes back to a place is put at
    the scale of what is already fused there (as a dense SLAM system tracks against its
    model), so revisits average into the same voxels instead of adding a second, shifted
    surface. Otherwise, the previous window's finished depth on the shared frames `shared`.
    Rendering SURFACE_ANCHOR_VIEWS frames spread over the window (the first one included) at
    half resolution (every other pixel) is enough for a median."""
    if volume is not None and volume.blocks_used:
        views = np.unique(np.linspace(0, len(adjusted) - 1, min(len(adjusted), SURFACE_ANCHOR_VIEWS)).round()
                          .astype(np.int64))
        current = adjusted[views, ::2, ::2]
        half = np.asarray(seq.intrinsics, np.float64) / 2.0
        rendered = np.stack([volume.render_depth(seq.poses[k], half, current.shape[1:]) for k in views])
        min_pixels = max(100, int(SURFACE_ANCHOR_MIN_COVER * current.size))
        if int(anchor_pixels(rendered, current).sum()) >= min_pixels:
            return anchor_factor(rendered, current, min_pixels), "fused surface"
    if shared:
        return anchor_factor(np.stack(shared), adjusted[:len(shared)]), "shared frames"
    return 1.0, "none"


def _window_sequence(video: TrackedVideo, store: FrameStore, pos: np.ndarray, undistort: bool) -> Sequence:
    features = [store.get(p, "features") for p in pos] if store.has(int(pos[0]), "features") else None
    seq = Sequence(video.indices[pos], video.timestamps[pos], store.stack(pos, "rgb"), [video.names[p] for p in pos],
                   video.intrinsics, store.stack(pos, "prior"), None if features is None else np.stack(features),
                   video.poses[pos])
    return seq.undistort(video.lens_k1) if undistort else seq


def _open_volume(video: TrackedVideo, final: np.ndarray, adjusted: np.ndarray, seq: Sequence, options):
    """The TSDF volume sized from the prior depth of all depth frames, brought to the scale
    of the first window's adjusted depth (the only adjusted depth known when it opens)."""
    from .fusion import TsdfVolume, estimate_block_count, fusion_device, volume_size

    prior, valid = seq.prior_depth, (seq.prior_depth > 0) & (adjusted > 0)
    ratio = float(np.median(adjusted[valid] / prior[valid])) if valid.any() else 1.0
    values = video.depth_sample * ratio
    if values.size == 0:
        raise ReconInputError("TSDF fusion: no frame has valid depth and a valid pose")
    voxel, trunc, max_depth = volume_size(values, options)
    estimate = estimate_block_count(final, seq.poses, seq.intrinsics, voxel, trunc, max_depth,
                                    options.block_resolution)
    # The first window sees part of the scene; the hash map grows past this when needed.
    capacity = int(min(options.block_count, max(4096, 2 * estimate)))
    return TsdfVolume(voxel, trunc, max_depth, capacity, colored=True, block_resolution=options.block_resolution,
                      device=fusion_device(options.device))


def _log_mesh(logger, volume, options, index: int) -> None:
    mesh, _ = volume.mesh(options)
    if len(mesh.triangles):
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors),
                        index=index)


def _epochs(medea) -> dict:
    if medea is None:
        return {}
    return {name: int(history.epochs) for name, history in medea.history.items()}


# --------------------------------------------------------------------------- export and report


def _finish(config, source, out: OutputFolder, video: TrackedVideo, fusion_state, windows, clock, logger,
            store_bytes: int):
    from .export import export_reconstruction
    from .fusion import FusionResult
    from .report import stream_report

    (volume, options) = fusion_state
    start = time.perf_counter()
    with clock.stage("fusion"):
        mesh, removed = volume.mesh(options)
        cloud = volume.point_cloud(options) if options.point_cloud else None
    fusion = FusionResult(mesh=mesh, point_cloud=cloud, voxel_size=volume.voxel, trunc=volume.trunc,
                          seconds=time.perf_counter() - start, max_depth=volume.max_depth,
                          frames_fused=volume.frames_fused, block_estimate=0, blocks_used=volume.blocks_used,
                          fragments_removed=removed)
    if len(mesh.triangles) == 0:
        log.warning("TSDF fusion: the mesh is empty (%d frames fused)", volume.frames_fused)
    kept = np.isfinite(video.poses).all(axis=(1, 2))
    with clock.stage("export"):
        files = export_reconstruction(out, mesh=mesh, poses=video.poses[kept], timestamps=video.timestamps[kept],
                                      intrinsics=video.intrinsics, shape=video.size, point_cloud=cloud,
                                      glb=config.glb)
        files["depth"] = out.path / DEPTH_DIR
    if logger is not None:
        with clock.stage("logging"):
            last = int(video.indices[-1])
            if len(mesh.triangles):
                logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                np.asarray(mesh.vertex_colors), index=last)
    report = stream_report(config=config, source=source, video=video, windows=[asdict(w) for w in windows],
                           fusion=fusion, min_confidence=options.min_confidence if config.refine != "none" else None,
                           seconds=clock.seconds, store_bytes=store_bytes)
    return StreamResult(output=out.path, frames_tracked=len(video.indices), depth_frames=int(video.depth_frame.sum()),
                        poses=video.poses, intrinsics=video.intrinsics, fusion=fusion, seconds=dict(clock.seconds),
                        files=files, report=report)


def _with_files(report: dict, files: dict, out: OutputFolder) -> dict:
    return {**report, "files": {k: str(Path(v).relative_to(out.path)) if Path(v).is_relative_to(out.path) else str(v)
                                for k, v in files.items()}}


__all__ = ["StreamResult", "TrackedVideo", "run_streamed", "track_video", "depth_windows"]

