"""The streamed pipeline's second pass (:mod:`recon.drivers.streamed`): depth in windows, fused as it
is finished.

Each window of depth frames (:func:`recon.drivers.stream_plan.plan_windows`), read back from
the frame store as a :class:`~recon.core.sequence.Sequence`: MEDeA, anchored to the surface
already fused (else to the previous window's frames: :func:`_anchor`), then the refinement
of its new frames. Each finished frame's depth is written, integrated into one
:class:`~recon.fusion.TsdfVolume` and logged; the mesh is re-extracted every ``mesh_every``.
More: docs/running.md#how-a-streamed-run-works
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..core.clock import StageClock
from ..core.config import PipelineConfig
from ..core.sequence import Sequence
from ..core.stages import PosePlan, window_frames
from ..errors import ReconInputError
from ..geometry.lens import worth_undistorting
from ..io.frame_store import FrameStore
from ..io.output_folder import OutputFolder
from ..threads import map_on_cores
from .segments import untrusted_scale
from .stream_plan import anchor_factor, anchor_pixels, plan_windows
from .stream_track import TrackedVideo

# Share of a window's pixels the fused surface must cover to anchor the window's scale.
SURFACE_ANCHOR_MIN_COVER = 0.02
# Frames of a window, spread over it, into which the fused surface is rendered (at half
# size) for the anchor. why: docs/decisions.md#the-windows-anchor
SURFACE_ANCHOR_VIEWS = 8
# Every this many pixels of them, each way: a median needs far fewer than a frame's pixels.
SURFACE_ANCHOR_STEP = 4
# A window whose own depth scale differs from the surface fused before it by more than this
# factor (either way) is reported: the anchor brings it to that surface, so what the first
# windows got wrong holds for the rest. why: docs/decisions.md#the-windows-anchor
ANCHOR_DISAGREEMENT = 1.15

log = logging.getLogger(__name__)


@dataclass
class _WindowRecord:
    frames: int
    new: int
    anchor: float
    anchored_to: str
    medea_epochs: dict
    refined_share: float | None
    refined_frames: int = 0
    medea_seconds: dict = field(default_factory=dict)
    # Input frame indices of the window's first and last frame.
    first_frame: int = 0
    last_frame: int = 0
    # Why MEDeA was skipped (--medea-gate and given poses the frames contradict).
    medea_skipped: str | None = None
    # Given poses: the factor MEDeA's search put on the window's prior (medea_core.global_scale).
    prior_factor: dict | None = None
    # MEDeA's Stage I: keyframe pairs left out for overlapping too little, and whether the
    # pairs left did not join the keyframes (Stage I skipped: MedeaConfig.min_pair_overlap).
    stage1_pairs_left_out: int = 0
    stage1_skipped: bool = False


def depth_windows(config: PipelineConfig, video: TrackedVideo, plan: PosePlan, store: FrameStore,
                  out: OutputFolder, logger, clock: StageClock, omega: np.ndarray | None = None):
    """MEDeA, refinement, depth files and fusion window by window: ((volume, fusion options),
    window records, the largest rolling-shutter shift in pixels of each depth frame by its
    position). omega: the body angular velocity (N, 3) rad/s of every tracked frame when
    the frames are resampled for a rolling shutter of ``config.rolling_shutter`` ms, else None."""
    import torch
    from tqdm.auto import tqdm

    from ..core.refine import default_min_confidence, default_weight_threshold, fusion_confidence
    from ..core.stages import adjust_with_medea, medea_settings, refine_depth
    from ..export import write_depth_frame
    from ..fusion import FusionOptions, confidence_weight

    positions = np.flatnonzero(video.depth_frame)
    if len(positions) < 2:
        raise ReconInputError(f"only {len(positions)} frames have a pose and moved enough to get depth; "
                              "lower --depth-frames or check the poses")
    if logger is not None and plan.estimated:
        with clock.stage("logging"):
            _log_final_cameras(logger, video)
    windows = plan_windows(len(positions), window_frames(config, video.size), int(config.window_overlap))
    options = FusionOptions(**{**asdict(config.fusion), "device": config.device, "progress": False,
                               "metric": not untrusted_scale(video.pose_info)})
    if options.min_confidence is None:
        options.min_confidence = default_min_confidence(plan.estimated)
    if options.weight_threshold is None:
        options.weight_threshold = default_weight_threshold(plan.estimated, config.refine == "mvs")
    undistort = worth_undistorting(video.intrinsics, video.size, video.lens_k1)
    volume, records, finished, swept, fused, shifts = None, [], {}, {}, 0, {}
    skipped = video.medea_skipped
    bar = tqdm(total=len(positions), desc="depth and fusion", unit="frame", disable=not config.progress)
    for window in windows:
        pos = positions[window.start:window.stop]
        with clock.stage("store"):
            seq, window_shifts = _window_sequence(video, store, pos, undistort, omega, config.rolling_shutter)
        shifts.update(zip(pos.tolist(), window_shifts))
        with clock.stage("medea"):
            if config.adjust and not skipped:
                adjusted, medea = adjust_with_medea(seq, medea_settings(config, plan.estimated), config.features,
                                                    progress=False)
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
        with clock.stage("export"):  # PNG encoding releases the GIL: the window's frames on every core
            map_on_cores(lambda k: write_depth_frame(out, seq.names[k], final[k - first], config.depth_npy),
                         range(window.shared, len(pos)))
        for k in range(window.shared, len(pos)):
            depth_k = final[k - first]
            with clock.stage("fusion"):
                weight = None if confidence is None else confidence_weight(
                    confidence[k - first], options.min_confidence, options.confidence_weights)
                fused += volume.integrate(depth_k, seq.poses[k], seq.intrinsics, seq.rgb[k], weight=weight)
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
        clock.mark("first_result")  # the first window's surface is fused: what a live viewer shows first
        records.append(_WindowRecord(len(pos), len(pos) - window.shared, factor, anchored_to, _epochs(medea),
                                     None if refined is None else float(refined.reconstructed.float().mean()),
                                     0 if refined is None else len(pos) - first, _seconds(medea),
                                     int(seq.indices[0]), int(seq.indices[-1]), skipped,
                                     None if medea is None or medea.global_scale is None
                                     else medea.global_scale.to_dict(), *_stage1(medea)))
    bar.close()
    warn_scale_disagreement(records, config)
    return (volume, options), records, shifts


def warn_scale_disagreement(records: list[_WindowRecord], config: PipelineConfig) -> None:
    """A warning when windows' own depth scales disagreed with the fused surface by more than
    ANCHOR_DISAGREEMENT: the depth is consistent, but its scale is the first windows'."""
    off = [r for r in records if abs(math.log(r.anchor)) > math.log(ANCHOR_DISAGREEMENT)]
    if not off:
        return
    worst = max(off, key=lambda r: abs(math.log(r.anchor)))
    hints = []
    if config.depth_frames != "motion":
        hints.append("keep the default --depth-frames motion")
    if config.refine == "none":
        hints.append("refine the depth (--refine mvs)")
    log.warning("the depth scale of %d of %d windows disagreed with the surface fused before them by more than "
                "%.0f%% (most: frames %d-%d, x%.2f); each was brought to that surface, so the scale of the first "
                "windows holds for all. Windows that span little camera motion hold their scale poorly%s",
                len(off), len(records), 100 * (ANCHOR_DISAGREEMENT - 1), worst.first_frame, worst.last_frame,
                worst.anchor, (": " + " or ".join(hints)) if hints else "")


def _anchor(volume, seq: Sequence, adjusted: np.ndarray, shared: list[np.ndarray]) -> tuple[float, str]:
    """(scale factor for a window's adjusted depth (N, H, W), what it was fitted to).

    Where the volume already holds surfaces in view, the factor brings the window to the
    fused surface rendered into all its frames: a camera that comes back to a place is put at
    the scale of what is already fused there (as a dense SLAM system tracks against its
    model), so revisits average into the same voxels instead of adding a second, shifted
    surface. Otherwise, the previous window's finished depth on the shared frames `shared`.
    Rendering SURFACE_ANCHOR_VIEWS frames spread over the window (the first one included) at
    every SURFACE_ANCHOR_STEP-th pixel is enough for a median."""
    from ..poses.result import evenly_apart

    if volume is not None and volume.blocks_used:
        views = evenly_apart(len(adjusted), SURFACE_ANCHOR_VIEWS)
        step = SURFACE_ANCHOR_STEP
        current = adjusted[views, ::step, ::step]
        coarse = np.asarray(seq.intrinsics, np.float64) / step
        rendered = np.stack([volume.render_depth(seq.poses[k], coarse, current.shape[1:]) for k in views])
        min_pixels = max(100, int(SURFACE_ANCHOR_MIN_COVER * current.size))
        if int(anchor_pixels(rendered, current).sum()) >= min_pixels:
            return anchor_factor(rendered, current, min_pixels), "fused surface"
    if shared:
        return anchor_factor(np.stack(shared), adjusted[:len(shared)]), "shared frames"
    return 1.0, "none"


def _window_sequence(video: TrackedVideo, store: FrameStore, pos: np.ndarray, undistort: bool,
                     omega: np.ndarray | None, readout_ms: float) -> tuple[Sequence, list[float]]:
    """The window's frames read back from the store, resampled for the rolling shutter (when
    omega is given; the shutter bends the recorded image, so before the lens), then into the
    lens' pinhole image: (sequence, largest shutter shift of each frame, [] without)."""
    features = [store.get(p, "features") for p in pos] if store.has(int(pos[0]), "features") else None
    seq = Sequence(video.indices[pos], video.timestamps[pos], store.stack(pos, "rgb"), [video.names[p] for p in pos],
                   video.intrinsics, store.stack(pos, "prior"), None if features is None else np.stack(features),
                   video.poses[pos])
    shifts: list[float] = []
    if omega is not None:
        seq, frame_shifts = seq.unroll(omega[pos], readout_ms / 1000.0)
        shifts = frame_shifts.tolist()
    return (seq.undistort(video.lens_k1) if undistort else seq), shifts


def _open_volume(video: TrackedVideo, final: np.ndarray, adjusted: np.ndarray, seq: Sequence, options):
    """The TSDF volume sized from the prior depth of all depth frames, brought to the scale
    of the first window's adjusted depth (the only adjusted depth known when it opens). Its
    far clip also reaches as far as the first window's final depth: the median ratio
    understates the far end where MEDeA stretched the prior's range."""
    from ..fusion import TsdfVolume, auto_max_depth, estimate_block_count, fusion_device, volume_size

    prior, valid = seq.prior_depth, (seq.prior_depth > 0) & (adjusted > 0)
    ratio = float(np.median(adjusted[valid] / prior[valid])) if valid.any() else 1.0
    values = video.depth_sample * ratio
    if values.size == 0:
        raise ReconInputError("TSDF fusion: no frame has valid depth and a valid pose")
    voxel, trunc, max_depth = volume_size(values, options)
    finished = final[:, ::4, ::4]
    if options.max_depth is None and (finished > 0).any():
        max_depth = max(max_depth, auto_max_depth(finished[finished > 0]))
    estimate = estimate_block_count(final, seq.poses, seq.intrinsics, voxel, trunc, max_depth,
                                    options.block_resolution)
    # The first window sees part of the scene; the hash map grows past this when needed.
    capacity = int(min(options.block_count, max(4096, 2 * estimate)))
    return TsdfVolume(voxel, trunc, max_depth, capacity, colored=True, block_resolution=options.block_resolution,
                      device=fusion_device(options.device))


def _log_final_cameras(logger, video: TrackedVideo) -> None:
    """Every frame's camera at its final pose, before its depth is logged. Tracking logged each
    frame's RGB with the pose and intrinsics the front end had then: none while its focal search
    buffered the first frames, poses the global BA, the metric scale and a join moved since.
    (Given poses are final as they come and were logged so.) A run in segments passes each
    stretch here, NaN elsewhere: the stretches are logged in order, each from its first frame."""
    logger.log_cameras(video.indices, video.poses, video.intrinsics, video.size)


def _log_mesh(logger, volume, options, index: int) -> None:
    mesh, _ = volume.mesh(options)
    if len(mesh.triangles):
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors),
                        index=index)


def _seconds(medea) -> dict:
    return {} if medea is None else {name: round(float(value), 3) for name, value in medea.seconds.items()}


def _stage1(medea) -> tuple[int, bool]:
    stage1 = None if medea is None else medea.history.get("stage1")
    return (0, False) if stage1 is None else (int(stage1.pairs_left_out), bool(stage1.skipped))


def _epochs(medea) -> dict:
    if medea is None:
        return {}
    return {name: int(history.epochs) for name, history in medea.history.items()}


__all__ = ["SURFACE_ANCHOR_MIN_COVER", "SURFACE_ANCHOR_STEP", "SURFACE_ANCHOR_VIEWS", "depth_windows"]
