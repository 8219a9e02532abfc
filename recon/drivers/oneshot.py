"""The one-shot driver: every selected frame in memory at once, through the stages in order.

``prior`` (the network loaded before the frames are decoded, so a bad model fails at once),
``decode``, ``poses`` (given, checked and optionally polished; or estimated, with the quality
gate, the rolling-shutter resampling and, where the trajectory's scale breaks, the joins or one
run per stretch: :mod:`recon.drivers.segments`), ``undistort``, ``medea``, ``refine``,
``fusion``, ``export``, ``logging``, then ``report.json``. The stages are
:mod:`recon.core.stages`; :mod:`recon.pipeline` decides that this driver runs (the input fits
the frame budget) and has opened the input and the output folder. Its streamed sibling is
:mod:`recon.drivers.streamed`.
"""

from __future__ import annotations

import logging
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.clock import StageClock
from ..core.config import PipelineConfig
from ..core.refine import default_min_confidence, default_weight_threshold, fusion_confidence
from ..core.report import build_report, segments_summary, segments_warning
from ..core.sequence import Sequence
from ..core.stages import (
    adjust_with_medea,
    camera_poses,
    decode,
    default_intrinsics,
    judge_given_poses,
    medea_settings,
    polished_poses,
    prior_function,
    refine_depth,
    tracking_states,
    unrolled_frames,
)
from ..errors import ReconInputError
from ..export import export_reconstruction
from ..fusion import FusionOptions
from ..geometry.lens import worth_undistorting
from ..io.output_folder import REPORT_JSON, OutputFolder, segment_name
from ..io.source import FrameSource
from ..memory import release_memory
from .recording import open_recording
from .result import RunResult
from .segments import estimator_options, settle_breaks, trajectory_stretches, untrusted_scale

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class PipelineResult(RunResult):
    """A one-shot run's result (RunResult), with what it held in memory: frames, the
    sequence as fused (frames at working size, names, intrinsics, prior depth, poses; frames
    the pose quality gate dropped are not in it); prior_depth, depth: (N, H, W) metres (depth
    is the final depth: refined, else MEDeA-adjusted, else the prior); adjusted_depth:
    MEDeA's (the prior when adjust=False); medea: MedeaResult or None; refined:
    mvs_core.RefineResult or None (its support and swept depth dropped once the fusion
    confidence is made, to bound memory)."""

    frames: Sequence
    prior_depth: np.ndarray
    depth: np.ndarray
    medea: object
    adjusted_depth: np.ndarray | None = None
    refined: object = None

    @property
    def frame_count(self) -> int:
        return len(self.frames)


def run_oneshot(config: PipelineConfig, source: FrameSource, out: OutputFolder, pose_plan,
                given: tuple[tuple | None, str], say: Callable[[str], None], timer: StageClock) -> PipelineResult:
    """Every stage after the input's selection (module docstring) into ``out``; given:
    (intrinsics or None, their source); timer: the run's clock (``decode`` already counted)."""
    intrinsics, intrinsics_from = given
    with timer.stage("prior"):  # the network is loaded before the frames are decoded: a bad model fails at once
        prior_of = prior_function(source, config.prior, path=config.prior_path, weights=config.weights,
                                  features=config.features and config.adjust, align=config.prior_align,
                                  device=config.device, progress=config.progress)
    with timer.stage("decode"):
        seq = decode(source, config.progress)
    seq = seq.with_(intrinsics=intrinsics)

    say(f"depth prior: {config.prior}")
    with timer.stage("prior"):
        prior = prior_of(seq, np.arange(len(seq)))
    seq = seq.with_(prior_depth=prior.depth, features=prior.features)

    say(f"poses: {config.poses}")
    with timer.stage("poses"):
        seq, pose_stage, tracking = _posed(config, pose_plan, source, seq)
        if seq.intrinsics is None and pose_stage.intrinsics is not None:
            seq, intrinsics_from = seq.with_(intrinsics=pose_stage.intrinsics), f"poses ({pose_stage.source})"
        if seq.intrinsics is None:
            seq, intrinsics_from = seq.with_(intrinsics=default_intrinsics(*seq.size)), "assumed (NYU field of view)"
            log.warning("camera intrinsics unknown; assuming NYU Depth v2's field of view "
                        "(pass --intrinsics or --fov for a better mesh)")
        seq = seq.with_(intrinsics=tuple(float(v) for v in seq.intrinsics))
        if config.rolling_shutter > 0:
            seq, pose_stage, tracking = _unroll(config, pose_plan, source, seq, pose_stage, tracking, say)
        if pose_plan.polishes(config):
            say("polishing the given poses against the frames")
            pose_stage = polished_poses(pose_stage, seq, config.polish_config, config.progress, config.device)
            seq = seq.with_(poses=pose_stage.poses)

    if pose_plan.estimated:
        stretch = trajectory_stretches(pose_stage.info, len(pose_stage.poses))
        stretch = stretch if pose_stage.keep is None else stretch[pose_stage.keep]
        stretch, poses, info = settle_breaks(config, stretch, seq.poses, np.arange(len(seq)),
                                             lambda p: (seq.rgb[p], seq.prior_depth[p]), seq.intrinsics,
                                             pose_stage.info)
        seq, pose_stage = seq.with_(poses=poses), replace(pose_stage, info=info)
        if stretch.max() > 0:
            return _run_segments(out, seq, stretch, pose_stage, timer, say, lambda piece, piece_out: _reconstruct(
                config, piece_out, source, piece, pose_stage, pose_plan, intrinsics_from, prior, StageClock(),
                tracking, say))
    return _reconstruct(config, out, source, seq, pose_stage, pose_plan, intrinsics_from, prior, timer, tracking, say)


def _reconstruct(config: PipelineConfig, out: OutputFolder, source, seq: Sequence, pose_stage, pose_plan,
                 intrinsics_from: str, prior, timer: StageClock, tracking, say) -> PipelineResult:
    """The stages after the poses (undistortion, MEDeA, refinement, fusion, export, Rerun,
    report) on the posed sequence, into ``out``."""
    from ..fusion import fuse

    undistorted = worth_undistorting(seq.intrinsics, seq.size, pose_stage.lens_k1)
    if undistorted:
        # The poses belong to the pinhole camera of the estimated lens: so must the images.
        say(f"undistorting frames and prior (lens k1 {pose_stage.lens_k1:+.4f})")
        with timer.stage("undistort"):
            seq = seq.undistort(pose_stage.lens_k1)
    else:
        timer.seconds["undistort"] = 0.0

    medea_result, medea_skipped = None, None
    if not pose_plan.estimated:
        with timer.stage("poses"):
            check, medea_skipped = judge_given_poses(seq.rgb, seq.poses, seq.intrinsics,
                                                     config.medea_gate and config.adjust)
        pose_stage = replace(pose_stage, info={**pose_stage.info, "check": check})
    if config.adjust and medea_skipped is None:
        say("MEDeA depth adjustment")
        with timer.stage("medea"):
            depth, medea_result = adjust_with_medea(seq, medea_settings(config, pose_plan.estimated), config.features,
                                                    config.progress)
    else:
        depth = seq.prior_depth
        timer.seconds["medea"] = 0.0
    adjusted = depth

    refined = None
    if config.refine == "mvs":
        say("multi-view stereo refinement")
        with timer.stage("refine"):
            refined = refine_depth(seq, depth, config.mvs, config.device, config.progress)
        depth = refined.depth.numpy()
        _warn_unsupported(refined, seq, config.mvs.min_frame_share)
    else:
        timer.seconds["refine"] = 0.0

    say("TSDF fusion")
    fusion_options = FusionOptions(**{**asdict(config.fusion), "device": config.device, "progress": config.progress,
                                      "metric": not untrusted_scale(pose_stage.info)})
    with timer.stage("fusion"):
        confidence = None if refined is None else fusion_confidence(refined)
        if refined is not None:
            # Their use is over (the confidence is made; a later call's `known` is the
            # streamed run's): a frame's worth each, dropped before the volume is built.
            refined.support, refined.swept = None, None
            release_memory(force=True)
        if fusion_options.min_confidence is None:
            fusion_options.min_confidence = default_min_confidence(pose_plan.estimated)
        if fusion_options.weight_threshold is None:
            fusion_options.weight_threshold = default_weight_threshold(pose_plan.estimated, refined is not None)
        fused = fuse(depth, seq.rgb, seq.poses, seq.intrinsics, fusion_options, confidence=confidence)

    say("export")
    with timer.stage("export"):
        files = export_reconstruction(
            out, mesh=fused.mesh, poses=seq.poses, timestamps=seq.timestamps, intrinsics=seq.intrinsics,
            shape=seq.size, depth=depth, frame_names=seq.names, point_cloud=fused.point_cloud, glb=config.glb,
            glb_rotation=fused.upright.rotation, depth_npy=config.depth_npy,
        )

    rerun_url = None
    with timer.stage("logging"):
        if config.rerun != "off":
            say(f"rerun: {config.rerun}")
            rerun_url, rec_path = _log_recording(config, out, seq, adjusted, fused.mesh, medea_result, refined,
                                                 tracking)
            if rec_path is not None:
                files["recording"] = rec_path

    report = build_report(
        config=config, source=source, seq=seq, intrinsics_from=intrinsics_from, pose_stage=pose_stage,
        undistorted=undistorted, prior=prior, medea_result=medea_result, medea_skipped=medea_skipped, refined=refined,
        fusion=fused, min_confidence=fusion_options.min_confidence if refined is not None else None,
        seconds=timer.seconds, files={k: str(Path(v).relative_to(out.path)) for k, v in files.items()},
    )
    files["report"] = out.write_json(REPORT_JSON, report)
    return PipelineResult(
        output=out.path, frames=seq, prior_depth=seq.prior_depth, depth=depth, poses=seq.poses,
        intrinsics=seq.intrinsics, fusion=fused, medea=medea_result, seconds=dict(timer.seconds), files=files,
        report=report, rerun_url=rerun_url, adjusted_depth=adjusted, refined=refined,
    )


def _run_segments(out: OutputFolder, seq: Sequence, stretch: np.ndarray, pose_stage, timer: StageClock, say,
                  reconstruct: Callable[[Sequence, OutputFolder], PipelineResult]) -> PipelineResult:
    """A trajectory whose scale breaks (``stretch``: (N,) the stretch of each posed frame,
    recon.drivers.segments.trajectory_stretches) reconstructed stretch by stretch into
    ``OUT/segment_NN/`` (``reconstruct(piece, its folder)``), with one summary report.json;
    the result of the whole run is the largest piece's, with ``segments``. A stretch of fewer
    than two frames is left out with a warning (recon.drivers.streamed does the same for a streamed run)."""
    pieces = []
    for k in range(int(stretch.max()) + 1):
        mine = np.flatnonzero(stretch == k)
        if len(mine) < 2:
            log.warning("%d frame(s) of stretch %d of the trajectory are left out: too few to reconstruct",
                        len(mine), k)
            continue
        name = segment_name(len(pieces))
        piece = seq.take(mine)
        say(f"{name}: frames {int(piece.indices[0])}-{int(piece.indices[-1])}")
        pieces.append(reconstruct(piece, OutputFolder(out.path / name, overwrite=True)))
    if not pieces:
        raise ReconInputError("no stretch of the trajectory between its scale breaks has two frames "
                              "(--on-break keep writes the trajectory as one)")
    largest = max(pieces, key=lambda p: len(p.frames))
    summary = segments_summary(largest.report, pieces, pose_stage.info, timer.seconds)
    log.warning(segments_warning(summary))
    result = replace(largest, output=out.path, report=summary, files={p.output.name: p.output for p in pieces},
                     seconds=dict(summary["seconds"]), segments=pieces)
    result.files["report"] = out.write_json(REPORT_JSON, summary)
    return result


def _unroll(config: PipelineConfig, pose_plan, source, seq: Sequence, pose_stage, tracking, say):
    """Frames resampled for a rolling shutter with the turn rate of the poses; estimated
    poses are estimated again on them (the first estimate carries the shutter's error)."""
    say(f"resampling the frames for a {config.rolling_shutter:g} ms rolling shutter")
    seq, shutter = unrolled_frames(seq, config.rolling_shutter)
    if pose_plan.estimated:
        say("poses again, on the resampled frames")
        seq, pose_stage, tracking = _posed(config, pose_plan, source, seq)
    return seq, replace(pose_stage, info={**pose_stage.info, "rolling_shutter": shutter}), tracking


def _posed(config: PipelineConfig, pose_plan, source, seq: Sequence):
    """(sequence with its poses, the pose stage, the tracking states): the frames the quality
    gate (or a missing ground truth) leaves out are taken out, with a warning."""
    pose_stage = camera_poses(pose_plan, source, seq, method=config.pose_method, options=estimator_options(config),
                              device=config.device, progress=config.progress)
    seq = seq.with_(poses=pose_stage.poses)
    tracking = tracking_states(pose_stage, seq)
    if pose_stage.keep is not None:
        log.warning(pose_stage.dropped_note)
        seq = seq.take(pose_stage.keep)
    return seq, pose_stage, tracking


def _warn_unsupported(refined, seq: Sequence, min_frame_share: float) -> None:
    """One warning naming how many frames the refinement could not confirm."""
    unsupported = np.flatnonzero(refined.unsupported.numpy())
    if len(unsupported):
        log.warning("the refinement reconstructed less than %.0f%% of the pixels of %d of %d frames (first: frame "
                    "%d): the frames do not confirm their depth (too little parallax or texture), so their MEDeA "
                    "depth is fused whole", 100 * min_frame_share, len(unsupported), len(seq),
                    int(seq.indices[unsupported[0]]))


def log_to_rerun(logger, seq: Sequence, depth, mesh, medea_result, progress=True, refined=None, tracking=None):
    """Every frame (RGB, prior, adjusted and refined depth, confidence, camera, trajectory),
    the mesh, the losses. depth: MEDeA's (or the prior when MEDeA was skipped); refined:
    the refinement's RefineResult or None; tracking: [(video frame, state, pose)] of every
    selected frame, dropped ones included (see recon.core.stages.tracking_states), or None."""
    from tqdm.auto import tqdm

    for index, state, pose in tracking or []:
        logger.log_tracking(index, state, pose)
    for k in tqdm(range(len(seq)), desc="rerun logging", unit="frame", disable=not progress, leave=False):
        extra = {} if refined is None else {"refined_depth": refined.depth[k].numpy(),
                                            "confidence": refined.confidence[k].numpy()}
        logger.log_frame(int(seq.indices[k]), seq.rgb[k], seq.prior_depth[k], depth[k], seq.poses[k], seq.intrinsics,
                         timestamp=float(seq.timestamps[k]), **extra)
    if mesh is not None and len(mesh.triangles):
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colors)
    if medea_result is not None:
        logger.log_losses(medea_result.history)


def _log_recording(config, out: OutputFolder, seq: Sequence, depth, mesh, medea_result, refined=None, tracking=None):
    """Log to Rerun in the configured mode (recording.open_recording): (server URL or None,
    .rrd path or None)."""
    with ExitStack() as stack:
        logger, rec_path = open_recording(config, out, stack)
        log_to_rerun(logger, seq, depth, mesh, medea_result, config.progress, refined, tracking)
    return (None if rec_path is not None else logger.url), rec_path


