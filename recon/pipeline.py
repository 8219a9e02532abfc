"""The whole reconstruction: named stages over one typed configuration, wired in order.

This module owns the driver: which stage runs when, what each hands to the next (one
:class:`~recon.sequence.Sequence` that gains prior depth, features and poses as it goes),
the choice of intrinsics, one timer per stage, the output folder and ``report.json``. The
stages are in :mod:`recon.stages`, the configuration in :mod:`recon.config`, the report's
content in :mod:`recon.report`; the methods live in :mod:`recon.io`, :mod:`recon.priors`,
:mod:`recon.poses`, :mod:`recon.medea`, :mod:`recon.refine`, :mod:`recon.fusion`,
:mod:`recon.export` and Rerun logging in :mod:`viewer`.

Stages, in order (each timed in ``PipelineResult.seconds`` under its name):

``decode``     open the input, check the output folder and the pose source, select and
               resize frames (stored at working resolution);
``prior``      per-frame metric depth (FastDepth by default; sensor depth; a depth folder; a
               local Hugging Face model, its disparity aligned to FastDepth or sensor depth);
               the network is loaded before the frames are decoded;
``poses``      camera-to-world poses: a pose file, the dataset's ground truth (both used as
               given), or estimated (frames the quality gate drops leave the sequence here);
               with a rolling-shutter readout given, the frames are resampled to one instant
               each with the poses' turn rate (:mod:`recon.rolling_shutter`) and estimated
               poses estimated again on them; given poses are polished against the frames
               only with ``polish`` (:mod:`recon.poses.polish`), and checked against them
               (:mod:`recon.poses.pose_check`: a warning when the frames contradict them);
``undistort``  frames, prior and features resampled into the pinhole camera when the poses
               came with a lens term (:mod:`recon.lens`);
``medea``      MEDeA multi-view depth adjustment (skipped with ``adjust=False``, and with
               ``medea_gate`` when the frames contradict the given poses);
``refine``     per-pixel multi-view stereo around MEDeA's depth, with a confidence per pixel
               (``refine="mvs"``, :mod:`recon.refine`; ``"none"`` keeps the paper's pipeline);
``fusion``     TSDF fusion of the final depth with colour (only the pixels the refinement
               reconstructed, when it ran), marching cubes, clean-up;
``export``     mesh.ply, mesh.glb, trajectory.txt, intrinsics.json, depth maps;
``logging``    the Rerun recording (frames, depths, cameras, trajectory, mesh, losses).

``report.json`` is written last: inputs, options, versions, timings, MEDeA loss summary.

Intrinsics, first that applies: ``intrinsics`` given (pixels of the input as decoded),
``fov`` given, the dataset's calibration, the pose file's, the pose estimator's estimate,
and finally a camera with NYU Depth v2's field of view (~63 degrees horizontal; a warning
says so). Poses ``"auto"``: a dataset's ground truth when it has one, else estimation.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from .clock import StageClock
from .config import PipelineConfig
from .errors import ReconInputError
from .export import export_reconstruction
from .fusion import FusionOptions
from .io.output_folder import (
    RECORDING,
    REPORT_JSON,
    UNFINISHED,
    OutputFolder,
    atomic_path,
    mark_finished,
    mark_unfinished,
)
from .lens import worth_undistorting
from .memory import release_memory
from .refine import default_min_confidence, fusion_confidence
from .report import build_report, segments_summary, segments_warning
from .segments import estimator_options, join_breaks, say_joins, stop_at_breaks, trajectory_stretches
from .sequence import Sequence
from .stages import (
    adjust_with_medea,
    budget_capacity,
    camera_poses,
    decode,
    default_intrinsics,
    given_intrinsics,
    judge_given_poses,
    plan_poses,
    polished_poses,
    prior_function,
    refine_depth,
    select_frames,
    tracking_states,
    undistort_known_lens,
    unrolled_frames,
)

if TYPE_CHECKING:
    from .stream import StreamResult

log = logging.getLogger(__name__)

STAGES = ("decode", "prior", "poses", "undistort", "medea", "refine", "fusion", "export", "logging")


@dataclass
class PipelineResult:
    """What a run produced (everything also on disk in ``output``).

    frames: the sequence as fused (frames at working size, names, intrinsics, prior depth,
    poses; frames the pose quality gate dropped are not in it); prior_depth, depth:
    (N, H, W) metres (depth is the final depth: refined, else MEDeA-adjusted, else the
    prior); adjusted_depth: MEDeA's (the prior when adjust=False); poses (N, 4, 4)
    camera-to-world; intrinsics (fx, fy, cx, cy) at working size; fusion: FusionResult;
    medea: MedeaResult or None; refined: mvs_core.RefineResult or None (its support and
    swept depth dropped once the fusion confidence is made, to bound memory); seconds: {stage:
    wall seconds}; files: {label: path}; report: what report.json holds.
    """

    output: Path
    frames: Sequence
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
    # Where the trajectory's scale broke (--on-break segments): each stretch's own run.
    segments: list["PipelineResult"] = field(default_factory=list)

    @property
    def seconds_per_frame(self) -> dict[str, float]:
        n = max(1, len(self.frames))
        return {stage: s / n for stage, s in self.seconds.items()}


def run_pipeline(config: PipelineConfig,
                 on_stage: Callable[[str], None] | None = None) -> PipelineResult | StreamResult:
    """Run every stage (module docstring) and write the output folder; returns what was made:
    a PipelineResult, or a streamed run's recon.stream.StreamResult. Both give output, poses,
    intrinsics, depth (a streamed run's read back from disk: its depth frames), fusion (its
    mesh), seconds, files, report, rerun_url and segments.

    The input is opened and the output folder checked before any heavy work, so bad input
    or a non-empty output folder fail at once, with nothing written. An output folder this
    run created is removed again if the run fails before writing anything into it.
    """
    created = not Path(config.output).exists()
    try:
        result = _run_stages(config, on_stage)
    except BaseException:
        if created and Path(config.output).is_dir():
            _remove_if_empty(Path(config.output))
        raise
    mark_finished(config.output)
    return result


def stream_reason(config: PipelineConfig, source, pose_plan) -> str | None:
    """Why this run is streamed (the line said), or None for a one-shot run.

    ``auto`` streams what a one-shot run cannot hold (more frames than the frame budget
    holds at their size, stages.budget_capacity: a one-shot run's memory grows with its
    frames' pixels, a streamed run's does not) and
    video files whose poses are estimated: at 30 fps most of their frames repeat a view, and
    the streamed run gives depth only to the frames the camera moved to reach, which on the
    videos measured was 1.1-1.9x faster for a mesh as good (docs/benchmarks.md, "Videos
    stream when their poses are estimated"). SfM needs every frame at once, and a rolling
    shutter with estimated poses needs the trajectory estimated a second time: neither is
    streamed by that rule.
    """
    if config.stream == "on":
        return "streaming"
    if config.stream == "off":
        return None
    capacity = budget_capacity(config.frame_budget, source.shape)
    if source.count > capacity:
        height, width = source.shape
        return (f"streaming {source.count} frames at {width}x{height} (a one-shot run holds {capacity} such frames "
                f"within the frame budget of {config.frame_budget} at 640x480)")
    if _streamed_as_video(config, source, pose_plan):
        return ("streaming the video (estimated poses: depth for the frames the camera moved to reach; "
                "--stream off gives every frame depth)")
    return None


def _streamed_as_video(config: PipelineConfig, source, pose_plan) -> bool:
    """auto's video rule (stream_reason): a video within the frame budget, poses estimated,
    not by SfM, no rolling shutter. Such a run that loses the camera can be run again at once."""
    return (config.stream == "auto" and source.count <= budget_capacity(config.frame_budget, source.shape)
            and source.kind == "video"
            and pose_plan.estimated and config.pose_method != "sfm" and config.rolling_shutter == 0)


def _remove_if_empty(folder: Path) -> None:
    """rmdir `folder` and its empty subfolders; anything holding a file other than the
    UNFINISHED.txt mark stays (with the mark: the remains of a failed run)."""
    if [p.name for p in folder.rglob("*") if p.is_file()] == [UNFINISHED]:
        mark_finished(folder)
    for sub in sorted((p for p in folder.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
        if not any(sub.iterdir()):
            sub.rmdir()
    if not any(folder.iterdir()):
        folder.rmdir()


def _run_stages(config: PipelineConfig, on_stage) -> PipelineResult:

    config.validate()
    say = on_stage or (lambda _: None)
    timer = StageClock()
    with timer.stage("decode"):
        source = select_frames(config.input, stride=config.stride, max_frames=config.max_frames,
                               start_time=config.start_time, end_time=config.end_time, width=config.width,
                               fps=config.fps, frame_budget=config.frame_budget if config.stream == "off" else None)
        intrinsics, intrinsics_from = given_intrinsics(source, config.intrinsics, config.fov)
        undistort_known_lens(source, intrinsics, intrinsics_from, config.distortion)
        out = OutputFolder(config.output, config.overwrite)
        mark_unfinished(out)
        pose_plan = plan_poses(config.poses, source)
        say(f"input: {source.description}")
    why = stream_reason(config, source, pose_plan)
    if why is not None:
        from .poses import TrackingLostError
        from .stream import run_streamed

        say(why)
        try:
            return run_streamed(config, source, out, pose_plan, (intrinsics, intrinsics_from), say)
        except TrackingLostError as err:
            if not (_streamed_as_video(config, source, pose_plan) and config.pose_method == "auto"
                    and err.sfm_may_help):
                raise
            # The one-shot run can still try SfM, which the streamed front end cannot.
            log.warning("the streamed front end lost the camera (%s); running the video at once, with SfM "
                        "as the fallback", err)
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

    if pose_plan.estimated and config.on_break != "keep":
        stretch = trajectory_stretches(pose_stage.info, len(pose_stage.poses))
        stretch = stretch if pose_stage.keep is None else stretch[pose_stage.keep]
        if stretch.max() > 0 and config.join_segments:
            stretch, poses, joins = join_breaks(stretch, seq.poses, np.arange(len(seq)),
                                                lambda p: (seq.rgb[p], seq.prior_depth[p]), seq.intrinsics)
            seq, pose_stage = seq.with_(poses=poses), replace(pose_stage, info={**pose_stage.info, "joins": joins})
            say_joins(joins)
        if stretch.max() > 0:
            if config.on_break == "stop":
                stop_at_breaks(pose_stage.info)
            return _run_segments(out, seq, stretch, pose_stage, timer, say, lambda piece, piece_out: _reconstruct(
                config, piece_out, source, piece, pose_stage, pose_plan, intrinsics_from, prior, StageClock(),
                tracking, say))
    return _reconstruct(config, out, source, seq, pose_stage, pose_plan, intrinsics_from, prior, timer, tracking, say)


def _reconstruct(config: PipelineConfig, out: OutputFolder, source, seq: Sequence, pose_stage, pose_plan,
                 intrinsics_from: str, prior, timer: StageClock, tracking, say) -> PipelineResult:
    """The stages after the poses (undistortion, MEDeA, refinement, fusion, export, Rerun,
    report) on the posed sequence, into ``out``."""
    from .fusion import fuse

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
            depth, medea_result = adjust_with_medea(seq, config.medea, config.features, config.progress)
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
    fusion_options = FusionOptions(**{**asdict(config.fusion), "device": config.device, "progress": config.progress})
    with timer.stage("fusion"):
        confidence = None if refined is None else fusion_confidence(refined)
        if refined is not None:
            # Their use is over (the confidence is made; a later call's `known` is the
            # streamed run's): a frame's worth each, dropped before the volume is built.
            refined.support, refined.swept = None, None
            release_memory(force=True)
        if fusion_options.min_confidence is None:
            fusion_options.min_confidence = default_min_confidence(pose_plan.estimated)
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
    recon.segments.trajectory_stretches) reconstructed stretch by stretch into
    ``OUT/segment_NN/`` (``reconstruct(piece, its folder)``), with one summary report.json;
    the result of the whole run is the largest piece's, with ``segments``. A stretch of fewer
    than two frames is left out with a warning (recon.stream does the same for a streamed run)."""
    pieces = []
    for k in range(int(stretch.max()) + 1):
        mine = np.flatnonzero(stretch == k)
        if len(mine) < 2:
            log.warning("%d frame(s) of stretch %d of the trajectory are left out: too few to reconstruct",
                        len(mine), k)
            continue
        name = f"segment_{len(pieces):02d}"
        piece = seq.take(mine)
        say(f"{name}: frames {int(piece.indices[0])}-{int(piece.indices[-1])}")
        pieces.append(reconstruct(piece, OutputFolder(out.path / name, overwrite=True)))
    if not pieces:
        raise ReconInputError("no stretch of the trajectory between its scale breaks has two frames "
                              "(--on-break keep writes the trajectory as one)")
    largest = max(pieces, key=lambda p: len(p.frames))
    summary = segments_summary(largest.report, pieces, pose_stage.info)
    summary["seconds"] = {**timer.seconds, **summary["seconds"]}
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
    selected frame, dropped ones included (see recon.stages.tracking_states), or None."""
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
    """Log to Rerun in the configured mode: (server URL or None, .rrd path or None).

    A saved recording goes to a temporary name first, like every other output file.
    """
    from viewer import RerunLogger

    def log_all(logger):
        log_to_rerun(logger, seq, depth, mesh, medea_result, config.progress, refined, tracking)

    if config.rerun == "save":
        if config.rerun_path is None:
            with out.atomic(RECORDING) as tmp:
                with RerunLogger("save", tmp, max_width=config.rerun_max_width) as logger:
                    log_all(logger)
            return None, out.path_for(RECORDING)
        with atomic_path(config.rerun_path, overwrite=config.overwrite) as tmp:
            with RerunLogger("save", tmp, max_width=config.rerun_max_width) as logger:
                log_all(logger)
        return None, Path(config.rerun_path)
    logger = RerunLogger(config.rerun, max_width=config.rerun_max_width)
    log_all(logger)
    logger.close()
    return logger.url, None


def format_summary(result) -> str:
    """The closing summary `recon run` prints: frames, time per stage, mesh, files (of a
    PipelineResult or a streamed run's StreamResult)."""
    frames = result.report["frames"]
    n = max(1, frames["count"])
    total = sum(result.seconds.values())
    lines = [f"{'stage':<10}{'seconds':>10}{'s/frame':>10}"]
    for stage in STAGES:
        if stage in result.seconds:
            s = result.seconds[stage]
            lines.append(f"{stage:<10}{s:>10.1f}{s / n:>10.3f}")
    lines.append(f"{'total':<10}{total:>10.1f}{total / n:>10.3f}")
    mesh = result.fusion.mesh
    w, h = frames["working_size"]
    counted = f"{frames['count']} frames" if "depth_frames" not in frames else \
        f"{frames['count']} frames tracked, {frames['depth_frames']} with depth"
    lines.append(
        f"{counted} at {w}x{h}; mesh {len(mesh.vertices)} vertices, {len(mesh.triangles)} triangles "
        f"(voxel {result.fusion.voxel_size * 1000:.1f} mm)"
    )
    lines.append(f"output: {result.output}")
    for label, path in result.files.items():
        lines.append(f"  {label:<12}{path}")
    if result.rerun_url:
        lines.append(f"rerun: {result.rerun_url}")
    return "\n".join(lines)


__all__ = ["STAGES", "PipelineConfig", "PipelineResult", "format_summary", "log_to_rerun", "run_pipeline"]
