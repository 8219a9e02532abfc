"""`recon batch` on Ray: joining a cluster, what is checked before any input runs, lost nodes,
and the progress line.

:func:`ray_session` joins the cluster at ``--address`` (or starts a local instance) and, on a
cluster, checks that every node able to run an input can write to the output root
(:func:`check_output_root`) before any input is scheduled; :func:`node_lost` tells an input
whose node left (run again elsewhere) from one whose worker died (reported failed);
:class:`Progress` counts finished inputs and estimates the time left. Ray is imported only
inside these functions: the rest of recon needs none.
More: docs/running.md#on-a-ray-cluster
"""

from __future__ import annotations

import logging
import socket
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from ..errors import ReconInputError

log = logging.getLogger("recon.commands.batch")

RAY_MISSING = "recon batch needs Ray: pip install -e .[batch]"
# The tasks pass only configurations and outcomes (kilobytes) through Ray's object store;
# a small store leaves the local machine's memory to the pipelines.
LOCAL_OBJECT_STORE_BYTES = 128 * 2**20
# How long the output-root probe waits for a node to answer (a fresh worker process on a
# busy node takes seconds to start).
PROBE_SECONDS = 120.0
PROBE_PREFIX = ".recon-batch-probe-"

DONE, SKIPPED, FAILED, PENDING = "done", "skipped", "failed", "pending"


# A one-shot run of 100 frames at 640x480 needs 2.3-3.5 GB (docs/benchmarks.md table D);
# longer inputs are streamed within the frame budget.
DEFAULT_MEMORY_GB = 3.0


@dataclass
class BatchOptions:
    """Where the tasks run and what each asks Ray for.

    address: an existing Ray cluster to join ("auto", "HOST:6379", "ray://HOST:10001");
    None starts a local Ray instance with num_cpus CPUs (None: all of this machine's).
    cpus_per_task, gpus_per_task, memory_per_task (GiB, 0 or None: no reservation): Ray
    resources of each input's task; torch uses cpus_per_task threads in it.
    node_retries: how many times an input whose node left the cluster is run again.
    """

    address: str | None = None
    num_cpus: int | None = None
    cpus_per_task: int = 2
    gpus_per_task: float = 0.0
    memory_per_task: float | None = DEFAULT_MEMORY_GB
    node_retries: int = 2

    def validate(self) -> None:
        if self.address is not None and self.num_cpus is not None:
            raise ReconInputError("--num-cpus sizes the local Ray instance; a cluster joined with --address has "
                                  "its own CPUs")
        if self.cpus_per_task < 1:
            raise ReconInputError(f"--cpus-per-task must be >= 1, got {self.cpus_per_task}")
        if self.gpus_per_task < 0:
            raise ReconInputError(f"--gpus-per-task must be >= 0, got {self.gpus_per_task}")
        if self.memory_per_task is not None and self.memory_per_task < 0:
            raise ReconInputError(f"--memory-per-task must be >= 0 GB, got {self.memory_per_task}")
        if self.node_retries < 0:
            raise ReconInputError(f"--node-retries must be >= 0, got {self.node_retries}")
        if self.num_cpus is not None and self.num_cpus < self.cpus_per_task:
            raise ReconInputError(f"--num-cpus {self.num_cpus} is fewer than one task's --cpus-per-task "
                                  f"{self.cpus_per_task}")


def default_gpus_per_task(device: str) -> float:
    """One GPU per task when the device asks for CUDA, else none."""
    return 1.0 if device.startswith("cuda") else 0.0


def import_ray():
    try:
        import ray
    except ImportError:
        raise ReconInputError(RAY_MISSING) from None
    return ray


def short_node(node_id: str | None) -> str:
    """The first 8 hex digits of a Ray node id, as the progress line shows it."""
    return "-" if not node_id else node_id[:8]


def node_label(node_id: str | None, host: str | None) -> str:
    """`node 06bcac5d (host)`: nodes on one machine share its name and IP, so the id leads."""
    return f"node {short_node(node_id)}" + (f" ({host})" if host else "")


# --------------------------------------------------------------------------- joining


@contextmanager
def ray_session(options: BatchOptions, out: Path) -> Iterator[object]:
    """Ray, connected: to the cluster at options.address, else to a new local instance that
    is shut down afterwards. A Ray the caller already started (Python API) is used as it is.
    On a cluster (address given or Ray already started) the output root `out` is probed on
    every node that can run an input (:func:`check_output_root`)."""
    ray = import_ray()
    if ray.is_initialized():
        check_output_root(ray, out, options)
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
        check_resources(alive_nodes(ray), options, local)
        if not local:
            check_output_root(ray, out, options)
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


def alive_nodes(ray) -> list[dict]:
    """Ray's records of the nodes now in the cluster (NodeID, NodeManagerHostname, Resources)."""
    return [node for node in ray.nodes() if node.get("Alive")]


def task_resources(options: BatchOptions) -> dict[str, float]:
    """What one input's task asks of a node, in Ray's units (memory in bytes)."""
    wanted = {"CPU": float(options.cpus_per_task), "GPU": float(options.gpus_per_task)}
    if options.memory_per_task:
        wanted["memory"] = options.memory_per_task * 2**30
    return {name: amount for name, amount in wanted.items() if amount > 0}


def task_slots(resources: dict, options: BatchOptions) -> int:
    """How many inputs' tasks a node with these resources runs at once."""
    return min((int(resources.get(name, 0) // amount) for name, amount in task_resources(options).items()),
               default=0)


def _amount(name: str, value: float) -> str:
    return f"{value / 2**30:.1f} GB memory" if name == "memory" else f"{value:g} {name}"


def check_resources(nodes: list[dict], options: BatchOptions, local: bool) -> None:
    """A task asking for more than any one node has would wait forever: refuse on the local
    instance; on a joined cluster (which may grow) say so once. nodes: Ray's node records."""
    if any(task_slots(node.get("Resources", {}), options) > 0 for node in nodes):
        return
    flags = {"CPU": "--cpus-per-task", "GPU": "--gpus-per-task", "memory": "--memory-per-task"}
    wanted = task_resources(options)
    asks = ", ".join(f"{_amount(name, amount)} ({flags[name]})" for name, amount in wanted.items())
    most = ", ".join(_amount(name, max((node.get("Resources", {}).get(name, 0) for node in nodes), default=0))
                     for name in wanted)
    text = f"each task asks for {asks} and no node of the Ray cluster has that much (the most any node has: {most})"
    if local:
        raise ReconInputError(text)
    log.warning("%s: tasks wait until such a node joins", text)


# --------------------------------------------------------------------------- the output root


def this_node() -> str | None:
    """The Ray node id of the process this runs in; None outside a Ray task or without Ray
    (get_runtime_context would start a Ray instance)."""
    try:
        import ray

        return ray.get_runtime_context().get_node_id() if ray.is_initialized() else None
    except ImportError:
        return None


def probe_output_root(folder: str, name: str, token: str) -> tuple[str | None, str, str | None]:
    """On one node: does it see the probe file the driver wrote in the output root, and can it
    write and remove a file of its own there? Returns (node id, host name, the problem or None)."""
    node = this_node()
    host = socket.gethostname()
    root = Path(folder)
    try:
        seen = (root / name).read_text()
    except OSError as error:
        return node, host, (f"does not see the probe file written there from the machine running recon batch "
                            f"({type(error).__name__}), so it is not the same folder there")
    if seen != token:
        return node, host, "holds another probe file there, so it is not the same folder there"
    own = root / f"{name}-{short_node(node)}-{uuid.uuid4().hex[:8]}"
    try:
        own.write_text(token)
        own.unlink()
    except OSError as error:
        return node, host, f"cannot write there ({type(error).__name__}: {error.strerror or error})"
    return node, host, None


def check_output_root(ray, out: Path, options: BatchOptions) -> None:
    """Before any input runs: every alive node that can hold an input's task sees `out` and
    can write there. The driver writes a probe file with a random token; a zero-CPU task
    pinned to each node reads it back and writes and removes a file of its own. Nodes that
    join later are not probed. Raises ReconInputError naming the path and the node."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    nodes = [node for node in alive_nodes(ray) if task_slots(node.get("Resources", {}), options) > 0]
    if not nodes:
        return
    token = uuid.uuid4().hex
    name = PROBE_PREFIX + token[:12]
    probe_file = out / name
    try:
        probe_file.write_text(token)
    except OSError as error:
        raise ReconInputError(f"{out}: cannot write the output-folder probe there ({type(error).__name__}: "
                              f"{error.strerror or error})") from None
    probe = ray.remote(num_cpus=0, max_retries=0)(probe_output_root)
    try:
        refs = {probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False))
                .remote(str(out), name, token): node for node in nodes}
        ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=PROBE_SECONDS)
        for ref in late:
            ray.cancel(ref, force=True)
        if late:
            node = refs[late[0]]
            raise ReconInputError(f"{out}: {node_label(node['NodeID'], node.get('NodeManagerHostname'))} did not "
                                  f"answer the output-folder check within {PROBE_SECONDS:.0f} s")
        for ref in ready:
            try:
                node_id, host, problem = ray.get(ref)
            except (ray.exceptions.TaskUnschedulableError, ray.exceptions.NodeDiedError):
                continue  # the node left the cluster after ray.nodes() listed it: it runs no input either
            except ray.exceptions.RayError as error:
                node = refs[ref]
                node_id, host = node["NodeID"], node.get("NodeManagerHostname")
                problem = f"failed the output-folder check ({type(error).__name__})"
            if problem:
                raise ReconInputError(f"{out}: {node_label(node_id, host)} {problem}; the output folder must be a "
                                      f"path every node of the cluster sees (a shared file system)")
    finally:
        probe_file.unlink(missing_ok=True)


# --------------------------------------------------------------------------- lost nodes


def node_lost(ray, error: Exception) -> bool:
    """Whether a task came back with this error because its node left the cluster (run it
    again elsewhere), not because its worker died on a live node (out of memory, a native
    crash: the same input would most likely die again)."""
    return isinstance(error, ray.exceptions.NodeDiedError)


def lost_node_id(error: Exception) -> str | None:
    """The node id Ray names in a NodeDiedError's text ("node ID: <hex>"), if any."""
    text = str(error)
    marker = "node ID: "
    at = text.find(marker)
    if at < 0:
        return None
    tail = text[at + len(marker):]
    end = next((i for i, c in enumerate(tail) if c not in "0123456789abcdef"), len(tail))
    return tail[:end] or None


# --------------------------------------------------------------------------- progress


class Progress:
    """The running count and the time left: k of n inputs finished; the time left is the
    mean seconds of the inputs run so far times those left, over the tasks the cluster runs at
    once (slots; None until one input has run)."""

    def __init__(self, total: int):
        self.total = total
        self.finished = 0
        self.task_seconds: list[float] = []
        self.slots = 1

    def add(self, seconds: float | None, ran: bool) -> None:
        self.finished += 1
        if ran and seconds is not None:
            self.task_seconds.append(seconds)

    def seconds_left(self) -> float | None:
        left = self.total - self.finished
        if left <= 0:
            return 0.0
        if not self.task_seconds:
            return None
        mean = sum(self.task_seconds) / len(self.task_seconds)
        return mean * left / max(1, min(self.slots, left))


def format_duration(seconds: float) -> str:
    """45 s, 3 min 20 s, 2 h 05 min."""
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    minutes, seconds = divmod(seconds, 60)
    if minutes < 60:
        return f"{minutes} min {seconds:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


def cluster_slots(ray, options: BatchOptions) -> int:
    """Inputs the cluster's alive nodes run at once (at least 1)."""
    return max(1, sum(task_slots(node.get("Resources", {}), options) for node in alive_nodes(ray)))


# --------------------------------------------------------------------------- what the user reads


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def format_progress(outcome, progress: Progress) -> str:
    """The line printed as an input finishes (outcome: a recon.commands.batch.Outcome):
    [k/n, time left] input, status, seconds, the node that ran it, nodes lost under it (and
    the error)."""
    left = progress.seconds_left()
    count = f"{progress.finished}/{progress.total}"
    if left is not None and progress.finished < progress.total:
        count += f", about {format_duration(left)} left"
    line = f"[{count}] {outcome.input}: {outcome.status}"
    if outcome.seconds is not None:
        line += f" in {outcome.seconds:.1f} s"
    if outcome.node is not None:
        line += f" on {node_label(outcome.node, outcome.host)}"
    if outcome.lost_nodes:
        line += f" (after losing {', '.join(node_label(n, None) for n in outcome.lost_nodes)})"
    if outcome.status == FAILED:
        line += f": {_first_line(outcome.error)}"
    return line


def _first_line(text: str | None) -> str:
    return (str(text or "").strip().splitlines() or [""])[0]


def format_table(rows: list) -> str:
    """The closing summary of the Outcome rows: input, frames, seconds, mesh size, node and
    result per input."""
    header = ("input", "frames", "seconds", "mesh (vertices / triangles)", "node", "result")
    lines = [header]
    for r in rows:
        mesh = "-" if r.vertices is None else f"{r.vertices} / {r.triangles}"
        frames = "-" if r.frames is None else str(r.frames)
        lines.append((r.input, frames, _seconds(r.seconds), mesh, short_node(r.node), _first_line(r.result)))
    widths = [max(len(line[c]) for line in lines) for c in range(len(header) - 1)]
    right = (False, True, True, True, False)  # numbers right-aligned
    out = []
    for line in lines:
        cells = [cell.rjust(w) if r else cell.ljust(w) for cell, w, r in zip(line, widths, right)]
        out.append("  ".join([*cells, line[-1]]))
    return "\n".join(out)


__all__ = [
    "DEFAULT_MEMORY_GB",
    "DONE",
    "FAILED",
    "PENDING",
    "SKIPPED",
    "BatchOptions",
    "Progress",
    "check_output_root",
    "check_resources",
    "default_gpus_per_task",
    "format_duration",
    "format_progress",
    "format_table",
    "import_ray",
    "node_label",
    "node_lost",
    "probe_output_root",
    "ray_session",
]
