"""`recon batch`: many inputs through the pipeline on Ray, one output folder each.

This module owns what a batch adds to `recon run`:

* the output folder of each input, ``OUT/<input name without suffix>`` (a name taken by an
  earlier input becomes name-2, name-3, ...: the same inputs in the same order always get
  the same folders);
* what a second run skips: an input whose folder holds ``report.json`` (the pipeline writes
  it last, so its presence means the rest is there) of that same input. A folder without
  it was left by a failed or killed run: it is ours, and the input is run again into it
  with ``overwrite``;
* the Ray task that runs one input (its CPUs, GPUs and memory as Ray resources, torch's
  threads set to its CPUs) and hands back an :class:`Outcome` instead of raising, so one
  bad input never stops the others; a task whose worker dies comes back as a failure too;
* what the user reads: one line per input as it finishes, the summary table, and
  ``OUT/batch.json`` with the same rows.

Ray is imported only when a batch runs (:func:`import_ray`), so the rest of recon needs none.
The command line's options become the :class:`~recon.core.config.PipelineConfig` template in
recon.commands.cli; every input gets a copy with its own input and output.
"""

from __future__ import annotations

import logging
import socket
import time
import traceback
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

from ..choices import POSE_CHOICES
from ..core.config import PipelineConfig, device_index
from ..errors import ReconInputError
from ..io.output_folder import REPORT_JSON, atomic_write_bytes, json_bytes, read_report

log = logging.getLogger(__name__)

BATCH_JSON = "batch.json"
RAY_MISSING = "recon batch needs Ray: pip install -e .[batch]"
# The tasks pass only configurations and outcomes (kilobytes) through Ray's object store;
# a small store leaves the local machine's memory to the pipelines.
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20

DONE, SKIPPED, FAILED = "done", "skipped", "failed"


@dataclass
class BatchOptions:
    """Where the tasks run and what each asks Ray for.

    address: an existing Ray cluster to join ("auto", "HOST:6379", "ray://HOST:10001");
    None starts a local Ray instance with num_cpus CPUs (None: all of this machine's).
    cpus_per_task, gpus_per_task, memory_per_task (GiB, None: no reservation): Ray
    resources of each input's task; torch uses cpus_per_task threads in it.
    """

    address: str | None = None
    num_cpus: int | None = None
    cpus_per_task: int = 2
    gpus_per_task: float = 0.0
    memory_per_task: float | None = None

    def validate(self) -> None:
        if self.address is not None and self.num_cpus is not None:
            raise ReconInputError("--num-cpus sizes the local Ray instance; a cluster joined with --address has "
                                  "its own CPUs")
        if self.cpus_per_task < 1:
            raise ReconInputError(f"--cpus-per-task must be >= 1, got {self.cpus_per_task}")
        if self.gpus_per_task < 0:
            raise ReconInputError(f"--gpus-per-task must be >= 0, got {self.gpus_per_task}")
        if self.memory_per_task is not None and self.memory_per_task <= 0:
            raise ReconInputError(f"--memory-per-task must be > 0 GB, got {self.memory_per_task}")
        if self.num_cpus is not None and self.num_cpus < self.cpus_per_task:
            raise ReconInputError(f"--num-cpus {self.num_cpus} is fewer than one task's --cpus-per-task "
                                  f"{self.cpus_per_task}")


def default_gpus_per_task(device: str) -> float:
    """One GPU per task when the device asks for CUDA, else none."""
    return 1.0 if device.startswith("cuda") else 0.0


@dataclass
class Job:
    """One input of the batch: as the user gave it (label), absolute, and its output folder."""

    label: str
    input: Path
    output: Path


@dataclass
class Outcome:
    """What became of one input: a row of the summary and of batch.json.

    status: "done" (run now), "skipped" (done by an earlier run) or "failed"; seconds: this
    run's wall time (None when skipped); frames, vertices, triangles: from the run or the
    earlier report; error: one line; detail: the traceback of an unexpected error;
    warnings: what recon warned about while running it.
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
    """Run one input (the body of a Ray task); every error comes back in the Outcome."""
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
    return outcome


def lost_task(job: Job, error: Exception) -> Outcome:
    """The outcome of a task that did not come back: its worker died (out of memory, a crash
    in native code) or its node left the cluster. How long it ran is not known here."""
    cause = getattr(error, "cause", None) or error  # a task's own exception, when Ray wrapped one
    first_line = (str(cause).strip().splitlines() or [""])[0]
    return Outcome(job.label, str(job.output), FAILED,
                   error=f"task lost: {type(cause).__name__}: {first_line}", detail=str(error))


# --------------------------------------------------------------------------- Ray


def import_ray():
    try:
        import ray
    except ImportError:
        raise ReconInputError(RAY_MISSING) from None
    return ray


@contextmanager
def ray_session(options: BatchOptions) -> Iterator[object]:
    """Ray, connected: to the cluster at options.address, else to a new local instance that
    is shut down afterwards. A Ray the caller already started (Python API) is used as it is."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    local = options.address is None
    # Ray's own logging stays off the terminal (the user reads recon's lines): no dashboard,
    # workers' output left in Ray's session logs, only Ray's errors shown.
    settings = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    if local:
        # "local": a new instance even when RAY_ADDRESS or an earlier `ray start` names one.
        settings.update(address="local", num_cpus=options.num_cpus, object_store_memory=LOCAL_OBJECT_STORE_BYTES)
    else:
        check_reachable(options.address)
        settings.update(address=options.address)
    try:
        ray.init(**settings)
    except ConnectionError as error:
        # Also what a cluster with token authentication answers a driver without its token.
        raise ReconInputError(f"--address {options.address}: cannot join a Ray cluster there ({error}; a cluster "
                              f"with token authentication needs RAY_AUTH_MODE=token and its token here too)") from None
    try:
        check_resources(ray.cluster_resources(), options, local)
        yield ray
    finally:
        ray.shutdown()


def check_reachable(address: str) -> None:
    """Ray keeps trying an address where nothing answers for minutes, with warnings of its
    own; a plain HOST:PORT that accepts no connection is refused at once instead."""
    host, _, port = address.rpartition(":")
    if "://" in address or not host or not port.isdigit():
        return  # "auto", "ray://HOST:PORT" (Ray Client): Ray's own checks
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except OSError as error:
        raise ReconInputError(f"--address {address}: no Ray cluster answers there ({error})") from None


def check_resources(available: dict, options: BatchOptions, local: bool) -> None:
    """A task asking for more than the cluster has would wait forever: refuse on the local
    instance; on a joined cluster (which may grow) say so once."""
    wanted = {"CPU": options.cpus_per_task, "GPU": options.gpus_per_task}
    for name, amount in wanted.items():
        have = available.get(name, 0)
        if amount > have:
            flag = f"--{name.lower()}s-per-task"
            text = f"each task asks for {amount:g} {name} ({flag}); the Ray cluster has {have:g}"
            if local:
                raise ReconInputError(text)
            log.warning("%s: tasks wait until such a node joins", text)


def _remote_runner(ray, options: BatchOptions):
    resources = dict(num_cpus=options.cpus_per_task, num_gpus=options.gpus_per_task,
                     # A dead worker (out of memory, a native crash) would most likely die again;
                     # the next `recon batch` retries the input anyway.
                     max_retries=0)
    if options.memory_per_task:
        resources["memory"] = int(options.memory_per_task * 2**30)
    return ray.remote(**resources)(run_input)


# --------------------------------------------------------------------------- the batch


def run_batch(inputs: list[str], out, template: PipelineConfig, options: BatchOptions,
              on_done: Callable[[Outcome, int, int], None] | None = None) -> list[Outcome]:
    """Run every input on Ray; returns one Outcome per input, in input order, and writes them
    to OUT/batch.json. on_done(outcome, k, n) is called as each input finishes (k of n).

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

    def finished(index: int, outcome: Outcome) -> None:
        outcomes[index] = outcome
        if on_done is not None:
            on_done(outcome, len(outcomes), len(jobs))

    todo = []
    for index, job in enumerate(jobs):
        outcome = earlier_outcome(job)
        if outcome is None:
            todo.append(index)
        else:
            finished(index, outcome)
    if todo:
        with ray_session(options) as ray:
            _run_tasks(ray, jobs, todo, template, options, finished)
    rows = [outcomes[i] for i in range(len(jobs))]
    write_batch_json(out, rows)
    return rows


def _run_tasks(ray, jobs: list[Job], todo: list[int], template: PipelineConfig, options: BatchOptions,
               finished: Callable[[int, Outcome], None]) -> None:
    runner = _remote_runner(ray, options)
    threads = max(1, int(options.cpus_per_task))
    pending = {runner.remote(jobs[i].label, job_config(template, jobs[i]), threads, options.gpus_per_task): i
               for i in todo}
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            index = pending.pop(ref)
            try:
                outcome = ray.get(ref)
            except ray.exceptions.RayError as error:
                outcome = lost_task(jobs[index], error)
            finished(index, outcome)


def write_batch_json(out: Path, rows: list[Outcome]) -> Path:
    """OUT/batch.json: counts and one row per input (atomic: a reader sees the old or the new one)."""
    out.mkdir(parents=True, exist_ok=True)
    counts = {status: sum(r.status == status for r in rows) for status in (DONE, SKIPPED, FAILED)}
    return atomic_write_bytes(out / BATCH_JSON, json_bytes({"inputs": len(rows), **counts,
                                                            "rows": [asdict(r) for r in rows]}), overwrite=True)


# --------------------------------------------------------------------------- what the user reads


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def format_progress(outcome: Outcome, k: int, n: int) -> str:
    """The line printed as an input finishes: [k/n] input, status, seconds (and the error)."""
    line = f"[{k}/{n}] {outcome.input}: {outcome.status}"
    if outcome.seconds is not None:
        line += f" in {outcome.seconds:.1f} s"
    if outcome.status == FAILED:
        line += f": {_first_line(outcome.error)}"
    return line


def _first_line(text: str | None) -> str:
    return (str(text or "").strip().splitlines() or [""])[0]


def format_table(rows: list[Outcome]) -> str:
    """The closing summary: input, frames, seconds, mesh size and result per input."""
    header = ("input", "frames", "seconds", "mesh (vertices / triangles)", "result")
    lines = [header]
    for r in rows:
        mesh = "-" if r.vertices is None else f"{r.vertices} / {r.triangles}"
        frames = "-" if r.frames is None else str(r.frames)
        lines.append((r.input, frames, _seconds(r.seconds), mesh, _first_line(r.result)))
    widths = [max(len(line[c]) for line in lines) for c in range(len(header) - 1)]
    right = (False, True, True, True)  # numbers right-aligned
    out = []
    for line in lines:
        cells = [cell.rjust(w) if r else cell.ljust(w) for cell, w, r in zip(line, widths, right)]
        out.append("  ".join([*cells, line[-1]]))
    return "\n".join(out)


__all__ = [
    "BATCH_JSON",
    "DONE",
    "FAILED",
    "SKIPPED",
    "BatchOptions",
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
