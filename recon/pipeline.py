"""The whole reconstruction: one typed configuration, the input opened, a driver chosen.

This module owns what comes before the stages and the choice between the two drivers: the
configuration checked, the input opened and its frames selected, the intrinsics and lens
the user gave, the output folder (checked before any heavy work, marked unfinished until the
run ends), the pose source, then one driver of :mod:`recon.drivers`: one-shot (every frame in
memory) or streamed (memory flat on long videos; :func:`stream_reason`). Both run the stages
of :mod:`recon.core.stages` and write the report of :mod:`recon.core.report`. The stages, in
order, and where the intrinsics come from: docs/running.md#the-stages-of-a-run.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

from .core.clock import StageClock
from .core.config import PipelineConfig
from .core.stages import budget_capacity, given_intrinsics, plan_poses, select_frames, undistort_known_lens
from .drivers.oneshot import PipelineResult, run_oneshot
from .drivers.result import RunResult
from .drivers.streamed import StreamResult, run_streamed
from .io.earlier_run import earlier_run_files, remove_earlier_run
from .io.output_folder import UNFINISHED, OutputFolder, mark_finished, mark_unfinished, stale_results
from .memory import release_memory
from .poses import TrackingLostError

log = logging.getLogger(__name__)

STAGES = ("decode", "prior", "poses", "undistort", "medea", "refine", "fusion", "export", "logging")


def run_pipeline(config: PipelineConfig, on_stage: Callable[[str], None] | None = None) -> RunResult:
    """Run every stage (module docstring) and write the output folder; returns what was made:
    a recon.drivers.result.RunResult (output, poses, intrinsics, depth, fusion, seconds,
    files, report, rerun_url, segments), of the one-shot driver (a PipelineResult, with the
    frames and depth in memory) or the streamed one (a StreamResult; its depth read back from
    disk: its depth frames).

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
    video files whose poses are estimated (the streamed run gives depth only to the frames
    the camera moved to reach). SfM needs every frame at once, and a rolling shutter with
    estimated poses needs the trajectory estimated a second time: neither is streamed by
    that rule. why: docs/decisions.md#streamed-or-one-shot
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


def _run_stages(config: PipelineConfig, on_stage) -> RunResult:
    """The input opened and checked (the ``decode`` stage), then the driver that runs the rest."""
    config.validate()
    say = on_stage or (lambda _: None)
    timer = StageClock()
    # What an earlier run wrote there (its report.json's list), removed once this run has
    # finished where it was not written again: --overwrite replaces recon's own results.
    started, earlier = time.time(), earlier_run_files(config.output) if config.overwrite else []
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
        say(why)
        try:
            return _said_stale(out, run_streamed(config, source, out, pose_plan, (intrinsics, intrinsics_from), say),
                               earlier, started)
        except TrackingLostError as err:
            if not (_streamed_as_video(config, source, pose_plan) and config.pose_method == "auto"
                    and err.sfm_may_help):
                raise
            # The one-shot run can still try SfM, which the streamed front end cannot.
            log.warning("the streamed front end lost the camera (%s); running the video at once, with SfM "
                        "as the fallback", err)
        # What the streamed attempt held (frames, flow graph) is garbage now, some of it in
        # reference cycles through the exception's frames: freed before the one-shot run
        # holds every frame (Record3D 0-79: 3.06 GB without this).
        release_memory(force=True)
    return _said_stale(out, run_oneshot(config, source, out, pose_plan, (intrinsics, intrinsics_from), say, timer),
                       earlier, started)


def _said_stale(out: OutputFolder, result: RunResult, earlier: list[Path], started: float) -> RunResult:
    """The result, once the files an earlier run wrote (``earlier``: its report's list) and
    this one did not write again (since ``started``) are removed, after a warning naming
    any other result left in the folder (``--overwrite``)."""
    removed = remove_earlier_run(out.path, earlier, started)
    if removed:
        log.info("%s: removed %d files an earlier run wrote and this one did not", out.path, len(removed))
    stale = stale_results(out.path, [p.output.name for p in result.segments])
    if stale:
        log.warning("%s: %s left by an earlier run, not part of this one (report.json lists what this run "
                    "wrote); remove them, or write to an empty folder", out.path, ", ".join(stale))
    return result


def format_summary(result: RunResult) -> str:
    """The closing summary `recon run` prints: frames, time per stage, mesh, files."""
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


__all__ = ["STAGES", "PipelineConfig", "PipelineResult", "RunResult", "StreamResult", "format_summary",
           "run_pipeline", "stream_reason"]
