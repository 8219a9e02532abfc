"""`recon batch --address` on a Ray cluster of two nodes on this machine (ray.cluster_utils:
a head and worker nodes, each with its own CPUs and a custom resource): the inputs spread
over both nodes, every output folder is complete and a second call skips them all; a worker
node killed while it runs inputs: they are run again on the head, none is reported done
without its report.json, finished outputs are not touched. Also what is checked before any
input runs (the output folder as each node sees it) and the progress line.

The tests skip when Ray is not installed (pip install -e .[batch])."""

from __future__ import annotations

import json
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from recon.commands.batch_cluster import Progress, format_duration, probe_output_root
from recon.commands.cli import main

# The benchmark kills a worker node the same way: one test of an input's start.
_SYS_PATH = list(sys.path)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from batch_cluster import files, started_after_a_finish  # noqa: E402

sys.path[:] = _SYS_PATH

pytestmark = pytest.mark.slow  # Ray clusters and end-to-end runs: `make test-fast` leaves them out

FRAMES, WIDTH, HEIGHT, FPS = 8, 160, 120, 10.0
STORE = 100 * 2**20  # each node's object store: the tasks pass kilobytes


@pytest.fixture(scope="module")
def cluster():
    """A Ray head node with 1 CPU (resource "head"); each test adds and removes its workers.
    Torn down whatever the tests do, and the signal handlers a Ray driver installs in this
    process (ray.init's SIGTERM handler) put back, so that later tests see their own."""
    import signal

    pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    head = Cluster(initialize_head=True, head_node_args=dict(num_cpus=1, resources={"head": 1},
                                                            object_store_memory=STORE, include_dashboard=False))
    try:
        yield head
    finally:
        head.shutdown()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)


def _worker(cluster, cpus: int):
    node = cluster.add_node(num_cpus=cpus, resources={"worker": 1}, object_store_memory=STORE)
    cluster.wait_for_nodes()
    return node


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Six copies of the same 8-frame synthetic video (clip0.mp4 ...), one pose file and one
    prior folder for all, and the options of a fast run with one CPU per input."""
    from recon.io.output_folder import frame_name
    from recon.io.pose_formats.trajectories import write_poses
    from recon.io.video import write_video
    from recon.synthetic import render_sequence

    folder = tmp_path_factory.mktemp("cluster")
    seq = render_sequence(FRAMES, WIDTH, HEIGHT, seed=0)
    write_video(seq.rgb, folder / "clip0.mp4", FPS)
    for k in range(1, 6):
        shutil.copy(folder / "clip0.mp4", folder / f"clip{k}.mp4")
    write_poses(folder / "poses.txt", seq.poses, "tum", timestamps=np.arange(FRAMES) / FPS)
    (folder / "prior").mkdir()
    for i, depth in enumerate(seq.depth):
        np.save(folder / "prior" / f"{frame_name(i)}.npy", depth.astype(np.float32))
    options = ["--poses", str(folder / "poses.txt"), "--prior", "folder", "--prior-path", str(folder / "prior"),
               "--width", "0", "--no-medea", "--refine", "none", "--no-npy", "--no-glb", "--fov", "60",
               "--cpus-per-task", "1"]
    return folder, [str(folder / f"clip{k}.mp4") for k in range(6)], options


def _batch(capfd, cluster, inputs, out, options) -> tuple[int, list[str], list[str], dict]:
    code = main(["batch", *inputs, "-o", str(out), "--address", cluster.address, *options])
    captured = capfd.readouterr()
    return code, captured.out.splitlines(), captured.err.splitlines(), json.loads((out / "batch.json").read_text())


def _complete(folder: Path) -> bool:
    return all((folder / name).is_file() for name in ("report.json", "mesh.ply", "trajectory.txt", "intrinsics.json"))


def test_two_nodes_share_the_inputs_and_a_second_call_skips_them(cluster, inputs, capfd):
    folder, clips, options = inputs
    worker = _worker(cluster, cpus=1)
    try:
        out = folder / "two_nodes"
        code, stdout, stderr, summary = _batch(capfd, cluster, clips[:4], out, options)
        assert code == 0, stderr
        rows = summary["rows"]
        assert [r["status"] for r in rows] == ["done"] * 4 and summary["pending"] == 0
        # Ray's node ids, as the tasks read them: every input ran on one of the two nodes, and
        # both nodes ran inputs.
        nodes = {cluster.head_node.node_id, worker.node_id}
        assert {r["node"] for r in rows} == nodes, [r["node"] for r in rows]
        assert all(r["attempts"] == 1 and r["lost_nodes"] == [] and r["host"] for r in rows)
        for r in rows:
            assert _complete(Path(r["output"])), r["output"]
            report = json.loads((Path(r["output"]) / "report.json").read_text())
            assert report["frames"]["count"] == FRAMES and Path(report["input"]["path"]) == Path(r["input"])
        progress = [line for line in stdout if line.startswith("[")]
        assert len(progress) == 4 and [line.split("]")[0].split(",")[0] for line in progress] == [
            "[1/4", "[2/4", "[3/4", "[4/4"]
        assert all(f"on node {r['node'][:8]} (" in "\n".join(progress) for r in rows)
        assert all("left]" in line for line in progress[:3]) and progress[3].startswith("[4/4] ")
        # The probe files of the output-folder check are gone.
        assert not list(out.glob(".recon-batch-probe-*"))

        before = {name: files(out / name) for name in ("clip0", "clip1", "clip2", "clip3")}
        code, stdout, stderr, summary = _batch(capfd, cluster, clips[:4], out, options)
        assert code == 0 and [r["status"] for r in summary["rows"]] == ["skipped"] * 4
        assert {name: files(out / name) for name in before} == before
    finally:
        cluster.remove_node(worker)


def test_a_lost_node_s_inputs_run_again_elsewhere(cluster, inputs, capfd):
    """The worker node (2 CPUs) is killed once an input is finished and the node runs inputs."""
    pytest.importorskip("psutil")
    folder, clips, options = inputs
    out = folder / "lost_node"
    worker = _worker(cluster, cpus=2)
    killed: dict = {}

    def kill_when_busy() -> None:
        # Killed as an input starts on the worker, so that it dies mid-input (an input seen
        # running may be finishing just then: its node's loss would cost it nothing).
        deadline = time.monotonic() + 300  # the batch's end stops it sooner
        before: set[int] = set()
        while time.monotonic() < deadline and "stop" not in killed:
            started, before, finished = started_after_a_finish(out, worker, before)
            if started:
                killed["finished"] = {p.name: files(p) for p in finished}
                killed["running"] = len(before)
                cluster.remove_node(worker, allow_graceful=False)
                return
            time.sleep(0.05)

    killer = threading.Thread(target=kill_when_busy)
    killer.start()
    try:
        code, stdout, stderr, summary = _batch(capfd, cluster, clips, out, options)
    finally:
        killed["stop"] = True
        killer.join()
        if "running" not in killed:
            cluster.remove_node(worker)
    assert "running" in killed, "the worker node never ran an input while another was finished"
    assert code == 0, stderr
    rows = summary["rows"]
    assert [r["status"] for r in rows] == ["done"] * 6 and all(_complete(Path(r["output"])) for r in rows)
    lost = [r for r in rows if r["lost_nodes"]]
    assert lost and all(r["lost_nodes"] == [worker.node_id] for r in lost), rows
    # Run again on the only node left, in the folder the lost node had begun.
    assert all(r["node"] == cluster.head_node.node_id and r["attempts"] == 2 for r in lost)
    assert any(f"{r['input']}: node {worker.node_id[:8]} left the cluster" in "\n".join(stderr) for r in lost)
    assert any("after losing node" in line for line in stdout)
    # What was finished when the node went away is as it was.
    assert {name: files(out / name) for name in killed["finished"]} == killed["finished"]


# --------------------------------------------------------------------------- pieces


def test_the_probe_names_what_a_node_does_not_see(tmp_path):
    """The output-folder check as it runs on one node: a folder where the driver's probe file
    is missing or different is not the same folder."""
    pytest.importorskip("ray")
    (tmp_path / "probe").write_text("token")
    assert probe_output_root(str(tmp_path), "probe", "token")[2] is None
    assert list(tmp_path.iterdir()) == [tmp_path / "probe"]  # its own file removed
    assert "does not see the probe file" in probe_output_root(str(tmp_path / "elsewhere"), "probe", "token")[2]
    assert "another probe file" in probe_output_root(str(tmp_path), "probe", "other")[2]


def test_the_time_left_counts_the_parallel_tasks():
    progress = Progress(6)
    progress.slots = 2
    progress.add(None, ran=False)  # done by an earlier run: no time
    assert progress.seconds_left() is None
    progress.add(10.0, ran=True)
    assert progress.seconds_left() == pytest.approx(10.0 * 4 / 2)
    for _ in range(3):
        progress.add(20.0, ran=True)
    assert progress.seconds_left() == pytest.approx(17.5 * 1)  # one left: one slot
    assert [format_duration(s) for s in (4.4, 65, 3600 + 5 * 60)] == ["4 s", "1 min 05 s", "1 h 05 min"]


def _can_unshare() -> bool:
    import subprocess

    if shutil.which("unshare") is None:
        return False
    try:
        return subprocess.run(["unshare", "-m", "--propagation", "private", "true"], capture_output=True,
                              timeout=10).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def test_a_node_that_does_not_see_the_output_folder_stops_the_batch(cluster, inputs, capfd):
    """A node of its own file system at the output folder's path (a tmpfs mounted there in a
    mount namespace of its own, as a machine without the shared file system would be): one
    `recon: error:` line naming the path and the node, before any input runs. Needs the
    rights to mount (root); runs last, as its node leaves the cluster afterwards."""
    import os
    import signal
    import subprocess
    import sys

    import ray

    if not _can_unshare():
        pytest.skip("needs `unshare -m` and mount rights to give a node a file system of its own")
    folder, clips, options = inputs
    out = folder / "not_shared"
    out.mkdir()
    ray_cli = Path(sys.executable).parent / "ray"
    start = (f"mount -t tmpfs tmpfs {out} && exec {ray_cli} start --address {cluster.address} --num-cpus 1 "
             f"--object-store-memory {STORE} --disable-usage-stats --block")
    node = None
    try:
        ray.init(address=cluster.address, log_to_driver=False)
        try:
            # A worker an earlier test killed may still be listed alive for a while (the probe
            # passes over a node that left): the node to look for is the new one.
            before = {n["NodeID"] for n in ray.nodes()}
            node = subprocess.Popen(["unshare", "-m", "--propagation", "private", "sh", "-c", start],
                                    start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            deadline = time.monotonic() + 60
            joined = []
            while not joined and time.monotonic() < deadline:
                time.sleep(0.5)
                joined = [n["NodeID"] for n in ray.nodes() if n["Alive"] and n["NodeID"] not in before]
        finally:
            ray.shutdown()
        assert joined, "the node in its own mount namespace did not join"
        capfd.readouterr()  # what this test's own Ray driver said while the node joined
        code = main(["batch", *clips[:2], "-o", str(out), "--address", cluster.address, *options])
        captured = capfd.readouterr()
        err = captured.err.splitlines()
        assert code == 2 and len(err) == 1, err
        assert err[0].startswith(f"recon: error: {out}: node {joined[0][:8]} (") and "does not see" in err[0]
        assert "every node" in err[0]
        assert not [line for line in captured.out.splitlines() if line.startswith("[")]  # no input ran
        assert not list(out.glob(".recon-batch-probe-*")) and not (out / "clip0").exists()
        assert [r["status"] for r in json.loads((out / "batch.json").read_text())["rows"]] == ["pending"] * 2
    finally:
        if node is not None:
            os.killpg(node.pid, signal.SIGTERM)  # `ray start --block` drains and stops its node
            try:
                node.wait(timeout=40)
            except subprocess.TimeoutExpired:
                os.killpg(node.pid, signal.SIGKILL)
                node.wait()
