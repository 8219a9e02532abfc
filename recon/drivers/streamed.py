"""The streamed pipeline: a long video flows through the stages in memory that does not grow
with its length.

Two passes, as in DROID-SLAM (tracking, then the global optimisation before the dense map
is trusted): ``track`` (:mod:`recon.drivers.stream_track`) decodes, gives priors, tracks and
closes the trajectory; ``depth`` (:mod:`recon.drivers.stream_depth`) adjusts, refines and fuses
the depth frames window by window. This module runs the two into an output folder and
writes the mesh, trajectory and report at the end. Memory holds per-frame poses, the
keyframes, one window and the TSDF volume.
More: docs/running.md#how-a-streamed-run-works
"""

from __future__ import annotations

import logging
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..core.clock import StageClock
from ..core.config import PipelineConfig
from ..core.report import segments_summary, segments_warning
from ..core.stages import PosePlan, PoseStage, shutter_summary, tracking_states, window_frames
from ..errors import ReconInputError
from ..geometry.rolling_shutter import angular_velocity
from ..io.frame_store import FrameStore
from ..io.output_folder import DEPTH_DIR, REPORT_JSON, OutputFolder, segment_name
from ..io.source import FrameSource
from .recording import open_recording
from .result import RunResult
from .segments import settle_breaks, trajectory_stretches
from .stream_depth import depth_windows
from .stream_track import TrackedVideo, track_video

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class StreamResult(RunResult):
    """A streamed run's result (RunResult): frames_tracked, the frames the trajectory
    covers (its poses; NaN for frames left out); depth_frames, those that got depth."""

    frames_tracked: int
    depth_frames: int

    @property
    def frame_count(self) -> int:
        return self.frames_tracked

    @property
    def depth(self) -> np.ndarray:
        """(D, H, W) metres: the depth of the frames that got depth (``report["frames"]
        ["depth_indices"]``), read back from the output folder (a streamed run keeps no depth in
        memory), so that code written for a one-shot run's ``PipelineResult.depth`` runs on
        both. Of a run written as segments: the largest segment's."""
        from ..io.output_folder import load_output

        folder = max(self.segments, key=lambda p: p.depth_frames).output if self.segments else self.output
        return load_output(folder).depth


# --------------------------------------------------------------------------- entry point


def run_streamed(config: PipelineConfig, source: FrameSource, out: OutputFolder, pose_plan: PosePlan,
                 given: tuple[tuple | None, str], say: Callable[[str], None]) -> StreamResult:
    """Both passes (module docstring) into ``out``; given: (intrinsics or None, their source)."""
    clock = StageClock()
    if config.rolling_shutter > 0 and pose_plan.estimated:
        log.warning("--rolling-shutter is not applied in a streamed run with estimated poses (the trajectory "
                    "would have to be estimated again on the resampled frames); the frames are used as "
                    "recorded (--stream off applies it)")
    with ExitStack() as stack:
        store = stack.enter_context(FrameStore())
        logger, rec_path = open_recording(config, out, stack)
        say("tracking (streamed)")
        video = track_video(config, source, pose_plan, given, store, logger, clock)
        stretch = np.zeros(len(video.indices), np.int64)
        if pose_plan.estimated:
            stretch, poses, info = settle_breaks(config, trajectory_stretches(video.pose_info, len(video.indices)),
                                                 video.poses, np.flatnonzero(video.depth_frame),
                                                 lambda p: (store.get(p, "rgb"), store.get(p, "prior")),
                                                 video.intrinsics, video.pose_info)
            video = replace(video, poses=poses, pose_info=info)
            if logger is not None:
                # Each frame's tracking state and verdicts, once the trajectory is settled (as at once).
                stage = PoseStage(video.poses, video.intrinsics, video.pose_source, video.pose_info)
                for index, state, pose in tracking_states(stage, video) or []:
                    logger.log_tracking(index, state, pose)
        if stretch.max() > 0:
            result = _run_segments(config, source, out, pose_plan, video, stretch, store, logger, clock, say)
            result.rerun_url = logger.url if logger is not None else None
            return _with_summary(result, out, rec_path)
        say(f"depth: {int(video.depth_frame.sum())} of {len(video.indices)} frames in windows of "
            f"{window_frames(config, video.size)}")
        omega = _turn_rate(config, pose_plan, video, say)
        volume, windows, shifts = depth_windows(config, video, pose_plan, store, out, logger, clock, omega)
        if omega is not None and shifts:
            at = np.array(sorted(shifts))
            summary = shutter_summary(omega[at], np.array([shifts[p] for p in at]), config.rolling_shutter)
            video = replace(video, pose_info={**video.pose_info, "rolling_shutter": summary})
        say("export")
        result = _finish(config, source, out, video, volume, windows, clock, logger, store.bytes_written)
        url = logger.url if logger is not None else None
    result.rerun_url = url
    return _with_summary(result, out, rec_path)


def _with_summary(result: StreamResult, out: OutputFolder, rec_path: Path | None) -> StreamResult:
    """The run's report.json written (with the recording's path, when one was saved)."""
    if rec_path is not None:
        result.files["recording"] = rec_path
    result.files["report"] = out.write_json(REPORT_JSON, _with_files(result.report, result.files, out))
    return result


def _run_segments(config: PipelineConfig, source: FrameSource, out: OutputFolder, pose_plan: PosePlan,
                  video: TrackedVideo, stretch: np.ndarray, store: FrameStore, logger, clock: StageClock,
                  say) -> StreamResult:
    """A trajectory whose scale breaks (``stretch``: (N,) the stretch of each tracked frame,
    recon.drivers.segments.trajectory_stretches) reconstructed stretch by stretch, each in
    ``OUT/segment_NN/`` with its own trajectory, depth, mesh and report, and one summary
    (the StreamResult of the whole run: its ``segments``, its mesh the largest one's). A
    stretch with fewer than two depth frames is left out with a warning. Where one stretch
    sits against the next is what broke: the segments share no frame of reference that can
    be trusted, so none is fused with another."""
    pieces: list[StreamResult] = []
    for k in range(int(stretch.max()) + 1):
        mine = stretch == k
        frames = video.indices[mine]
        if (video.depth_frame & mine).sum() < 2:
            log.warning("frames %d-%d (stretch %d of the trajectory) have fewer than two depth frames and are left "
                        "out", frames[0], frames[-1], k)
            continue
        name = segment_name(len(pieces))
        posed = video.indices[mine & np.isfinite(video.poses).all(axis=(1, 2))]  # as its report names them
        say(f"{name}: frames {posed[0]}-{posed[-1]}")
        part = replace(video, poses=np.where(mine[:, None, None], video.poses, np.nan),
                       depth_frame=video.depth_frame & mine)
        part_out = OutputFolder(out.path / name, overwrite=True)
        part_clock = StageClock(started=clock.started)
        volume, windows, _ = depth_windows(config, part, pose_plan, store, part_out, logger, part_clock)
        piece = _finish(config, source, part_out, part, volume, windows, part_clock, logger, store.bytes_written)
        piece.files["report"] = part_out.write_json(REPORT_JSON, _with_files(piece.report, piece.files, part_out))
        pieces.append(piece)
    if not pieces:
        raise ReconInputError("no stretch of the trajectory between its scale breaks has two depth frames "
                              "(report.json is not written; --on-break keep writes the trajectory as one)")
    largest = max(pieces, key=lambda p: p.depth_frames)
    summary = segments_summary(largest.report, pieces, {"source": video.pose_source, **video.pose_info,
                                                        "lens_k1": video.lens_k1}, clock.seconds)
    summary["frames"]["tracked"] = len(video.indices)
    log.warning(segments_warning(summary))
    files = {p.output.name: p.output for p in pieces}
    return StreamResult(output=out.path, frames_tracked=len(video.indices),
                        depth_frames=summary["frames"]["depth_frames"], poses=video.poses,
                        intrinsics=video.intrinsics, fusion=largest.fusion,
                        seconds=dict(summary["seconds"]), files=files, report=summary, segments=pieces)


def _turn_rate(config: PipelineConfig, pose_plan: PosePlan, video: TrackedVideo, say) -> np.ndarray | None:
    """The body angular velocity (N, 3) of every tracked frame when the depth frames are to be
    resampled for a rolling shutter (given poses: they do not depend on the frames), else None."""
    if config.rolling_shutter <= 0 or pose_plan.estimated:
        return None
    say(f"depth frames resampled for a {config.rolling_shutter:g} ms rolling shutter")
    return angular_velocity(video.poses, video.timestamps)


# --------------------------------------------------------------------------- export and report


def _finish(config, source, out: OutputFolder, video: TrackedVideo, fusion_state, windows, clock, logger,
            store_bytes: int):
    from ..core.report import stream_report
    from ..export import export_reconstruction
    from ..fusion import FusionResult
    from ..fusion.tsdf import finished_mesh
    from ..fusion.upright import estimate_upright

    (volume, options) = fusion_state
    start = time.perf_counter()
    with clock.stage("fusion"):
        mesh, cloud, removed, full, weight = finished_mesh(volume, options, config.refine != "none")
    fusion = FusionResult(mesh=mesh, point_cloud=cloud, voxel_size=volume.voxel, trunc=volume.trunc,
                          seconds=time.perf_counter() - start, max_depth=volume.max_depth,
                          frames_fused=volume.frames_fused, block_estimate=0, blocks_used=volume.blocks_used,
                          fragments_removed=removed, triangles_full=full,
                          upright=estimate_upright(video.poses, np.asarray(mesh.vertices)),
                          weight_threshold=weight)
    kept = np.isfinite(video.poses).all(axis=(1, 2))
    with clock.stage("export"):
        files = export_reconstruction(out, mesh=mesh, poses=video.poses[kept], timestamps=video.timestamps[kept],
                                      intrinsics=video.intrinsics, shape=video.size, point_cloud=cloud,
                                      glb=config.glb, glb_rotation=fusion.upright.rotation)
        files["depth"] = out.path / DEPTH_DIR
    if logger is not None:
        with clock.stage("logging"):
            last = int(video.indices[-1])
            if len(mesh.triangles):
                logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                                np.asarray(mesh.vertex_colors), index=last)
    report = stream_report(config=config, source=source, video=video, windows=[asdict(w) for w in windows],
                           fusion=fusion, min_confidence=options.min_confidence if config.refine != "none" else None,
                           seconds=clock.seconds, store_bytes=store_bytes,
                           first_result_s=clock.marks.get("first_result"))
    return StreamResult(output=out.path, frames_tracked=len(video.indices), depth_frames=int(video.depth_frame.sum()),
                        poses=video.poses, intrinsics=video.intrinsics, fusion=fusion, seconds=dict(clock.seconds),
                        files=files, report=report)


def _with_files(report: dict, files: dict, out: OutputFolder) -> dict:
    return {**report, "files": {k: str(Path(v).relative_to(out.path)) if Path(v).is_relative_to(out.path) else str(v)
                                for k, v in files.items()}}


__all__ = ["StreamResult", "TrackedVideo", "run_streamed", "track_video", "depth_windows"]

