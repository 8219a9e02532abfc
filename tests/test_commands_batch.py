"""`recon batch`: three short synthetic videos (one of them corrupt) on a local Ray instance
with 2 CPUs: two outputs complete, the corrupt one reported with its error (exit code 2);
the same command again skips the finished ones and redoes a folder a broken run left. Also
the planning without Ray: output names, what counts as done, the summary, a missing Ray.

The Ray tests skip when Ray is not installed (pip install -e .[batch])."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from recon.commands.batch import BatchOptions, Job, earlier_outcome, format_table, lost_task, output_names
from recon.commands.cli import main
from recon.errors import ReconInputError

pytestmark = pytest.mark.slow  # end-to-end runs: `make test-fast` leaves them out

FRAMES, WIDTH, HEIGHT, FPS = 8, 160, 120, 10.0


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """room.mp4 and other/room.mp4 (the same 8 frames of the synthetic room, so one pose file
    and one prior folder serve both), broken.mp4 (text), and the options of a fast run."""
    from recon.io.output_folder import frame_name
    from recon.io.pose_formats.trajectories import write_poses
    from recon.io.video import write_video
    from recon.synthetic import render_sequence

    folder = tmp_path_factory.mktemp("batch")
    seq = render_sequence(FRAMES, WIDTH, HEIGHT, seed=0)
    (folder / "other").mkdir()
    inputs = [folder / "room.mp4", folder / "other" / "room.mp4", folder / "broken.mp4"]
    write_video(seq.rgb, inputs[0], FPS)
    write_video(seq.rgb, inputs[1], FPS)
    inputs[2].write_text("not a video\n" * 50)
    write_poses(folder / "poses.txt", seq.poses, "tum", timestamps=np.arange(FRAMES) / FPS)
    (folder / "prior").mkdir()
    for i, depth in enumerate(seq.depth):
        np.save(folder / "prior" / f"{frame_name(i)}.npy", depth.astype(np.float32))
    # No intrinsics: the runs assume a field of view and warn, so the warnings' way back is seen.
    options = ["--poses", str(folder / "poses.txt"), "--prior", "folder", "--prior-path", str(folder / "prior"),
               "--width", "0", "--no-medea", "--refine", "none", "--no-npy", "--no-glb",
               "--num-cpus", "2", "--cpus-per-task", "1"]
    return folder, [str(p) for p in inputs], options


def _batch(capfd, inputs, out, options) -> tuple[int, list[str], list[str], dict]:
    code = main(["batch", *inputs, "-o", str(out), *options])
    captured = capfd.readouterr()
    return code, captured.out.splitlines(), captured.err.splitlines(), json.loads((out / "batch.json").read_text())


def test_batch_runs_each_input_and_resumes(clips, capfd):
    pytest.importorskip("ray")
    folder, inputs, options = clips
    out = folder / "out"
    code, stdout, stderr, summary = _batch(capfd, inputs, out, options)
    assert code == 2
    # Ray's own output stays off the terminal: only recon's lines, the last one the count.
    assert stderr and all(line.startswith("recon: ") for line in stderr), stderr
    assert stderr[-1] == "recon: error: 1 of 3 inputs failed"
    assert sum("recon: warning: " in line and "intrinsics unknown" in line for line in stderr) == 2, stderr
    assert any(line.startswith(f"recon: warning: {inputs[1]}: ") for line in stderr), stderr
    for name in ("room", "room-2"):
        assert (out / name / "mesh.ply").stat().st_size > 0 and (out / name / "report.json").is_file(), name
    assert not (out / "broken").exists()  # the failed run left nothing behind
    rows = summary["rows"]
    assert [r["status"] for r in rows] == ["done", "done", "failed"]
    assert [Path(r["output"]).name for r in rows] == ["room", "room-2", "broken"]
    assert rows[0]["frames"] == FRAMES and rows[0]["vertices"] > 1000 and rows[0]["triangles"] > 1000
    assert "broken.mp4" in rows[2]["error"] and "not a video" in rows[2]["error"] and rows[2]["detail"] is None
    progress = [line for line in stdout if line.startswith("[")]
    assert len(progress) == 3 and any(line.startswith("[") and "broken.mp4: failed in" in line for line in progress)
    table = stdout[len(progress):]
    assert table[0].split()[:3] == ["input", "frames", "seconds"] and len(table) == 4
    assert "not a video" in table[3] and str(FRAMES) in table[1].split()

    # Again: the two finished inputs are skipped, a folder a killed run left (no report.json)
    # is run again into, the corrupt input fails again.
    mesh_time = (out / "room" / "mesh.ply").stat().st_mtime_ns
    (out / "room-2" / "report.json").unlink()
    code, stdout, stderr, summary = _batch(capfd, inputs, out, options)
    assert code == 2 and stderr[-1] == "recon: error: 1 of 3 inputs failed"
    assert [r["status"] for r in summary["rows"]] == ["skipped", "done", "failed"]
    assert summary["rows"][0]["frames"] == FRAMES and summary["rows"][0]["seconds"] is None
    assert (out / "room" / "mesh.ply").stat().st_mtime_ns == mesh_time
    assert (out / "room-2" / "report.json").is_file()
    assert "skipped: done" in "\n".join(stdout)
    assert (summary["inputs"], summary["done"], summary["skipped"], summary["failed"]) == (3, 1, 1, 1)


def test_missing_inputs_fail_without_a_task(tmp_path, capfd):
    """Nothing to run (one input missing, one already done, its input gone since): no Ray
    instance is started."""
    pytest.importorskip("ray")
    done = tmp_path / "done.mp4"
    (tmp_path / "out" / "done").mkdir(parents=True)
    (tmp_path / "out" / "done" / "report.json").write_text(json.dumps({"input": {"path": str(done)},
                                                                        "frames": {"count": 5}}))
    code, stdout, stderr, summary = _batch(capfd, [str(done), str(tmp_path / "gone.mp4")], tmp_path / "out", [])
    assert code == 2 and stderr == ["recon: error: 1 of 2 inputs failed"]
    assert [r["status"] for r in summary["rows"]] == ["skipped", "failed"]
    assert summary["rows"][1]["error"].endswith("gone.mp4: no such file or folder")


def test_bad_batch_options_fail_before_ray(tmp_path, capfd):
    pytest.importorskip("ray")
    video = tmp_path / "clip.mp4"
    video.write_bytes(b"")
    for options, words in [(["--address", "auto", "--num-cpus", "2"], ["--num-cpus", "--address"]),
                           (["--cpus-per-task", "0"], ["--cpus-per-task"]),
                           (["--num-cpus", "1", "--cpus-per-task", "2"], ["--num-cpus 1"]),
                           (["--device", "warp-drive"], ["--device", "warp-drive"]),
                           (["--intrinsics", "1,2"], ["--intrinsics"]),
                           (["--prior", "hf"], ["prior 'hf'", "--prior-path"]),
                           (["--prior", "hf", "--prior-path", str(tmp_path)], [str(tmp_path), "no config.json"]),
                           (["--memory-per-task", "-1"], ["--memory-per-task"]),
                           (["-o", str(video / "out")], [str(video / "out"), "cannot write"])]:
        assert main(["batch", str(video), "-o", str(tmp_path / "out"), *options]) == 2
        err = capfd.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("recon: error: "), err
        assert all(word in err[0] for word in words), (words, err)
    assert not (tmp_path / "out").exists()


def test_without_ray_one_line_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert main(["batch", str(tmp_path / "clip.mp4"), "-o", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == "recon: error: recon batch needs Ray: pip install -e .[batch]\n"


def test_help_does_not_import_ray():
    import subprocess

    code = ("import sys; from recon.commands.cli import build_parser; build_parser().format_help(); "
            "assert 'ray' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# --------------------------------------------------------------------------- planning, without Ray


def test_output_names_are_deterministic(tmp_path):
    (tmp_path / "scene.v2").mkdir()
    inputs = [Path("a.mp4"), Path("x/a.mp4"), Path("A.mov"), Path("a-2.mp4"), tmp_path / "scene.v2", Path("b")]
    assert output_names(inputs) == ["a", "a-2", "A-3", "a-2-2", "scene.v2", "b"]
    assert output_names(inputs) == output_names(list(inputs))


def test_a_folder_holding_another_inputs_result_is_not_skipped(tmp_path):
    for name in ("one.mp4", "two.mp4"):
        (tmp_path / name).write_bytes(b"")
    folder = tmp_path / "out" / "one"
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps({"input": {"path": str(tmp_path / "two.mp4")}}))
    outcome = earlier_outcome(Job("one.mp4", tmp_path / "one.mp4", folder))
    assert outcome.status == "failed" and "two.mp4" in outcome.error and "order" in outcome.error
    (folder / "report.json").write_text(json.dumps({"input": {"path": str(tmp_path / "one.mp4")},
                                                    "frames": {"count": 7}, "fusion": {"vertices": 3,
                                                                                       "triangles": 1}}))
    outcome = earlier_outcome(Job("one.mp4", tmp_path / "one.mp4", folder))
    assert (outcome.status, outcome.frames, outcome.vertices, outcome.result) == ("skipped", 7, 3, "skipped: done")
    (folder / "report.json").unlink()
    assert earlier_outcome(Job("one.mp4", tmp_path / "one.mp4", folder)) is None  # incomplete: run again
    assert earlier_outcome(Job("gone.mp4", tmp_path / "gone.mp4", folder)).error == "gone.mp4: no such file or folder"


def test_a_lost_task_is_one_line_and_the_table_lines_up(tmp_path):
    job = Job("clip.mp4", tmp_path / "clip.mp4", tmp_path / "out" / "clip")
    outcome = lost_task(job, RuntimeError("The worker died unexpectedly.\nSee the logs."))
    assert outcome.error == "task lost: RuntimeError: The worker died unexpectedly." and "logs" in outcome.detail
    outcome.seconds = 3.0
    table = format_table([outcome]).splitlines()
    assert len(table) == 2 and table[1].index("3.0") + 3 == table[0].index("seconds") + len("seconds")
    assert table[1].endswith("  task lost: RuntimeError: The worker died unexpectedly.")


def test_batch_options_are_checked():
    BatchOptions().validate()
    with pytest.raises(ReconInputError, match="gpus-per-task"):
        BatchOptions(gpus_per_task=-1).validate()
    from recon.commands.batch import check_resources

    nodes = [{"Resources": {"CPU": 8.0, "memory": 16.0 * 2**30}}, {"Resources": {"CPU": 1.0, "GPU": 1.0}}]
    with pytest.raises(ReconInputError, match="1 GPU"):  # no node has both
        check_resources(nodes, BatchOptions(gpus_per_task=1), local=True)
    check_resources(nodes, BatchOptions(gpus_per_task=1), local=False)  # a cluster may grow: a warning
    check_resources(nodes, BatchOptions(gpus_per_task=1, cpus_per_task=1, memory_per_task=0), local=True)
    with pytest.raises(ReconInputError, match=r"20.0 GB memory \(--memory-per-task\) and no node .* 16.0 GB memory"):
        check_resources(nodes, BatchOptions(memory_per_task=20), local=True)
    with pytest.raises(ReconInputError, match="node-retries"):
        BatchOptions(node_retries=-1).validate()
