"""The `recon` command line end to end: the demo on a short synthetic video (files, mesh
quality against the ground-truth mesh, GLB axes, the Rerun recording), `recon view`, and
every kind of bad input (one-line error, exit code 2, nothing previously written lost)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh

from recon.commands.cli import build_parser, main
from recon.commands.cli_config import pipeline_config_from_args
from recon.commands.demo import pose_estimator_available
from recon.export.writers import to_gltf_axes
from recon.fusion.upright import camera_up
from recon.io.depth_maps import read_depth_png_mm
from recon.io.pose_formats.trajectories import read_poses

from helpers import glb_vertex_colors, read_recording, save_tiny_depth_anything, save_tiny_dpt

pytestmark = pytest.mark.slow  # end-to-end runs: `make test-fast` leaves them out

FRAMES, WIDTH, HEIGHT = 24, 320, 240


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """`recon demo` on 24 frames at 320x240 with ground-truth poses, recording saved."""
    out = tmp_path_factory.mktemp("demo") / "out"
    code = main(["demo", "-o", str(out), "--frames", str(FRAMES), "--width", str(WIDTH), "--height", str(HEIGHT),
                 "--poses", "gt", "--quiet"])
    assert code == 0
    return out, json.loads((out / "report.json").read_text())


def test_demo_writes_every_output(demo):
    out, report = demo
    for name in ("mesh.ply", "mesh.glb", "recording.rrd", "trajectory.txt", "intrinsics.json", "report.json",
                 "input/synthetic.mp4", "input/poses_gt.txt"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    pngs, npys = sorted((out / "depth").glob("*.png")), sorted((out / "depth").glob("*.npy"))
    assert len(pngs) == len(npys) == FRAMES
    # PNG (mm) and npy (m) hold the same depth, at the working size.
    depth_m = np.load(npys[3])
    assert depth_m.shape == (HEIGHT, WIDTH) and (depth_m > 0).all()
    np.testing.assert_allclose(read_depth_png_mm(pngs[3]), depth_m, atol=0.0006)
    # Trajectory: the ground-truth poses that went in come out (TUM, camera-to-world): given
    # poses are used as given.
    written = read_poses(out / "trajectory.txt").poses
    given = read_poses(out / "input/poses_gt.txt").poses
    np.testing.assert_allclose(written, given, atol=1e-5)
    assert not any(p.name.startswith(".") for p in out.rglob("*")), "temporary files left behind"
    # report.json: inputs, options, versions, per-stage timings, MEDeA loss summary.
    assert report["frames"]["count"] == FRAMES and report["input"]["kind"] == "video"
    assert set(report["seconds"]) == {"decode", "prior", "poses", "undistort", "medea", "refine", "fusion", "export",
                                     "logging"}
    # ... and checked against the frames, which they fit (recon.poses.given.pose_check); not polished.
    check = report["poses"]["check"]
    assert "polish" not in report["poses"] and check["disagreement"] is None and check["median_px"] < 0.3
    # Given intrinsics are used as given: no lens is fitted on top of them, no frame resampled.
    assert report["poses"]["lens_k1"] == 0.0 and report["poses"]["frames_undistorted"] is False
    assert report["intrinsics"]["undistorted"] is None
    assert report["refine"]["method"] == "mvs" and 0.5 < report["refine"]["reconstructed"] <= 1.0
    assert all(v >= 0 for v in report["seconds"].values()) and report["seconds"]["medea"] > 0
    stage1 = report["medea"]["stages"]["stage1"]
    assert stage1["epochs"] > 1 and stage1["last"]["total"] < stage1["first"]["total"]
    # Given poses: the prior's scale was searched against them (medea_core.global_scale).
    searched = report["medea"]["global_scale"]
    assert searched["pairs"] > 0 and searched["applied"] == (searched["gain"] >= 0.05)
    assert {"recon", "torch", "open3d", "rerun"} <= set(report["versions"])
    assert report["options"]["poses"].endswith("poses_gt.txt") and report["intrinsics"]["source"] == "given"


def test_a_runs_report_reruns_it_with_the_same_config(demo):
    """`recon run IN -o OUT --config OUT/report.json` is the run's config again, exactly."""
    out, report = demo
    options = report["options"]
    parser = build_parser()
    args = parser.parse_args(["run", options["input"], "-o", options["output"], "--config", str(out / "report.json")])
    assert json.loads(json.dumps(pipeline_config_from_args(args, parser).to_dict())) == options  # as report.json has it


def test_demo_mesh_quality(demo):
    """MEDeA's depth fuses into a mesh within 5 cm of the ground truth; the raw prior does not."""
    _, report = demo
    ev = report["evaluation"]
    assert ev["depth_adjusted"]["abs_rel"] < 0.4 * ev["depth_prior"]["abs_rel"]
    adjusted, prior = ev["mesh_adjusted"], ev["mesh_prior"]
    assert adjusted["fscore"] >= 0.85, adjusted
    assert adjusted["fscore"] > prior["fscore"] + 0.4, (adjusted, prior)
    assert adjusted["accuracy"] < 0.5 * prior["accuracy"]
    # The refinement (the written depth and mesh) keeps MEDeA's result or betters it.
    assert ev["depth_refined"]["abs_rel"] <= ev["depth_adjusted"]["abs_rel"] + 0.002
    assert ev["mesh_refined"]["fscore"] >= 0.85 and ev["mesh_refined"]["accuracy"] <= adjusted["accuracy"]


def test_glb_matches_ply_and_is_y_up(demo):
    out, report = demo
    ply = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    glb = trimesh.load(str(out / "mesh.glb"), file_type="glb", force="mesh", process=False)
    assert len(glb.vertices) == len(ply.vertices) and len(glb.faces) == len(ply.triangles)
    assert glb_vertex_colors(out / "mesh.glb").shape == (len(ply.vertices), 4)
    # The GLB is the PLY turned by report.json's upright rotation, then to glTF's axes.
    upright = report["upright"]
    rotation = np.asarray(upright["transform"])[:3, :3]
    np.testing.assert_allclose(glb.vertices, to_gltf_axes(np.asarray(ply.vertices), rotation), atol=1e-4)
    # The synthetic world is level (y down, the floor at y = 0, the ceiling above): the
    # floor and walls find the level within 2 degrees, closer than the cameras' mean.
    cameras_up = camera_up(read_poses(out / "trajectory.txt").poses)
    cameras_tilt = np.degrees(np.arccos(-cameras_up[1]))
    assert upright["source"] == "surfaces" and upright["tilt_deg"] < min(2.0, cameras_tilt), (upright, cameras_tilt)
    # In glTF (y up) the floor must be the lowest part of the mesh.
    ply_y = np.asarray(ply.vertices)[:, 1]
    floor = np.abs(ply_y) < 0.02
    assert floor.sum() > 100 and glb.vertices[floor, 1].mean() < np.percentile(glb.vertices[:, 1], 5) + 0.05


def test_recording_has_frames_cameras_mesh_losses(demo):
    out, report = demo
    entities, components, frames, _ = read_recording(out / "recording.rrd")
    for entity in ("/world/camera", "/world/camera/rgb", "/world/camera/prior_depth", "/world/camera/adjusted_depth",
                   "/world/trajectory/00000", "/world/mesh", "/medea/stage1/total"):
        assert entity in entities, entity
    indices = report["frames"]["indices"]
    assert sorted(frames["/world/camera/rgb"]) == indices
    assert sorted(frames["/world/camera/adjusted_depth"]) == indices
    assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices"} <= components["/world/mesh"]
    assert len(frames["/medea/stage1/total#epoch"]) == report["medea"]["stages"]["stage1"]["epochs"]


def test_view_logs_an_output_folder(demo, tmp_path):
    out, report = demo
    rrd = tmp_path / "view.rrd"
    assert main(["view", str(out), "--rerun", "save", str(rrd), "--quiet"]) == 0
    entities, _, frames, _ = read_recording(rrd)
    assert "/world/mesh" in entities
    assert sorted(frames["/world/camera/adjusted_depth"]) == report["frames"]["indices"]
    assert main(["view", str(out), "--rerun", "save", str(rrd), "--quiet"]) == 2  # exists: refused


def test_run_on_an_image_folder_with_a_pose_file(demo, tmp_path):
    """`recon run` on frames as PNGs, poses by file, prior from a folder, MEDeA off, no Rerun."""
    out, _ = demo
    images = tmp_path / "frames"
    images.mkdir()
    cap = cv2.VideoCapture(str(out / "input/synthetic.mp4"))
    for i in range(6):
        ok, bgr = cap.read()
        assert ok
        cv2.imwrite(str(images / f"frame_{i:06d}.png"), bgr)
    cap.release()
    result = tmp_path / "result"
    k = json.loads((out / "intrinsics.json").read_text())
    code = main(["run", str(images), "-o", str(result), "--width", "160", "--poses", str(out / "input/poses_gt.txt"),
                 "--prior", "folder", "--prior-path", str(out / "input/prior"), "--no-medea", "--rerun", "off",
                 "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--quiet", "--no-npy"])
    assert code == 0
    report = json.loads((result / "report.json").read_text())
    assert report["frames"]["working_size"] == [160, 120] and report["medea"] == {}
    assert report["intrinsics"]["values"][0] == pytest.approx(k["fx"] / 2)
    assert len(list((result / "depth").glob("*.png"))) == 6 and not list((result / "depth").glob("*.npy"))
    assert not (result / "recording.rrd").exists()


# --------------------------------------------------------------------------- bad input


def _video(path: Path, frames: int, size=(64, 48)) -> Path:
    fourcc = cv2.VideoWriter_fourcc(*"MJPG" if path.suffix == ".avi" else "mp4v")
    writer = cv2.VideoWriter(str(path), fourcc, 10.0, size)
    rng = np.random.default_rng(0)
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    writer.release()
    return path


def _images(folder: Path, sizes) -> Path:
    folder.mkdir()
    for i, (w, h) in enumerate(sizes):
        cv2.imwrite(str(folder / f"img{i}.png"), np.full((h, w, 3), 100, np.uint8))
    return folder


def _run_fails(capsys, argv, *expected) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("recon: error: "), err
    assert "Traceback" not in err[0]
    for text in expected:
        assert text in err[0], (text, err[0])
    return err[0]


@pytest.mark.parametrize(
    "make_input, expected",
    [
        (lambda d: d / "missing.mp4", ["missing.mp4", "no such file"]),
        (lambda d: (d / "notes.mp4", (d / "notes.mp4").write_text("not a video\n" * 50))[0],
         ["notes.mp4", "not a video"]),
        (lambda d: _video(d / "empty.avi", 0), ["empty.avi", "no decodable frames"]),
        (lambda d: _video(d / "one.mp4", 1), ["one.mp4", "at least 2 frames"]),
        (lambda d: (d / "empty").mkdir() or d / "empty", ["empty", "no images"]),
        (lambda d: _images(d / "mixed", [(64, 48), (64, 48), (32, 24)]), ["img2.png", "32x24", "64x48"]),
    ],
    ids=["missing-file", "not-a-video", "zero-frame-video", "one-frame-video", "empty-folder", "mixed-sizes"],
)
def test_bad_input_one_line_exit_2(tmp_path, capsys, make_input, expected):
    source = make_input(tmp_path)
    out = tmp_path / "out"
    _run_fails(capsys, ["run", str(source), "-o", str(out), "--quiet"], *expected)
    assert not out.exists(), "a failed run must not leave an output folder behind"


def _run_subprocess(*argv: str) -> subprocess.CompletedProcess:
    """`python -m recon ARGV` in a fresh process: its stderr is all of file descriptor 2,
    what C libraries print included (capsys sees only Python's sys.stderr)."""
    return subprocess.run([sys.executable, "-m", "recon", *argv], capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("content", [b"", np.random.default_rng(0).bytes(5000), b"not a video\n" * 50],
                         ids=["empty", "random-bytes", "text"])
def test_not_a_video_says_one_line_and_nothing_from_ffmpeg(tmp_path, content):
    """FFmpeg's own complaint ("moov atom not found") stays off stderr: recon's line says it."""
    fake = tmp_path / "clip.mp4"
    fake.write_bytes(content)
    proc = _run_subprocess("run", str(fake), "-o", str(tmp_path / "out"), "--quiet")
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("recon: error: "), lines
    assert str(fake) in lines[0] and "not a video" in lines[0]
    assert proc.stdout == ""
    assert not (tmp_path / "out").exists()


def test_existing_output_folder_is_kept(tmp_path, capsys):
    video = _video(tmp_path / "clip.mp4", 4)
    out = tmp_path / "out"
    out.mkdir()
    (out / "mesh.ply").write_text("precious result")
    _run_fails(capsys, ["run", str(video), "-o", str(out), "--quiet"], str(out), "not empty", "--overwrite")
    assert (out / "mesh.ply").read_text() == "precious result" and len(list(out.iterdir())) == 1
    _run_fails(capsys, ["demo", "-o", str(out), "--quiet"], "not empty")
    assert (out / "mesh.ply").read_text() == "precious result" and len(list(out.iterdir())) == 1


def test_bad_options(tmp_path, capsys):
    video = _video(tmp_path / "clip.mp4", 4)
    out = str(tmp_path / "out")
    _run_fails(capsys, ["run", str(video), "-o", out, "--intrinsics", "500,500,320"], "--intrinsics", "4 numbers")
    _run_fails(capsys, ["run", str(video), "-o", out, "--intrinsics", "1500,1500,960,540"], "--intrinsics",
               "(960, 540) lies outside")
    _run_fails(capsys, ["run", str(video), "-o", out, "--rerun", "loud"], "--rerun", "loud")
    _run_fails(capsys, ["run", str(video), "-o", out, "--stride", "0"], "stride")
    _run_fails(capsys, ["run", str(video), "-o", out, "--prior", "folder"], "--prior-path")
    _run_fails(capsys, ["run", str(video), "-o", out, "--voxel-size", "-1"], "voxel_size")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "medea.batch_pairs=0"], "batch_pairs=0")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "medea.stage2.lr=-0.1"], "stage2.lr=-0.1")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "medea.image_scale=0"], "image_scale=0.0")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "mesh_every=-3"], "mesh every", "-3")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "depth_motion=0"], "depth motion", "> 0")
    _run_fails(capsys, ["run", str(video), "-o", out, "--device", "gpu0"], "--device gpu0", "cuda:N")
    _run_fails(capsys, ["run", str(video), "-o", out, "--rolling-shutter", "150"], "rolling-shutter readout", "150")
    _run_fails(capsys, ["view", str(tmp_path / "nothing")], "no such file")
    assert not Path(out).exists()


def test_bad_pose_file(tmp_path, capsys):
    video = _video(tmp_path / "clip.mp4", 4)
    poses = tmp_path / "poses.txt"
    poses.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n5 0 0 0 0 0 0 1\n")  # 3 poses, 4 frames, gap at 0.2-0.3 s
    msg = _run_fails(capsys, ["run", str(video), "-o", str(tmp_path / "out"), "--poses", str(poses), "--quiet",
                              "--prior", "folder", "--prior-path", str(_depth_folder(tmp_path, 4))], "poses.txt")
    assert "frame" in msg and not (tmp_path / "out").exists()


@pytest.mark.parametrize("stream", ["off", "on"])
def test_pose_options_reach_the_estimator(demo, tmp_path, capsys, stream):
    """--pose-option sets FrontendConfig fields: a correlation floor no moving frame can pass, with
    no lost frames allowed, stops tracking at the first frame after the keyframe, saying why,
    and naming it as the video counts its frames (every 2nd frame read: the second is frame 2),
    in one-shot and streamed runs."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    result = tmp_path / "result"
    msg = _run_fails(capsys, ["run", str(out / "input/synthetic.mp4"), "-o", str(result), "--width", "160",
                              "--stride", "2", "--stream", stream,
                              "--poses", "estimate", "--pose-method", "frontend", "--pose-option", "max_lost=0",
                              "--pose-option", "min-match-correlation=1", "--prior", "folder",
                              "--prior-path", str(out / "input/prior"), "--intrinsics",
                              f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--quiet", "--rerun", "off"],
                     "tracking lost at frame 2:", "correlation")
    assert "< 1.0" in msg and ": 1 consecutive" in msg and not result.exists()  # both options applied


def test_pose_option_errors_and_list(tmp_path, capsys):
    from recon.poses.frontend.streaming import FrontendConfig

    video = _video(tmp_path / "clip.mp4", 4)
    out = str(tmp_path / "out")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "windw=3"], "unknown pose option", "windw")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "window=three"], "window", "'three'", "int")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "window"], "KEY=VALUE")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "calibrate_lens=maybe"], "bool")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "ba_stride=0"], "ba_stride must be >= 1")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "lost_inlier=1.5"], "lost_inlier", "[0, 1]")
    _run_fails(capsys, ["run", str(video), "-o", out, "--pose-option", "mapper=glomap"], "mapper", "'global'")
    _run_fails(capsys, ["demo", "-o", out, "--pose-option", "windw=3"], "windw")
    assert not Path(out).exists()
    with pytest.raises(SystemExit) as exit_info:  # like --help: no input needed
        main(["run", "--pose-option", "list"])
    assert exit_info.value.code == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[1:]
            if not line.startswith(" ")}  # indented: the summary under a row
    assert rows["window"][1:3] == ["int", str(FrontendConfig().window)]
    assert rows["calibrate_lens"][-2:] == ["FrontendConfig,", "SfMConfig"]
    assert "torch_threads" in rows and "mapper" in rows and "flow" not in rows


def test_output_cut_short_by_the_reader_is_not_an_error():
    """`recon run --pose-option list | head -1`: the pipe closes early; no traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "recon", "run", "--pose-option", "list"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0)
    assert proc.stdout.read(20)  # the header, then stop reading
    proc.stdout.close()
    stderr = proc.stderr.read().decode()
    proc.wait(timeout=60)
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr, stderr
    assert proc.returncode in (0, -13), proc.returncode  # 0, or killed by SIGPIPE before Python saw it


@pytest.mark.parametrize("key, value", [("correction_grid", (2, 5)), ("torch_threads", None), ("calibrate_lens", False),
                                        ("keyframe_flow", 12.5), ("mapper", "global")])
def test_demo_replay_command_reads_back_its_pose_options(key, value):
    from recon.poses.options import format_pose_option, parse_pose_option

    assert parse_pose_option(format_pose_option(key, value)) == (key, value)


def _depth_folder(tmp_path: Path, n: int) -> Path:
    folder = tmp_path / "prior"
    folder.mkdir()
    for i in range(n):
        np.save(folder / f"frame_{i:06d}.npy", np.full((48, 64), 2.0, np.float32))
    return folder


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    """8 frames of the synthetic room at 160x120 as a video, its trajectory and (as the folder
    prior) its true depth, with NaN in the top 10 rows of frame 2 and inf in the left 4
    columns of frame 5, as depth tools write for "no depth"."""
    from recon.commands.demo import write_demo_inputs
    from recon.io.output_folder import OutputFolder
    from recon.synthetic import render_sequence

    seq = render_sequence(8, 160, 120, seed=0)
    inputs = write_demo_inputs(OutputFolder(tmp_path_factory.mktemp("scene")), seq, seq.depth)
    files = sorted(inputs["prior"].glob("*.npy"))
    for k, rows, cols, value in ((2, slice(0, 10), slice(None), np.nan), (5, slice(None), slice(0, 4), np.inf)):
        depth = np.load(files[k])
        depth[rows, cols] = value
        np.save(files[k], depth)
    return seq, inputs, files


def _small_scene_argv(small_scene, out: Path, prior: Path | None = None) -> list[str]:
    seq, inputs, _ = small_scene
    return ["run", str(inputs["video"]), "-o", str(out), "--poses", str(inputs["poses"]), "--prior", "folder",
            "--prior-path", str(prior or inputs["prior"]), "--intrinsics", ",".join(map(str, seq.intrinsics)),
            "--width", "160", "--no-medea", "--refine", "none", "--depth-frames", "all", "--rerun", "off", "--no-npy",
            "--quiet"]


@pytest.mark.parametrize("stream", ["off", "on"])
def test_folder_prior_nan_and_inf_are_invalid_pixels(small_scene, tmp_path, capsys, stream):
    """A depth folder with NaN and inf pixels: the run completes, says so once in a warning,
    and report.json counts them per file (one-shot and streamed runs alike)."""
    _, _, files = small_scene
    out = tmp_path / "out"
    assert main(_small_scene_argv(small_scene, out) + ["--stream", stream]) == 0
    err = capsys.readouterr().err.splitlines()
    assert all(line.startswith("recon: warning: ") for line in err), err
    said = [line for line in err if "NaN" in line]
    assert len(said) == 1 and str(files[2].parent) in said[0], err
    report = json.loads((out / "report.json").read_text())
    assert report.get("streamed", False) == (stream == "on")
    info = report["prior"]["info"]
    assert info["nonfinite_pixels"] == 10 * 160 + 4 * 120
    assert info["nonfinite_files"] == {files[2].name: 10 * 160, files[5].name: 4 * 120}
    # The invalid pixels have no depth in the output either.
    depth = read_depth_png_mm(out / "depth" / files[2].with_suffix(".png").name)
    assert depth.shape == (120, 160) and (depth[:10] == 0).all() and (depth[10:] > 0).mean() > 0.95


@pytest.mark.parametrize("stream", ["off", "on"])
def test_an_empty_mesh_is_not_written_and_says_why(small_scene, tmp_path, capsys, stream):
    """Depth all beyond --max-depth fuses nothing: the run still writes its depth, trajectory
    and report, warns once that the mesh is empty (naming the settings that decide it), and
    removes the mesh an earlier run left in the folder instead of leaving it to pass for this
    run's."""
    out = tmp_path / "out"
    argv = _small_scene_argv(small_scene, out) + ["--stream", stream, "--point-cloud"]
    files = [out / name for name in ("mesh.ply", "mesh.glb", "point_cloud.ply")]
    assert main(argv) == 0
    assert all(path.is_file() for path in files)
    capsys.readouterr()
    assert main(argv + ["--max-depth", "0.05", "--overwrite"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "mesh is empty" in line]
    assert len(err) == 1 and err[0].startswith("recon: warning: ") and "--max-depth 0.05" in err[0], err
    assert not any(path.exists() for path in files)
    report = json.loads((out / "report.json").read_text())
    assert report["fusion"]["triangles"] == 0 and "mesh_ply" not in report["files"]
    assert (out / "trajectory.txt").is_file() and len(list((out / "depth").glob("*.png"))) == 8


def test_folder_prior_map_without_valid_pixel_is_refused(small_scene, tmp_path, capsys):
    _, _, files = small_scene
    prior = tmp_path / "prior"
    prior.mkdir()
    for path in files:
        np.save(prior / path.name, np.load(path))
    np.save(prior / files[3].name, np.full_like(np.load(files[3]), np.nan))
    out = tmp_path / "out"
    _run_fails(capsys, _small_scene_argv(small_scene, out, prior), str(prior / files[3].name), "no valid pixel")
    assert not out.exists()


def test_warnings_are_prefixed_lines_on_stderr(capsys):
    import logging

    from recon.commands.cli import _log_warnings_to_stderr

    _log_warnings_to_stderr()
    _log_warnings_to_stderr()  # once, however often main runs in a process
    logging.getLogger("recon.fusion").warning("skipping %d of %d frames", 2, 9)
    logging.getLogger("recon.poses").info("not shown")
    assert capsys.readouterr().err == "recon: warning: skipping 2 of 9 frames\n"


@pytest.mark.skipif(pose_estimator_available(), reason="pose estimation is installed")
def test_missing_pose_estimator_is_a_clear_error(tmp_path, capsys):
    video = _video(tmp_path / "clip.mp4", 4)
    _run_fails(capsys, ["run", str(video), "-o", str(tmp_path / "out"), "--poses", "estimate", "--quiet",
                        "--prior", "folder", "--prior-path", str(_depth_folder(tmp_path, 4))],
               "pose estimation not available", "--poses FILE")


def test_frame_budget_raises_the_stride(tmp_path):
    from recon.core.stages import select_frames

    video = _video(tmp_path / "clip.mp4", 12)
    source = select_frames(video, frame_budget=5)
    assert source.selection.stride == 3 and source.count == 4
    source = select_frames(video, frame_budget=5, stride=1)
    assert source.count == 12


def test_the_frame_budget_counts_frames_at_640x480():
    """A one-shot run's memory grows with its frames' pixels: a larger frame counts for
    more, a smaller one for one; streamed windows count the same way."""
    from recon.core.config import PipelineConfig
    from recon.core.stages import budget_capacity, window_frames

    assert budget_capacity(150, (480, 640)) == 150 and budget_capacity(150, (240, 320)) == 150
    assert budget_capacity(150, (960, 1280)) == 37 and budget_capacity(150, (1138, 640)) == 63
    config = PipelineConfig(Path("in.mp4"), Path("out"))
    assert window_frames(config, (480, 640)) == 48 and window_frames(config, (1138, 640)) == 20
    assert window_frames(config, (4000, 3000)) == config.window_overlap + 2


def test_help_texts():
    parser = build_parser()
    texts = {}
    for name in ("run", "demo", "view"):
        sub = parser._subparsers._group_actions[0].choices[name]
        texts[name] = sub.format_help()
    for option in ("--poses", "--prior", "--intrinsics", "--fov", "--stride", "--width", "--voxel-size", "--device",
                   "--pose-option", "--rerun", "--preset", "--no-medea", "--set", "--overwrite", "examples:",
                   "--prior-path", "--prior-align"):
        assert option in texts["run"], option
    assert "--frames" in texts["demo"] and "--poses" in texts["demo"] and "--pose-option" in texts["demo"]
    assert "recording.rrd" in texts["view"]


def _run_parser():
    return build_parser()._subparsers._group_actions[0].choices["run"]


def test_run_help_is_short_and_says_where_the_other_settings_are():
    """`recon run --help` lists at most 45 options; its epilog sends the rest to --set/--config."""
    text = _run_parser().format_help()
    options = [line for line in text.splitlines() if line.startswith("  -")]
    assert len(options) <= 45, len(options)
    assert "--set NAME=VALUE or --config FILE" in " ".join(text.split())
    for gone in ("--stage1-epochs", "--no-photometric", "--window-overlap", "--block-count", "--refine-option"):
        assert gone not in text


def test_batch_takes_set_and_config_like_run():
    """`recon batch` has the run flags and --set/--config, so a setting without a flag reaches
    every input's config as it reaches `recon run`'s."""
    import argparse

    parser = build_parser()
    args = parser.parse_args(["batch", "a.mp4", "b.mp4", "-o", "out", "--set", "medea.stage1.epochs=7",
                              "--set", "fusion.block_count=1000", "--device", "cpu"])
    run_args = argparse.Namespace(**{**vars(args), "input": ".", "output": ".", "overwrite": False, "rerun": ["off"]})
    config = pipeline_config_from_args(run_args, parser)
    assert config.medea.stage1.epochs == 7 and config.fusion.block_count == 1000


def test_flag_help_is_the_field_docstring():
    """A flag that sets a setting has no help of its own: its help is the summary of that
    setting's field docstring (recon.options.field_summary), and every setting of RUN_FLAGS has one."""
    from recon.commands.cli_config import RUN_FLAGS, setting_field
    from recon.core.config import PipelineConfig
    from recon.options import field_summary

    helps = {a.option_strings[0]: a.help for a in _run_parser()._actions if a.option_strings}
    flags = [flag for _, _, group in RUN_FLAGS for flag in group]
    assert len(flags) >= 30
    for flag in flags:
        summary = field_summary(*setting_field(flag.setting))
        assert summary and helps[flag.option].startswith(summary.replace("%", "%%")), flag.option
    assert helps["--no-medea"].startswith(field_summary(PipelineConfig, "adjust"))


def test_refine_setting_errors_and_list(tmp_path, capsys):
    """The refinement's settings are reached with --set mvs.NAME: misspelt, mistyped and
    out-of-range values stop the run in one line, and `--set list` names them all."""
    from mvs_core import MvsConfig

    video = _video(tmp_path / "clip.mp4", 4)
    out = str(tmp_path / "out")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "mvs.hypothesis=3"], "no such setting",
               "mvs.hypotheses")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "mvs.hypotheses=many"], "hypotheses", "int")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "mvs.band=-1"], "band")
    _run_fails(capsys, ["run", str(video), "-o", out, "--set", "mvs.keep_best=9"], "keep_best")
    _run_fails(capsys, ["run", str(video), "-o", out, "--min-confidence", "2"], "min_confidence")
    assert not Path(out).exists()
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--set", "list"])
    assert exit_info.value.code == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()[1:]}
    assert rows["mvs.hypotheses"][1:3] == ["int", str(MvsConfig().hypotheses)]


def test_refine_none_keeps_the_papers_pipeline(demo, tmp_path):
    """--refine none: no polish, no refinement; the depth written is MEDeA's and every pixel is fused."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    common = ["--poses", str(out / "input/poses_gt.txt"), "--prior", "folder", "--prior-path", str(out / "input/prior"),
              "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--width", "0", "--max-frames", "12",
              "--quiet", "--rerun", "off", "--no-npy"]
    plain = tmp_path / "plain"
    assert main(["run", str(out / "input/synthetic.mp4"), "-o", str(plain), "--refine", "none", *common]) == 0
    report = json.loads((plain / "report.json").read_text())
    assert report["refine"] == {"method": "none"} and report["seconds"]["refine"] == 0.0
    assert "polish" not in report["poses"] and report["options"]["refine"] == "none"
    # Unrefined depth is fused unconfirmed: a voxel needs two frames (refined: one, see below).
    assert report["fusion"]["weight_threshold"] == 2.0
    refined = tmp_path / "refined"
    assert main(["run", str(out / "input/synthetic.mp4"), "-o", str(refined), *common,
                 "--set", "mvs.num_sources=3"]) == 0
    report = json.loads((refined / "report.json").read_text())
    assert report["options"]["mvs"]["num_sources"] == 3 and len(report["refine"]["sources"][0]) == 3
    assert 0.3 < report["refine"]["reconstructed"] <= 1.0
    assert report["fusion"]["weight_threshold"] == 1.0 and report["options"]["fusion"]["weight_threshold"] is None


@pytest.mark.parametrize("mode", ["one-shot", "stream"])
def test_given_poses_the_frames_contradict_are_said_and_gated_on_request(demo, tmp_path, capsys, monkeypatch,
                                                                         mode):
    """The epipolar check's verdict on the given poses (recon.poses.given.pose_check, tested on TUM
    and 7-Scenes in test_pose_check) is said in one warning and recorded; MEDeA still runs,
    unless --medea-gate skips it, in a one-shot run and in every window of a streamed run
    (which judges the first frames as they come)."""
    import recon.poses.given.pose_check as pose_check

    real = pose_check.check_given_poses

    def contradicted(*args, **kwargs):
        check = real(*args, **kwargs)
        check.disagreement = "the flow misses the epipolar lines by 2.00 px"
        return check

    monkeypatch.setattr(pose_check, "check_given_poses", contradicted)
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    common = ["--poses", str(out / "input/poses_gt.txt"), "--prior", "folder", "--prior-path", str(out / "input/prior"),
              "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--width", "0", "--max-frames", "12",
              "--quiet", "--rerun", "off", "--no-npy", "--no-glb"]
    if mode == "one-shot":
        common += ["--stream", "off"]
    else:  # two windows at least, to see that the verdict holds for the next
        common += ["--stream", "on", "--depth-frames", "all", "--window", "6", "--set", "window_overlap=2"]
    said = tmp_path / "said"
    assert main(["run", str(out / "input/synthetic.mp4"), "-o", str(said), *common]) == 0
    report = json.loads((said / "report.json").read_text())
    err = capsys.readouterr().err
    assert report["poses"]["check"]["disagreement"] == "the flow misses the epipolar lines by 2.00 px"
    assert report["poses"]["check"]["judged"] >= 4 and report["options"]["medea_gate"] is False
    assert err.count("the frames contradict the given poses") == 1 and "--medea-gate" in err
    if mode == "stream":
        assert all(w["medea_epochs"] and not w["medea_skipped"] for w in report["windows"]["each"])
    else:
        assert report["medea"]["stages"]["stage1"]["epochs"] > 0
    gated = tmp_path / "gated"
    assert main(["run", str(out / "input/synthetic.mp4"), "-o", str(gated), *common, "--medea-gate"]) == 0
    report = json.loads((gated / "report.json").read_text())
    err = capsys.readouterr().err
    assert "MEDeA skipped, the frames contradict the given poses" in err
    skipped = "the frames contradict the given poses: the flow misses the epipolar lines by 2.00 px"
    if mode == "stream":
        windows = report["windows"]
        assert windows["medea_skipped"] == windows["count"] >= 2
        assert all(w["medea_skipped"] == skipped and not w["medea_epochs"] for w in windows["each"])
    else:
        assert report["medea"] == {"skipped": skipped}
        assert report["seconds"]["medea"] == 0.0 and report["refine"]["reconstructed"] > 0.3


def test_a_known_lens_is_undone_before_every_stage(demo, tmp_path, capsys):
    """--distortion (OpenCV's k1,k2,p1,p2[,k3]) with the camera it belongs to: the frames are
    resampled into the pinhole camera as they are decoded (report.json says with what); the
    coefficients alone, with no camera, are refused."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    video = str(out / "input/synthetic.mp4")
    common = ["--poses", str(out / "input/poses_gt.txt"), "--prior", "folder", "--prior-path",
              str(out / "input/prior"), "--width", "0", "--max-frames", "4", "--no-medea", "--refine", "none",
              "--quiet", "--rerun", "off", "--no-npy", "--no-glb"]
    lens = tmp_path / "lens"
    assert main(["run", video, "-o", str(lens), *common, "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}",
                 "--distortion", "0.1,0,0,0"]) == 0
    undistorted = json.loads((lens / "report.json").read_text())["intrinsics"]["undistorted"]
    assert undistorted["distortion"] == [0.1, 0.0, 0.0, 0.0] and undistorted["source"] == "given"
    assert undistorted["max_shift_px"] > 1.0
    _run_fails(capsys, ["run", video, "-o", str(tmp_path / "no_camera"), *common, "--distortion", "0.1,0,0,0"],
               "--distortion needs the camera")
    _run_fails(capsys, ["run", video, "-o", str(tmp_path / "bad"), *common, "--distortion", "0.1,0"],
               "--distortion", "4 or 5 numbers")


@pytest.mark.skipif(not pose_estimator_available(), reason="pose estimation not installed")
def test_a_scale_the_prior_cannot_vouch_for_is_written_and_marked_unless_stopped(demo, tmp_path, capsys):
    """FastDepth does not see the rendered room (2.4x too near, its depth uncorrelated with
    the room's): with the poses estimated, whose metres come from it, the run writes the
    result, says once that its size is not to be trusted, and marks it in report.json
    (recon.poses.checks.prior_agreement), the fusion's voxel following the depth alone; under
    --on-break stop it stops with one line naming the frames and writes nothing."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    common = [str(out / "input/synthetic.mp4"), "--width", "0", "--no-medea", "--refine", "none", "--quiet",
              "--rerun", "off", "--no-npy", "--no-glb", "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}"]
    stopped = tmp_path / "stopped"
    _run_fails(capsys, ["run", "-o", str(stopped), *common, "--on-break", "stop"],
               "does not follow the scene's geometry at frames 0-", "without --on-break stop")
    assert not (stopped / "mesh.ply").exists() and not (stopped / "trajectory.txt").exists()
    kept = tmp_path / "kept"
    assert main(["run", "-o", str(kept), *common]) == 0
    err = capsys.readouterr().err
    assert err.count("does not follow the scene's geometry") == 1 and "not to be trusted" in err
    report = json.loads((kept / "report.json").read_text())
    verdict = report["poses"]["metric_scale"]
    assert verdict["judged"] and not verdict["trusted"] and verdict["median"] < verdict["min_correlation"]
    assert (kept / "mesh.ply").is_file()


def test_rolling_shutter_resamples_the_frames_and_estimates_the_poses_again(demo, tmp_path, capsys):
    """--rolling-shutter: a one-shot run resamples the turning frames and estimates the poses
    again on them (report.json: poses.rolling_shutter); a streamed run says it does not."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    video = str(out / "input/synthetic.mp4")
    common = ["--poses", "estimate", "--pose-method", "frontend", "--prior", "folder", "--prior-path",
              str(out / "input/prior"), "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--width", "0",
              "--no-medea", "--refine", "none", "--rolling-shutter", "30", "--quiet", "--rerun", "off", "--no-npy"]
    one_shot = tmp_path / "one_shot"
    assert main(["run", video, "-o", str(one_shot), "--stream", "off", *common]) == 0
    report = json.loads((one_shot / "report.json").read_text())
    shutter = report["poses"]["rolling_shutter"]
    assert shutter["readout_ms"] == 30.0 and shutter["frames_resampled"] >= FRAMES // 2
    assert 0.5 < shutter["max_shift_px"] < 20 and shutter["median_turn_deg_per_s"] > 5
    assert report["options"]["rolling_shutter"] == 30.0
    assert len(read_poses(one_shot / "trajectory.txt").poses) == FRAMES
    assert "not applied" not in capsys.readouterr().err
    assert main(["run", video, "-o", str(tmp_path / "streamed"), "--stream", "on", *common]) == 0
    assert "--rolling-shutter is not applied in a streamed run" in capsys.readouterr().err


@pytest.mark.parametrize("stream", ["off", "on"])
def test_frames_without_pose_evidence_are_dropped_with_a_warning(demo, tmp_path, capsys, stream):
    """Three noise frames in the middle of the walk: the front end cannot place them, the
    quality gate drops them from depth and fusion with one warning, report.json names them,
    and the recording shows each frame's tracking state (dropped ones in red), at once and
    streamed."""
    out, _ = demo
    priors = sorted((out / "input/prior").iterdir())
    cap = cv2.VideoCapture(str(out / "input/synthetic.mp4"))
    images, prior_folder = tmp_path / "frames", tmp_path / "prior"
    images.mkdir(), prior_folder.mkdir()
    rng = np.random.default_rng(0)
    n = 0
    for i in range(FRAMES):
        ok, bgr = cap.read()
        assert ok
        if i == 12:
            for _ in range(3):
                cv2.imwrite(str(images / f"frame_{n:06d}.png"), rng.integers(0, 256, bgr.shape, dtype=np.uint8))
                np.save(prior_folder / f"frame_{n:06d}.npy", np.load(priors[i]))
                n += 1
        cv2.imwrite(str(images / f"frame_{n:06d}.png"), bgr)
        np.save(prior_folder / f"frame_{n:06d}.npy", np.load(priors[i]))
        n += 1
    cap.release()
    k = json.loads((out / "intrinsics.json").read_text())
    result = tmp_path / "result"
    code = main(["run", str(images), "-o", str(result), "--poses", "estimate", "--pose-method", "frontend",
                 "--prior", "folder", "--prior-path", str(prior_folder), "--intrinsics",
                 f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--quiet", "--rerun", "save", "--no-npy",
                 "--stream", stream])
    assert code == 0
    err = capsys.readouterr().err
    assert "recon: warning: 3 of 27 frames have no pose the images back (video frames 12-14)" in err
    report = json.loads((result / "report.json").read_text())
    quality = report["poses"]["quality"]
    assert quality["dropped"] == 3 and quality["dropped_ranges"] == [[12, 14]]
    if stream == "off":
        assert report["frames"]["count"] == 24 and 12 not in report["frames"]["indices"]
        assert len(list((result / "depth").glob("*.png"))) == 24
    else:  # depth for the frames the camera's motion selects, none of them dropped
        assert not {12, 13, 14} & set(report["frames"]["depth_indices"])
        assert len(list((result / "depth").glob("*.png"))) == len(report["frames"]["depth_indices"])
    entities, _, frames, _ = read_recording(result / "recording.rrd")
    # A streamed run keeps no pose for a dropped frame, so it has no red camera to show.
    assert "/tracking" in entities and ("/world/dropped" in entities) == (stream == "off")
    assert sorted(frames["/tracking"]) == list(range(27))


def test_a_run_that_dies_leaves_a_folder_that_says_so(demo, tmp_path, capsys, monkeypatch):
    """UNFINISHED.txt is there from the start of a run and goes at its end: the remains of a
    run that failed (or crashed in native code, where nothing can clean up) say so, even
    over an earlier run's files, and recon eval, view and export refuse them."""
    out, _ = demo
    k = json.loads((out / "intrinsics.json").read_text())
    folder = tmp_path / "run"
    args = ["run", str(out / "input/synthetic.mp4"), "-o", str(folder), "--poses",
            str(out / "input/poses_gt.txt"), "--prior", "folder", "--prior-path", str(out / "input/prior"),
            "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--max-frames", "6", "--no-medea",
            "--refine", "none", "--quiet", "--rerun", "off"]
    assert main(args) == 0
    assert (folder / "report.json").is_file() and not (folder / "UNFINISHED.txt").exists()

    def dies(*_, **__):
        raise MemoryError("out of memory in fusion (simulated)")

    with monkeypatch.context() as patch:
        patch.setattr("recon.fusion.fuse", dies)
        with pytest.raises(MemoryError):
            main([*args, "--overwrite"])
    assert (folder / "UNFINISHED.txt").is_file() and (folder / "report.json").is_file()  # the earlier run's
    capsys.readouterr()
    for command in (["eval", str(folder), "--gt", str(out / "input")], ["export", str(folder), "--to", "colmap"],
                    ["view", str(folder), "--rerun", "save", str(tmp_path / "v.rrd")]):
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "did not finish (UNFINISHED.txt is there)" in err[0], (command, err)
    assert main([*args, "--overwrite"]) == 0
    assert not (folder / "UNFINISHED.txt").exists()


def _six_frames_over(demo_out, folder) -> list[str]:
    """`recon run` of six frames of the demo's inputs (poses, prior and camera given, no MEDeA
    or refinement: fast) into `folder` with --overwrite."""
    k = json.loads((demo_out / "intrinsics.json").read_text())
    return ["run", str(demo_out / "input/synthetic.mp4"), "-o", str(folder), "--poses",
            str(demo_out / "input/poses_gt.txt"), "--prior", "folder", "--prior-path", str(demo_out / "input/prior"),
            "--intrinsics", f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}", "--max-frames", "6", "--no-medea",
            "--refine", "none", "--quiet", "--rerun", "off", "--overwrite"]


def test_overwrite_names_what_an_earlier_run_left_and_keeps_it(demo, tmp_path, capsys):
    """A run with --overwrite into a folder that holds an earlier run's segment folder: the
    run writes its single reconstruction, says the segment folder is not part of it, and
    leaves it where it was (other files are never deleted)."""
    out, _ = demo
    folder = tmp_path / "run"
    (folder / "segment_03").mkdir(parents=True)
    (folder / "segment_03" / "report.json").write_text("{}")
    args = _six_frames_over(out, folder)
    capsys.readouterr()
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "segment_03 left by an earlier run, not part of this one" in err
    assert (folder / "segment_03" / "report.json").is_file() and (folder / "mesh.ply").is_file()


def test_overwrite_removes_what_an_earlier_run_wrote_and_nothing_else(demo, tmp_path, capsys):
    """--overwrite into the folder of an earlier run written as two segments: the new single
    reconstruction replaces them. What the earlier report.json listed and the new run did not
    write again goes (segment_00 wholly, segment_01's mesh and depth); a file recon did not
    write stays, in segment_01 and at the top, and the segment folder holding it is named."""
    out, _ = demo
    folder = tmp_path / "run"
    for name in ("segment_00", "segment_01"):
        (folder / name / "depth").mkdir(parents=True)
        (folder / name / "mesh.ply").write_text("old")
        (folder / name / "depth" / "frame_000000.png").write_text("old")
        (folder / name / "report.json").write_text(json.dumps(
            {"files": {"mesh_ply": "mesh.ply", "depth": "depth"}, "frames": {"names": ["frame_000000"]}}))
    (folder / "report.json").write_text(json.dumps({"files": {"segment_00": "segment_00",
                                                              "segment_01": "segment_01"}}))
    (folder / "segment_01" / "notes.txt").write_text("mine")
    (folder / "mine.txt").write_text("mine")
    args = _six_frames_over(out, folder)
    capsys.readouterr()
    assert main(args) == 0
    err = capsys.readouterr().err
    assert not (folder / "segment_00").exists()
    assert sorted(p.name for p in (folder / "segment_01").iterdir()) == ["notes.txt"]
    assert (folder / "mine.txt").read_text() == "mine" and (folder / "mesh.ply").is_file()
    assert "segment_01 left by an earlier run" in err and "segment_00" not in err
    assert json.loads((folder / "report.json").read_text())["files"]["mesh_ply"] == "mesh.ply"


@pytest.mark.parametrize("output", ["/proc/recon_out", "/proc/self/status/out"])
def test_output_folder_that_cannot_be_written_is_one_line(tmp_path, capsys, output):
    """/proc cannot hold a folder (mkdir fails) and a file cannot hold one either: the one-line
    error and exit 2, before any frame is decoded."""
    video = _video(tmp_path / "clip.mp4", 4)
    _run_fails(capsys, ["run", str(video), "-o", output, "--quiet"], output, "output folder")


# --------------------------------------------------------------------------- a fresh install


def test_run_on_a_fresh_install_uses_the_packaged_fastdepth(tmp_path, monkeypatch):
    """`recon run` with the default prior where nothing but the package is present: no
    ../shared beside the checkout, no cache, no $RECON_WEIGHTS (issue 23: "fastdepth weights
    not found"). It runs on the FastDepth model packaged with recon and writes a mesh."""
    import recon.priors
    import recon.priors.weights as weights
    from recon.io.pose_formats.trajectories import write_poses
    from recon.synthetic import render_sequence

    # Hide every place outside the package (raising=False: an older lookup order had them).
    monkeypatch.delenv(weights.ENV_VAR, raising=False)
    monkeypatch.setattr(weights, "SHARED_WEIGHTS", tmp_path / "no_shared", raising=False)
    monkeypatch.setattr(weights, "CACHE_WEIGHTS", tmp_path / "no_cache", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))

    seq = render_sequence(num_frames=6, width=128, height=96, seed=0)
    video = tmp_path / "my_video.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (128, 96))
    for rgb in seq.rgb:
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    poses = tmp_path / "poses.txt"
    write_poses(poses, seq.poses, "tum", timestamps=np.arange(len(seq.poses)) / 10.0)
    fx, fy, cx, cy = seq.intrinsics
    out = tmp_path / "out"
    code = main(["run", str(video), "-o", str(out), "--poses", str(poses), "--intrinsics", f"{fx},{fy},{cx},{cy}",
                 "--width", "0", "--no-medea", "--refine", "none", "--rerun", "off", "--no-npy", "--no-glb",
                 "--quiet"])
    assert code == 0
    assert (out / "mesh.ply").stat().st_size > 0
    report = json.loads((out / "report.json").read_text())
    packaged = Path(recon.priors.__file__).resolve().parent / "models" / "fastdepth.npz"
    assert report["prior"]["name"] == "fastdepth" and report["prior"]["info"]["weights"] == str(packaged)
# --------------------------------------------------------------------------- a local Hugging Face model (--prior hf)


@pytest.fixture(scope="module")
def rgbd_room(tmp_path_factory) -> Path:
    """6 frames of the synthetic room at 96x72 as an Open3D/Redwood RGB-D folder: colour, depth
    (uint16 mm), trajectory.log, camera.json; ground-truth poses and sensor depth for `recon run`."""
    from recon.io.pose_formats.trajectories import write_poses
    from recon.synthetic import render_sequence

    room = render_sequence(6, 96, 72, seed=0)
    root = tmp_path_factory.mktemp("rgbd_room")
    (root / "color").mkdir()
    (root / "depth").mkdir()
    for i, (rgb, depth) in enumerate(zip(room.rgb, room.depth)):
        cv2.imwrite(str(root / "color" / f"{i:05d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(root / "depth" / f"{i:05d}.png"), np.round(depth * 1000).astype(np.uint16))
    write_poses(root / "trajectory.log", room.poses, "log")
    fx, fy, cx, cy = room.intrinsics
    k = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    (root / "camera.json").write_text(json.dumps({"width": 96, "height": 72,
                                                  "intrinsic_matrix": np.asarray(k).T.ravel().tolist()}))
    return root


def _hf_run(rgbd_room: Path, model: Path, out: Path, *options: str) -> dict:
    """`recon run` on the RGB-D room with ground-truth poses and the HF model; its report.json."""
    code = main(["run", str(rgbd_room), "-o", str(out), "--prior", "hf", "--prior-path", str(model), "--poses", "gt",
                 "--width", "0", "--rerun", "off", "--quiet", *options])
    assert code == 0
    assert len(list((out / "depth").glob("*.png"))) == 6 and len(list((out / "depth").glob("*.npy"))) == 6
    assert len(trimesh.load(out / "mesh.ply").vertices) > 0
    return json.loads((out / "report.json").read_text())


def test_hf_prior_affine_disparity_aligned_to_fastdepth(rgbd_room, fastdepth_weights, tmp_path):
    """A DPT model (affine-invariant disparity, from its config) is fitted to FastDepth by default;
    report.json says which model, what it predicts and what it was aligned to."""
    pytest.importorskip("transformers", reason="the hf prior needs the optional extra 'hf' (transformers)")
    model = save_tiny_dpt(tmp_path / "dpt")
    report = _hf_run(rgbd_room, model, tmp_path / "out", "--weights", str(fastdepth_weights), "--no-medea",
                     "--refine", "none")
    prior = report["prior"]
    assert prior["name"] == "hf" and prior["kind"] == "metric" and prior["features"] is None
    assert prior["info"]["path"] == str(model) and prior["info"]["model_type"] == "dpt"
    assert prior["info"]["output"] == "affine_disparity" and prior["info"]["aligned_to"] == "prior:fastdepth"
    options = report["options"]
    assert (options["prior"], options["prior_path"], options["prior_align"]) == ("hf", str(model), "fastdepth")
    depth = np.load(sorted((tmp_path / "out" / "depth").glob("*.npy"))[0])
    assert np.isfinite(depth).all() and (depth > 0).mean() > 0.5  # metric, from the alignment


def test_hf_prior_aligned_to_sensor_depth(rgbd_room, tmp_path):
    pytest.importorskip("transformers", reason="the hf prior needs the optional extra 'hf' (transformers)")
    model = save_tiny_dpt(tmp_path / "dpt")
    report = _hf_run(rgbd_room, model, tmp_path / "out", "--prior-align", "sensor", "--no-medea", "--refine", "none")
    assert report["prior"]["info"]["aligned_to"] == "prior:sensor" and report["prior"]["kind"] == "metric"
    assert report["options"]["prior_align"] == "sensor"


def test_hf_prior_metric_model_streamed_with_medea(rgbd_room, tmp_path):
    """A metric Depth Anything is used as it is (no alignment), also batch by batch in a streamed
    run, and MEDeA runs on it (no encoder features)."""
    pytest.importorskip("transformers", reason="the hf prior needs the optional extra 'hf' (transformers)")
    model = save_tiny_depth_anything(tmp_path / "da")
    report = _hf_run(rgbd_room, model, tmp_path / "out", "--stream", "on", "--depth-frames", "all",
                     "--set", "medea.stage1.epochs=2", "--set", "medea.stage2.epochs=2", "--refine", "none")
    prior = report["prior"]
    assert report["streamed"] and prior["name"] == "hf" and prior["info"]["path"] == str(model)
    assert prior["info"]["model_type"] == "depth_anything" and prior["info"]["output"] == "metric"
    assert "aligned_to" not in prior["info"] and report["windows"]["count"] >= 1


def test_hf_prior_option_errors(tmp_path, capsys, monkeypatch):
    """What can be told without loading a model (nor transformers installed): one line, exit 2,
    no output folder."""
    video = _video(tmp_path / "clip.mp4", 4)
    out = str(tmp_path / "out")
    (tmp_path / "weights.bin").write_bytes(b"")
    (tmp_path / "empty").mkdir()
    model = tmp_path / "model"
    model.mkdir()
    (model / "config.json").write_text('{"model_type": "dpt"}')
    run = ["run", str(video), "-o", out, "--quiet", "--prior", "hf"]
    _run_fails(capsys, run, "prior 'hf'", "--prior-path MODEL_DIR")
    _run_fails(capsys, [*run, "--prior-path", str(tmp_path / "missing")], "missing", "no such", "never downloaded")
    _run_fails(capsys, [*run, "--prior-path", str(tmp_path / "weights.bin")], "weights.bin", "not a folder")
    _run_fails(capsys, [*run, "--prior-path", str(tmp_path / "empty")], "empty", "no config.json")
    monkeypatch.setitem(sys.modules, "transformers", None)  # `import transformers` fails, as when not installed
    _run_fails(capsys, [*run, "--prior-path", str(model)], "needs the optional dependency transformers",
               "recon[hf]")
    assert not Path(out).exists()


def test_hf_model_that_cannot_load_fails_before_decoding(tmp_path, capsys, monkeypatch):
    pytest.importorskip("transformers", reason="the hf prior needs the optional extra 'hf' (transformers)")
    def no_decoding(*args, **kwargs):
        raise AssertionError("frames decoded before the model was loaded")

    monkeypatch.setattr("recon.drivers.oneshot.decode", no_decoding)
    video = _video(tmp_path / "clip.mp4", 4)
    out = str(tmp_path / "out")
    model = save_tiny_dpt(tmp_path / "dpt")
    (model / "config.json").write_text('{"model_type": "bert"}')  # not a depth model
    capsys.readouterr()
    run = ["run", str(video), "-o", out, "--quiet", "--prior", "hf", "--prior-path", str(model)]
    _run_fails(capsys, run, str(model), "cannot load the depth model")
    model = save_tiny_dpt(tmp_path / "dpt2")  # loads, predicts disparity: the reference must exist
    capsys.readouterr()
    _run_fails(capsys, [*run[:-1], str(model), "--prior-align", "sensor"], "--prior-align sensor", "RGB-D")
    assert not Path(out).exists()


@pytest.mark.parametrize("masked_as", [TypeError, None])
def test_sigterm_is_reported_as_such_even_when_a_library_masks_it(monkeypatch, capsys, masked_as):
    """A C function interrupted by SIGTERM (numpy.fromfile inside np.load) can replace the
    handler's exception with its own TypeError; the run was still terminated, and says so."""
    import signal

    from recon.commands import cli

    def stopped_mid_read(args):
        try:
            signal.raise_signal(signal.SIGTERM)
        except BaseException:
            if masked_as is None:
                raise
            raise masked_as("expected str, bytes or os.PathLike object, not BufferedReader") from None

    monkeypatch.setitem(cli._COMMANDS, "eval", stopped_mid_read)
    before = signal.getsignal(signal.SIGTERM)
    assert main(["eval", "somewhere", "--gt", "elsewhere"]) == 128 + signal.SIGTERM
    assert capsys.readouterr().err.strip().splitlines()[-1] == "recon: terminated"
    assert signal.getsignal(signal.SIGTERM) is before  # the handler is put back


def test_an_ordinary_error_after_a_finished_run_is_not_taken_for_a_sigterm(monkeypatch):
    from recon.commands import cli

    def broken(args):
        raise TypeError("a bug")

    monkeypatch.setitem(cli._COMMANDS, "eval", broken)
    with pytest.raises(TypeError, match="a bug"):
        main(["eval", "somewhere", "--gt", "elsewhere"])


def test_a_crash_in_native_code_leaves_the_python_stack_on_stderr():
    """A segmentation fault inside a run (here: reading address 0) says where it happened."""
    import subprocess
    import sys

    code = ("import ctypes, recon.commands.cli as cli\n"
            "cli._main = lambda argv: ctypes.string_at(0)\n"
            "cli.main(['run'])\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert "Segmentation fault" in done.stderr and "recon/commands/cli.py" in done.stderr, done.stderr[-2000:]
