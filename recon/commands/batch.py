"""`recon batch`: many inputs through the pipeline on Ray, one output folder each.

This module owns what a batch adds to `recon run`: each input's folder
``OUT/<input name without suffix>`` (name-2, name-3, ... in input order), skipping an input
whose folder holds its ``report.json`` (a folder without one is run again into), the Ray task
per input (its resources as Ray resources, an :class:`Outcome` naming its node instead of an
exception, so one bad input never stops the others) and the rows of ``OUT/batch.json``,
rewritten as each input finishes. Joining a cluster, the checks before any input runs, lost
nodes and the progress line: recon.commands.batch_cluster.
More: docs/running.md#many-videos-recon-batch
"""

from __future__ import annotations

import logging
import socket
import time
import traceback
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

from ..choices import POSE_CHOICES
from ..core.config import PipelineConfig, device_index
from ..errors import ReconInputError
from ..io.output_folder import REPORT_JSON, atomic_write_bytes, json_bytes, read_report
from .batch_cluster import (
    DONE,
    FAILED,
    PENDING,
    SKIPPED,
    BatchOptions,
    Progress,
    check_resources,
    cluster_slots,
    default_gpus_per_task,
    format_progress,
    format_table,
    import_ray,
    lost_node_id,
    node_label,
    node_lost,
    ray_session,
    task_resources,
    this_node,
)

log = logging.getLogger(__name__)

BATCH_JSON = "batch.json"



@dataclass
class Job:
    """One input of the batch: as the user gave it (label), absolute, and its output folder."""

    label: str
    input: Path
    output: Path


@dataclass
class Outcome:
    """What became of one input: a row of the summary and of batch.json.

    status: "done" (run now), "skipped" (done by an earlier run), "failed", or "pending" (in
    batch.json while the batch runs); seconds: this run's wall time (None when skipped);
    frames, vertices, triangles: from the run or the earlier report; error: one line;
    detail: the traceback of an unexpected error; warnings: what recon warned about while
    running it; node, host: the Ray node id and host name that ran it; attempts: tasks
    started for it; lost_nodes: the nodes that left the cluster while running it.
    """

    input: str
    output: str
    status: str
    seconds: float | None = None
    frames: int | None = None
    vertices: int | None = None
    triangles: int | None = None
    error: str | None = None
    detail: str | None = None
    warnings: list[str] = field(default_factory=list)
    node: str | None = None
    host: str | None = None
    attempts: int = 0
    lost_nodes: list[str] = field(default_factory=list)

    @property
    def result(self) -> str:
        """The summary table's last column."""
        if self.status == SKIPPED:
            return "skipped: done"
        return self.error if self.status == FAILED else "ok"


# --------------------------------------------------------------------------- planning


def _base_name(path: Path) -> str:
    # A folder's name is kept whole: dataset folders carry dots ("scene.v2") that are no suffix.
    name = path.name if path.is_dir() else path.stem
    return name or "input"


def output_names(inputs: list[Path]) -> list[str]:
    """Each input's output folder name, in order: its name without suffix; a name taken by an
    earlier input (compared ignoring case, as macOS and Windows file systems do) gets -2, -3, ..."""
    taken: set[str] = set()
    names = []
    for path in inputs:
        base = name = _base_name(path)
        k = 1
        while name.lower() in taken:
            k += 1
            name = f"{base}-{k}"
        taken.add(name.lower())
        names.append(name)
    return names


def plan_jobs(inputs: list[str], out) -> list[Job]:
    """One Job per input, paths made absolute: the tasks may run in another folder or on
    another machine, where only absolute paths mean the same file."""
    paths = [Path(text).expanduser().absolute() for text in inputs]
    out = Path(out).expanduser().absolute()
    return [Job(str(text), path, out / name) for text, path, name in zip(inputs, paths, output_names(paths))]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.resolve() == b.resolve()
    except OSError:
        return False


def earlier_outcome(job: Job) -> Outcome | None:
    """The outcome of an input that needs no task: done by an earlier run (skipped, even if
    the input is gone since), or missing (failed); None when it must run."""
    try:
        report = read_report(job.output)
    except (ReconInputError, OSError):
        report = None  # unreadable report: an incomplete folder, run again
    if report is None:
        if not job.input.exists():
            return Outcome(job.label, str(job.output), FAILED, error=f"{job.label}: no such file or folder")
        return None
    done_input = Path((report.get("input") or {}).get("path") or job.input)
    if not _same_file(done_input, job.input):
        # Names are given in input order: a reordered input list would point an input at
        # another one's result. Refuse rather than skip or overwrite it.
        return Outcome(job.label, str(job.output), FAILED,
                       error=f"{job.output / REPORT_JSON}: the result of {done_input}, not of this input (give the "
                             f"inputs in the earlier order, or another -o)")
    fusion = report.get("fusion") or {}
    return Outcome(job.label, str(job.output), SKIPPED, frames=(report.get("frames") or {}).get("count"),
                   vertices=fusion.get("vertices"), triangles=fusion.get("triangles"))


def job_config(template: PipelineConfig, job: Job) -> PipelineConfig:
    """The template with this input and output. A folder left by a broken run (files but no
    report.json) is written over: it is this batch's own folder."""
    incomplete = job.output.is_dir() and any(job.output.iterdir())
    return replace(template, input=job.input, output=job.output, overwrite=incomplete)


def batch_template(template: PipelineConfig) -> PipelineConfig:
    """The template as every task gets it: files it names made absolute (a task's working
    folder may differ), no progress bars (a task's output goes to Ray's log files)."""
    if template.rerun not in ("off", "save") or template.rerun_path is not None:
        raise ReconInputError("a batch saves each input's Rerun recording as OUT/<name>/recording.rrd, or none: "
                              f"rerun must be 'off' or 'save' without a path, got {template.rerun!r}")

    def absolute(path):
        return None if path is None else Path(path).expanduser().absolute()

    poses = template.poses if template.poses in POSE_CHOICES else str(absolute(template.poses))
    return replace(template, prior_path=absolute(template.prior_path), weights=absolute(template.weights),
                   poses=poses, progress=False)


# --------------------------------------------------------------------------- the task


class _WarningList(logging.Handler):
    """Collects recon's warnings inside a task: the worker's own output is not forwarded to
    the user's terminal, so they travel back with the outcome."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _task_device(device: str, gpus: float) -> str:
    # Ray shows a task only the GPUs it was given, numbered from 0: "cuda:N" of the user's
    # machine means the task's own GPU there. Without a GPU of its own, auto means the CPU.
    if device == "auto":
        import torch

        return "cuda" if gpus > 0 and torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and gpus > 0:
        return "cuda"
    return device


def _with_device(config: PipelineConfig, device: str) -> PipelineConfig:
    medea = replace(config.medea, device=device)
    return replace(config, device=device, medea=medea)


def _failure(job_input: str, output: str, error: BaseException, start: float) -> Outcome:
    if isinstance(error, ReconInputError):
        return Outcome(job_input, output, FAILED, time.perf_counter() - start, error=str(error))
    return Outcome(job_input, output, FAILED, time.perf_counter() - start,
                   error=f"{type(error).__name__}: {error}", detail=traceback.format_exc())


def run_input(label: str, config: PipelineConfig, threads: int, gpus: float) -> Outcome:
    """Run one input (the body of a Ray task); every error comes back in the Outcome, with
    the node that ran it."""
    import cv2
    import torch

    from ..pipeline import run_pipeline

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    warnings = _WarningList()
    recon_log = logging.getLogger("recon")
    recon_log.addHandler(warnings)
    start = time.perf_counter()
    try:
        result = run_pipeline(_with_device(config, _task_device(config.device, gpus)))
        mesh = result.fusion.mesh
        # One-shot or streamed (recon.drivers.streamed), as a skipped row reads it.
        frames = result.report["frames"]["count"]
        outcome = Outcome(label, str(config.output), DONE, time.perf_counter() - start, frames=frames,
                          vertices=len(mesh.vertices), triangles=len(mesh.triangles))
    except Exception as error:
        outcome = _failure(label, str(config.output), error, start)
    finally:
        recon_log.removeHandler(warnings)
    outcome.warnings = warnings.messages
    outcome.node, outcome.host = this_node(), socket.gethostname()
    return outcome


def lost_task(job: Job, error: Exception) -> Outcome:
    """The outcome of a task that did not come back: its worker died (out of memory, a crash
    in native code) or its node left the cluster. How long it ran is not known here."""
    cause = getattr(error, "cause", None) or error  # a task's own exception, when Ray wrapped one
    first_line = (str(cause).strip().splitlines() or [""])[0]
    return Outcome(job.label, str(job.output), FAILED,
                   error=f"task lost: {type(cause).__name__}: {first_line}", detail=str(error))


# --------------------------------------------------------------------------- the batch


def run_batch(inputs: list[str], out, template: PipelineConfig, options: BatchOptions,
              on_done: Callable[[Outcome, Progress], None] | None = None) -> list[Outcome]:
    """Run every input on Ray; returns one Outcome per input, in input order. OUT/batch.json
    holds the same rows, rewritten as each input finishes (those not finished yet: "pending"),
    so that a killed driver leaves a true record. on_done(outcome, progress) is called as each
    input finishes (progress: the count k of n and the time left).

    Missing inputs and completed outputs start no task; all other inputs run as Ray tasks.
    """
    import_ray()  # the missing package is the first thing to hear about
    options.validate()
    device_index(template.device)  # only its spelling: the GPU is the task's, on the node Ray picks
    template.validate()  # the run options, once, before any task (e.g. --prior hf without a model folder)
    template = batch_template(template)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ReconInputError(f"{out}: output path exists and is not a folder")
    jobs = plan_jobs(inputs, out)
    outcomes: dict[int, Outcome] = {}
    progress = Progress(len(jobs))

    def rows() -> list[Outcome]:
        return [outcomes.get(i) or Outcome(job.label, str(job.output), PENDING) for i, job in enumerate(jobs)]

    def finished(index: int, outcome: Outcome, ran: bool) -> None:
        outcomes[index] = outcome
        progress.add(outcome.seconds, ran)
        if ran:
            write_batch_json(out, rows())
        if on_done is not None:
            on_done(outcome, progress)

    todo = []
    for index, job in enumerate(jobs):
        outcome = earlier_outcome(job)
        if outcome is None:
            todo.append(index)
        else:
            finished(index, outcome, ran=False)
    try:
        write_batch_json(out, rows())  # creates OUT, which the cluster's nodes are checked against
    except OSError as error:
        raise ReconInputError(f"{out}: cannot write the batch's record there ({type(error).__name__}: "
                              f"{error.strerror or error})") from None
    if todo:
        with ray_session(options, out) as ray:
            progress.slots = cluster_slots(ray, options)
            _run_tasks(ray, jobs, todo, template, options, finished, progress)
    return rows()


def _remote_runner(ray, options: BatchOptions):
    resources = {"num_cpus": options.cpus_per_task, "num_gpus": options.gpus_per_task,
                 # Ray retries nothing: a dead worker (out of memory, a native crash) would most
                 # likely die again (the next `recon batch` retries the input anyway), and an input
                 # whose node left the cluster is run again by _run_tasks.
                 "max_retries": 0,
                 # Each input in a fresh worker process: what one input leaves in the process
                 # (torch's allocator, Open3D's buffers) is not carried into the next one's
                 # --memory-per-task; the start costs about 3 s on 2 cores against minutes per input.
                 "max_calls": 1}
    if "memory" in task_resources(options):
        resources["memory"] = int(task_resources(options)["memory"])
    return ray.remote(**resources)(run_input)


def _run_tasks(ray, jobs: list[Job], todo: list[int], template: PipelineConfig, options: BatchOptions,
               finished: Callable[[int, Outcome, bool], None], progress: Progress) -> None:
    runner = _remote_runner(ray, options)
    threads = max(1, int(options.cpus_per_task))
    lost: dict[int, list[str]] = {i: [] for i in todo}

    def submit(index: int):
        # job_config again on a retry: the lost node's partial folder is this batch's to overwrite.
        return runner.remote(jobs[index].label, job_config(template, jobs[index]), threads, options.gpus_per_task)

    pending = {submit(i): i for i in todo}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            index = pending.pop(ref)
            job = jobs[index]
            try:
                outcome = _checked(ray.get(ref), job)
            except ray.exceptions.RayError as error:
                if not node_lost(ray, error) or len(lost[index]) >= options.node_retries:
                    outcome = lost_task(job, error)
                else:
                    node = lost_node_id(error)
                    lost[index].append(node or "unknown")
                    progress.slots = cluster_slots(ray, options)
                    outcome = _after_lost_node(job, node)
                    if outcome is None:
                        log.warning("%s: %s left the cluster while running it; running it again", job.label,
                                    node_label(node, None))
                        pending[submit(index)] = index
                        continue
            # Tasks started for it: the lost ones, and the one that came back (none when the
            # lost node had written report.json before it went away).
            outcome.attempts = len(lost[index]) + (outcome.node is None or outcome.node not in lost[index])
            outcome.lost_nodes = list(lost[index])
            finished(index, outcome, True)


def _checked(outcome: Outcome, job: Job) -> Outcome:
    """A task's outcome as the driver sees it: "done" only when report.json is there too (a node
    writing to a folder of its own that this machine does not see is a failure)."""
    if outcome.status == DONE and not (job.output / REPORT_JSON).is_file():
        outcome.status = FAILED
        outcome.error = (f"{job.output / REPORT_JSON}: not found here although {node_label(outcome.node, outcome.host)}"
                         f" finished the input; the output folder must be a path every node sees (a shared file "
                         f"system)")
    return outcome


def _after_lost_node(job: Job, node: str | None) -> Outcome | None:
    """An input whose node left the cluster: done after all (on that node) when its report.json
    was written before the node went away, else None (run it again)."""
    earlier = earlier_outcome(job)
    if earlier is None:
        return None
    if earlier.status == SKIPPED:
        earlier.status, earlier.node = DONE, node
    return earlier


def write_batch_json(out: Path, rows: list[Outcome]) -> Path:
    """OUT/batch.json: counts and one row per input (atomic: a reader sees the old or the new one)."""
    out.mkdir(parents=True, exist_ok=True)
    counts = {status: sum(r.status == status for r in rows) for status in (DONE, SKIPPED, FAILED, PENDING)}
    return atomic_write_bytes(out / BATCH_JSON, json_bytes({"inputs": len(rows), **counts,
                                                            "rows": [asdict(r) for r in rows]}), overwrite=True)


__all__ = [
    "BATCH_JSON",
    "DONE",
    "FAILED",
    "PENDING",
    "SKIPPED",
    "BatchOptions",
    "check_resources",
    "Job",
    "Outcome",
    "default_gpus_per_task",
    "earlier_outcome",
    "format_progress",
    "format_table",
    "output_names",
    "plan_jobs",
    "run_batch",
    "run_input",
]
