"""`recon batch` on a Ray cluster of two nodes on this machine against one node, and a worker
node lost mid-run (issue 66).

The inputs: N copies (default 6) of one synthetic video (recon.synthetic, --frames frames at
--width x --height), with its trajectory as a pose file and its depth as a folder prior, run
without MEDeA and refinement (the batch's own costs and the pipeline's fixed costs, not MEDeA's
speed, are measured). Every setup is a fresh `ray.cluster_utils.Cluster` on this machine, and
the batch a separate `python -m recon batch --address ...` process with --cpus-per-task 1:

* ``two nodes``: a head with 1 CPU and a worker node with 1 CPU;
* ``one node``: a head with 2 CPUs (the same 2 CPUs in all, so the row measures what a second
  node costs, not what it adds: this machine has 2 cores);
* ``lost node``: a head with 1 CPU and a worker with 2 CPUs, killed (its raylet and workers,
  no drain) once one input is finished and the worker runs an input; what became of each input.

Wall time is the batch process's, Ray's start on the driver included. Prints a table and
writes benchmarks/results/batch_cluster.json.

Usage: python benchmarks/batch_cluster.py [--inputs 6] [--frames 16] [--width 320] [--height 240]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine, say, table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STORE = 100 * 2**20


def make_inputs(folder: Path, count: int, frames: int, width: int, height: int) -> tuple[list[str], list[str]]:
    """count copies of one synthetic video, and the run options that go with them."""
    from recon.io.output_folder import frame_name
    from recon.io.pose_formats.trajectories import write_poses
    from recon.io.video import write_video
    from recon.synthetic import render_sequence

    seq = render_sequence(frames, width, height, seed=0)
    write_video(seq.rgb, folder / "clip0.mp4", 10.0)
    for k in range(1, count):
        shutil.copy(folder / "clip0.mp4", folder / f"clip{k}.mp4")
    write_poses(folder / "poses.txt", seq.poses, "tum", timestamps=np.arange(frames) / 10.0)
    (folder / "prior").mkdir()
    for i, depth in enumerate(seq.depth):
        np.save(folder / "prior" / f"{frame_name(i)}.npy", depth.astype(np.float32))
    options = ["--poses", str(folder / "poses.txt"), "--prior", "folder", "--prior-path", str(folder / "prior"),
               "--width", "0", "--no-medea", "--refine", "none", "--no-npy", "--no-glb", "--fov", "60",
               "--cpus-per-task", "1", "--quiet"]
    return [str(folder / f"clip{k}.mp4") for k in range(count)], options


def run_batch(address: str, inputs: list[str], out: Path, options: list[str]) -> tuple[float, int, dict, str]:
    """One `recon batch` process; (wall seconds, exit code, batch.json, its stderr)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "recon", "batch", *inputs, "-o", str(out), "--address", address,
                           *options], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    return wall, done.returncode, json.loads((out / "batch.json").read_text()), done.stderr


def finished_outputs(out: Path) -> list[Path]:
    """The output folders under `out` whose run has ended: report.json written and the
    UNFINISHED.txt mark gone (a run writes its report, then removes the mark)."""
    from recon.io.output_folder import UNFINISHED

    return [p.parent for p in out.glob("*/report.json") if not (p.parent / UNFINISHED).exists()]


def running_input_pids(node) -> set[int]:
    """The worker processes of this node's raylet running an input's task now (their process
    title names the task while it runs)."""
    import psutil
    from ray._private import ray_constants

    raylet = psutil.Process(node.all_processes[ray_constants.PROCESS_TYPE_RAYLET][0].process.pid)
    pids = set()
    for child in raylet.children(recursive=True):
        try:
            if any("run_input" in part for part in child.cmdline()[:1]):
                pids.add(child.pid)
        except psutil.Error:
            pass
    return pids


def started_after_a_finish(out: Path, node, before: set[int]) -> tuple[bool, set[int], list[Path]]:
    """Whether an input started on `node` since the last look while another input's output
    under `out` is finished. An input runs in a process of its own (recon batch asks Ray
    for a fresh worker per input), so a process running an input that `before`, the ids seen
    at the last look, lacks is a start: killing the node then loses an input mid-run.

    Returns:
        (started, the process ids running inputs now, the finished output folders).
    """
    finished = finished_outputs(out)
    now = running_input_pids(node)
    return bool(finished and now - before), now, finished


def files(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


def setup(name: str, nodes: list[int], inputs: list[str], options: list[str], work: Path, lose: bool) -> dict:
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args=dict(num_cpus=nodes[0], object_store_memory=STORE,
                                                               include_dashboard=False))
    killed: dict = {}
    try:
        workers = [cluster.add_node(num_cpus=cpus, object_store_memory=STORE) for cpus in nodes[1:]]
        cluster.wait_for_nodes()
        names = {cluster.head_node.node_id: "head", **{w.node_id: f"worker{k + 1}" for k, w in enumerate(workers)}}
        out = work / name.replace(" ", "_")
        stop = threading.Event()

        def kill_when_busy() -> None:
            before: set[int] = set()
            while not stop.is_set():
                started, before, finished = started_after_a_finish(out, workers[0], before)
                if started:
                    killed.update(finished={p.name: files(p) for p in finished}, running=len(before),
                                  at=time.perf_counter())
                    cluster.remove_node(workers[0], allow_graceful=False)
                    return
                time.sleep(0.05)

        killer = threading.Thread(target=kill_when_busy) if lose else None
        if killer:
            killer.start()
        say(f"{name}: {len(inputs)} inputs on nodes of {nodes} CPUs")
        try:
            wall, code, summary, stderr = run_batch(cluster.address, inputs, out, options)
        finally:
            stop.set()
            if killer:
                killer.join()
        rows = summary["rows"]
        result = {
            "setup": name, "node_cpus": nodes, "wall_s": round(wall, 2), "exit_code": code,
            "statuses": dict(Counter(r["status"] for r in rows)),
            "per_node": dict(Counter(names.get(r["node"], r["node"]) for r in rows)),
            "task_s_mean": round(float(np.mean([r["seconds"] for r in rows if r["seconds"]])), 2),
            "done_without_report": [r["input"] for r in rows
                                    if r["status"] == "done" and not (Path(r["output"]) / "report.json").is_file()],
        }
        if lose:
            result.update(
                lost_while_running=killed.get("running"),
                finished_before_loss=sorted(killed.get("finished", {})),
                finished_untouched=all(files(out / n) == f for n, f in killed.get("finished", {}).items()),
                run_again=[{"input": Path(r["input"]).name, "lost": [names.get(n, n) for n in r["lost_nodes"]],
                            "ran_on": names.get(r["node"], r["node"]), "attempts": r["attempts"],
                            "status": r["status"]} for r in rows if r["lost_nodes"]],
                warnings=[line for line in stderr.splitlines() if "left the cluster" in line],
            )
        say(f"{name}: {result['wall_s']} s, {result['per_node']}, {result['statuses']}")
        return result
    finally:
        cluster.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", type=int, default=6)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="batch_cluster_"))
    try:
        inputs, options = make_inputs(work, args.inputs, args.frames, args.width, args.height)
        results = [setup("two nodes", [1, 1], inputs, options, work, lose=False),
                   setup("one node", [2], inputs, options, work, lose=False),
                   setup("lost node", [1, 2], inputs, options, work, lose=True)]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(table(["setup", "CPUs per node", "wall s", "inputs per node", "mean task s", "result"],
                [[r["setup"], "+".join(map(str, r["node_cpus"])), r["wall_s"],
                  ", ".join(f"{k} {v}" for k, v in sorted(r["per_node"].items())), r["task_s_mean"],
                  ", ".join(f"{v} {k}" for k, v in r["statuses"].items())] for r in results]))
    lost = results[-1]
    print(f"lost node: {lost['lost_while_running']} input(s) running on it when killed; run again: "
          f"{lost['run_again']}; finished before the loss {lost['finished_before_loss']} untouched: "
          f"{lost['finished_untouched']}; done without report.json: {lost['done_without_report']}")
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "batch_cluster.json"
    path.write_text(json.dumps({"machine": machine(), "inputs": args.inputs, "frames": args.frames,
                                "size": [args.width, args.height], "results": results}, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
