"""`recon export` and `recon run --export` (recon.export.tools and the modules it runs): the
COLMAP text model read back with pycolmap and the nerfstudio transforms.json checked field
by field, both against the run's own files (trajectory, intrinsics, depth maps, mesh); the
frames decoded again from the input; streamed runs, an output folder of the previous
version, segments, a known lens, and the command line's errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from recon.commands.cli import main
from recon.errors import ReconInputError
from recon.export import ExportOptions, export_colmap, export_folder, export_nerfstudio
from recon.export.colmap_export import colmap_text_model
from recon.export.nerfstudio_export import nerfstudio_transforms
from recon.io.pose_formats.trajectories import read_poses

from helpers import no_temp_files, random_poses

pytestmark = pytest.mark.slow  # end-to-end runs: `make test-fast` leaves them out

FRAMES, WIDTH, HEIGHT = 8, 160, 120
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: OpenCV (x right, y down, z forward) -> OpenGL
QUIET = ExportOptions(progress=False)


def _rotation(axis, degrees: float) -> np.ndarray:
    """A rigid transform (4, 4): a rotation about `axis` and a translation."""
    rvec = np.asarray(axis, np.float64) / np.linalg.norm(axis) * np.radians(degrees)
    t = np.eye(4)
    t[:3, :3] = cv2.Rodrigues(rvec)[0]
    t[:3, 3] = [0.3, -0.2, 0.1]
    return t


UPRIGHT = _rotation([1.0, 0.2, -0.3], 17.0)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The synthetic room (8 frames, 160x120) as a video with its trajectory and depth, and two
    quick runs of it (given poses, the true depth as the prior, no MEDeA, no refinement): a
    one-shot run with `--export colmap,nerfstudio`, and a streamed one that gives every other
    frame depth."""
    from recon.commands.demo import write_demo_inputs
    from recon.io.output_folder import OutputFolder
    from recon.synthetic import render_sequence

    root = tmp_path_factory.mktemp("export")
    seq = render_sequence(FRAMES, WIDTH, HEIGHT, seed=0)
    inputs = write_demo_inputs(OutputFolder(root / "scene"), seq, seq.depth)
    common = ["--poses", str(inputs["poses"]), "--prior", "folder", "--prior-path", str(inputs["prior"]),
              "--intrinsics", ",".join(map(str, seq.intrinsics)), "--width", str(WIDTH), "--no-medea",
              "--refine", "none", "--rerun", "off", "--quiet"]
    one_shot, streamed = root / "one_shot", root / "streamed"
    assert main(["run", str(inputs["video"]), "-o", str(one_shot), "--stream", "off", "--export",
                 "colmap,nerfstudio", *common]) == 0
    assert main(["run", str(inputs["video"]), "-o", str(streamed), "--stream", "on", "--depth-frames", "2",
                 *common]) == 0
    return {"seq": seq, "inputs": inputs, "one_shot": one_shot, "streamed": streamed, "common": common}


def _copy(run: Path, dst: Path, upright: np.ndarray | None = None, edit=None) -> Path:
    """A copy of an output folder (without its exports), with report.json's upright transform
    set, and `edit(report)` applied."""
    shutil.copytree(run, dst, ignore=shutil.ignore_patterns("colmap", "nerfstudio"))
    report = json.loads((dst / "report.json").read_text())
    if upright is not None:
        report["upright"] = {"transform": upright.tolist(), "source": "surfaces", "tilt_deg": 17.0}
    if edit is not None:
        edit(report)
    (dst / "report.json").write_text(json.dumps(report))
    return dst


def _run_files(run: Path):
    """(trajectory (N, 4, 4), intrinsics.json, report.json) of an output folder."""
    return (read_poses(run / "trajectory.txt", "tum").poses, json.loads((run / "intrinsics.json").read_text()),
            json.loads((run / "report.json").read_text()))


def _mesh(run: Path, transform: np.ndarray = np.eye(4)) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's vertices moved by `transform`, and their colours as uint8."""
    mesh = o3d.io.read_triangle_mesh(str(run / "mesh.ply"))
    xyz = np.asarray(mesh.vertices) @ transform[:3, :3].T + transform[:3, 3]
    return xyz, np.round(np.asarray(mesh.vertex_colors) * 255).astype(np.uint8)


def _frame_of(image: np.ndarray, frames: np.ndarray) -> int:
    """Which of the rendered frames (N, H, W, 3) an exported image shows (least mean error)."""
    return int(np.argmin([np.abs(image.astype(float) - f).mean() for f in frames]))


def _run_fails(capsys, argv, *expected) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("recon: error: "), err
    for text in expected:
        assert text in err[0], (text, err[0])
    return err[0]


# --------------------------------------------------------------------------- COLMAP


def test_colmap_model_reads_back_with_pycolmap(runs, tmp_path):
    """cameras.txt (PINHOLE, the intrinsics with COLMAP's half pixel), images.txt (every pose
    of the trajectory, world-to-camera, upright, its 2D-point line present), points3D.txt (a
    subset of the mesh's vertices with their colours) and the images they name."""
    pycolmap = pytest.importorskip("pycolmap")
    run = _copy(runs["one_shot"], tmp_path / "run", UPRIGHT)
    result = export_colmap(run, options=ExportOptions(max_points=500, progress=False))
    assert result.path == run / "colmap" and result.images == FRAMES and result.points == 500
    poses, k, report = _run_files(run)
    rec = pycolmap.Reconstruction(str(run / "colmap/sparse/0"))

    (camera,) = rec.cameras.values()
    assert camera.model.name == "PINHOLE" and (camera.width, camera.height) == (k["width"], k["height"]) == (WIDTH,
                                                                                                            HEIGHT)
    # recon's pixel centres are at integers, COLMAP's at +0.5.
    np.testing.assert_allclose(camera.params, [k["fx"], k["fy"], k["cx"] + 0.5, k["cy"] + 0.5], rtol=0, atol=1e-12)

    images = sorted(rec.images.values(), key=lambda im: im.name)
    assert [im.name for im in images] == [f"frame_{i:06d}.jpg" for i in report["frames"]["indices"]]
    for image, pose in zip(images, poses):
        w2c = np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]])
        np.testing.assert_allclose(np.linalg.inv(w2c), UPRIGHT @ pose, atol=1e-5)
        assert image.camera_id == camera.camera_id
    for k_frame, image in enumerate(images):
        rgb = cv2.cvtColor(cv2.imread(str(run / "colmap/images" / image.name)), cv2.COLOR_BGR2RGB)
        assert rgb.shape == (HEIGHT, WIDTH, 3)
        assert _frame_of(rgb, runs["seq"].rgb) == k_frame  # the frame of that pose, decoded again
        assert np.abs(rgb.astype(float) - runs["seq"].rgb[k_frame]).mean() < 6

    xyz = np.array([p.xyz for p in rec.points3D.values()])
    colours = np.array([p.color for p in rec.points3D.values()])
    assert len(xyz) == 500 and colours.dtype == np.uint8 and colours.shape == (500, 3)
    vertices, vertex_colours = _mesh(run, UPRIGHT)
    assert len(vertices) > 500
    distance, nearest = cKDTree(vertices).query(xyz)
    assert distance.max() < 1e-5  # mesh vertices, upright like the poses
    np.testing.assert_array_equal(colours, vertex_colours[nearest])

    # images.txt: two lines per image, the second (2D points) present and empty.
    lines = (run / "colmap/sparse/0/images.txt").read_text().split("\n")
    data = [n for n, line in enumerate(lines) if line and not line.startswith("#")]
    assert len(data) == FRAMES and all(lines[n + 1] == "" for n in data)
    # recon's own reader takes the model back: the poses, and the principal point in recon's
    # pixel convention again (it takes COLMAP's half pixel off).
    back = read_poses(run / "colmap", "colmap")
    np.testing.assert_allclose(back.poses, UPRIGHT @ poses, atol=1e-9)
    assert (back.intrinsics["cx"], back.intrinsics["cy"]) == (pytest.approx(k["cx"]), pytest.approx(k["cy"]))


# --------------------------------------------------------------------------- nerfstudio


def test_nerfstudio_transforms_field_by_field(runs, tmp_path):
    """transforms.json as nerfstudio's data conventions and dataparser read it: shared
    intrinsics at the top (pixel centres at +0.5), OPENCV without distortion, OpenGL camera
    axes, the upright transform as applied_transform, depth PNGs in millimetres, a coloured
    PLY in the world of the poses."""
    run = _copy(runs["one_shot"], tmp_path / "run", UPRIGHT)
    result = export_nerfstudio(run, options=ExportOptions(max_points=700, progress=False))
    assert result.images == result.depth_maps == FRAMES and result.points == 700
    poses, k, report = _run_files(run)
    dest = run / "nerfstudio"
    data = json.loads((dest / "transforms.json").read_text())

    assert set(data) == {"camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "p1", "p2",
                         "depth_unit_scale_factor", "ply_file_path", "applied_transform", "frames"}
    assert data["camera_model"] == "OPENCV"
    assert (data["fl_x"], data["fl_y"]) == (k["fx"], k["fy"])
    assert (data["cx"], data["cy"]) == (k["cx"] + 0.5, k["cy"] + 0.5)
    assert (data["w"], data["h"]) == (WIDTH, HEIGHT) and all(isinstance(data[n], int) for n in ("w", "h"))
    assert data["k1"] == data["k2"] == data["p1"] == data["p2"] == 0.0
    assert data["depth_unit_scale_factor"] == 0.001
    np.testing.assert_allclose(data["applied_transform"], UPRIGHT[:3], atol=1e-12)
    assert np.shape(data["applied_transform"]) == (3, 4)

    frames = data["frames"]
    assert len(frames) == FRAMES
    for frame, pose, index in zip(frames, poses, report["frames"]["indices"]):
        assert set(frame) == {"file_path", "transform_matrix", "depth_file_path"}
        assert frame["file_path"] == f"images/frame_{index:06d}.jpg"
        assert cv2.imread(str(dest / frame["file_path"])).shape == (HEIGHT, WIDTH, 3)
        m = np.asarray(frame["transform_matrix"])
        assert m.shape == (4, 4)
        np.testing.assert_allclose(m, UPRIGHT @ pose @ GL_FROM_CV, atol=1e-9)
        # OpenGL camera: looks down -z; the point 1 m in front of the camera is the same point.
        np.testing.assert_allclose(m @ [0, 0, -1, 1], UPRIGHT @ pose @ [0, 0, 1, 1], atol=1e-9)
        assert frame["depth_file_path"] == f"depth/frame_{index:06d}.png"
        png = cv2.imread(str(dest / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (HEIGHT, WIDTH)
        metres = np.load(run / "depth" / f"frame_{index:06d}.npy")
        assert (png > 0).mean() > 0.9
        np.testing.assert_allclose(png * data["depth_unit_scale_factor"], metres, atol=0.001)
    # recon's own nerfstudio reader takes the poses back, and the principal point in recon's
    # pixel convention again (it takes nerfstudio's half pixel off).
    back = read_poses(dest, "nerfstudio")
    np.testing.assert_allclose(back.poses, UPRIGHT @ poses, atol=1e-9)
    assert (back.intrinsics["cx"], back.intrinsics["cy"]) == (pytest.approx(k["cx"]), pytest.approx(k["cy"]))

    header = (dest / data["ply_file_path"]).read_bytes().split(b"end_header\n")[0].decode()
    assert "element vertex 700" in header
    assert all(f"property uchar {c}" in header for c in ("red", "green", "blue"))
    cloud = o3d.io.read_point_cloud(str(dest / data["ply_file_path"]))
    assert len(cloud.points) == 700 and cloud.has_colors()
    vertices, vertex_colours = _mesh(run, UPRIGHT)
    distance, nearest = cKDTree(vertices).query(np.asarray(cloud.points))
    assert distance.max() < 1e-5
    np.testing.assert_array_equal(np.round(np.asarray(cloud.colors) * 255).astype(np.uint8), vertex_colours[nearest])


def test_run_export_and_a_streamed_run_with_depth_for_some_frames(runs, tmp_path):
    """`recon run --export colmap,nerfstudio` left both exports in OUT; a streamed run that gave
    every other frame depth exports every tracked frame, and since nerfstudio wants depth on
    every frame or none, the frames without depth get an all-zero map."""
    one_shot = runs["one_shot"]
    assert (one_shot / "colmap/sparse/0/points3D.txt").is_file() and (one_shot / "nerfstudio/transforms.json").is_file()
    assert len(list((one_shot / "colmap/images").glob("*.jpg"))) == FRAMES and no_temp_files(one_shot)

    streamed = runs["streamed"]
    _, _, report = _run_files(streamed)
    with_depth = report["frames"]["depth_indices"]
    assert with_depth == [0, 2, 4, 6]
    results = export_folder(streamed, ["nerfstudio", "colmap"], dest=tmp_path / "exports", options=QUIET)
    assert [(r.format, r.path) for r in results] == [("nerfstudio", tmp_path / "exports/nerfstudio"),
                                                      ("colmap", tmp_path / "exports/colmap")]
    assert results[0].depth_maps == len(with_depth)
    assert not (streamed / "colmap").exists()
    data = json.loads((tmp_path / "exports/nerfstudio/transforms.json").read_text())
    assert [f["file_path"] for f in data["frames"]] == [f"images/frame_{i:06d}.jpg" for i in range(FRAMES)]
    for index, frame in enumerate(data["frames"]):
        png = cv2.imread(str(tmp_path / "exports/nerfstudio" / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (HEIGHT, WIDTH)
        if index in with_depth:
            metres = np.load(streamed / "depth" / f"frame_{index:06d}.npy")
            np.testing.assert_allclose(png * 0.001, metres, atol=0.001)
        else:
            assert not png.any()
    assert len(list((tmp_path / "exports/colmap/images").glob("*.jpg"))) == FRAMES


def test_an_output_folder_of_the_previous_version_exports(runs, tmp_path):
    """A folder without the keys this version added or may add (no upright transform, no frame
    names, no lens entries, intrinsics.json without model and convention): both exports are
    written, in the run's own world, without applied_transform."""
    def older(report):
        report.pop("upright", None)
        report["frames"].pop("names", None)
        report["intrinsics"].pop("undistorted", None)
        report["poses"].pop("frames_undistorted", None)
        report["poses"].pop("lens_k1", None)

    run = _copy(runs["one_shot"], tmp_path / "old", edit=older)
    k = json.loads((run / "intrinsics.json").read_text())
    (run / "intrinsics.json").write_text(json.dumps({n: k[n] for n in ("fx", "fy", "cx", "cy", "width", "height")}))
    results = export_folder(run, "colmap,nerfstudio", options=QUIET)
    assert [r.format for r in results] == ["colmap", "nerfstudio"]
    poses, _, _ = _run_files(run)
    np.testing.assert_allclose(read_poses(run / "colmap", "colmap").poses, poses, atol=1e-9)
    data = json.loads((run / "nerfstudio/transforms.json").read_text())
    assert "applied_transform" not in data
    np.testing.assert_allclose([f["transform_matrix"] for f in data["frames"]], poses @ GL_FROM_CV, atol=1e-9)


def test_a_known_lens_gives_the_pinhole_images_of_the_run(runs, tmp_path):
    """--distortion: the run resampled its frames into the pinhole camera as it decoded them;
    the export does the same, so its PINHOLE camera describes its images: they match OpenCV's
    own undistortion of the recorded frames, not the frames as recorded."""
    seq, inputs = runs["seq"], runs["inputs"]
    out = tmp_path / "lens"
    assert main(["run", str(inputs["video"]), "-o", str(out), "--stream", "off", "--max-frames", "3",
                 "--distortion", "0.1,0,0,0", *runs["common"]]) == 0
    assert json.loads((out / "report.json").read_text())["intrinsics"]["undistorted"]["distortion"][0] == 0.1
    export_colmap(out, options=ExportOptions(image_format="png", progress=False))
    assert "PINHOLE" in (out / "colmap/sparse/0/cameras.txt").read_text()
    fx, fy, cx, cy = seq.intrinsics
    camera = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    cap = cv2.VideoCapture(str(inputs["video"]))
    for index in range(3):
        ok, recorded = cap.read()
        assert ok
        exported = cv2.imread(str(out / f"colmap/images/frame_{index:06d}.png")).astype(float)
        pinhole = cv2.undistort(recorded, camera, np.array([0.1, 0, 0, 0])).astype(float)
        inner = (slice(12, -12), slice(16, -16))
        assert np.abs(exported - pinhole)[inner].mean() < 2.0
        assert np.abs(exported - recorded)[inner].mean() > 2 * np.abs(exported - pinhole)[inner].mean()
    cap.release()


def test_a_rolling_shutter_is_unrolled_as_the_run_did(runs, tmp_path):
    """--rolling-shutter with given poses: the run resampled every frame to one instant with
    the poses' turn rate; the exported images are those frames (the readout in seconds, each
    frame with its own turn rate), not the frames as recorded."""
    from recon.geometry.rolling_shutter import angular_velocity, recorded_positions, unroll_images

    seq, inputs = runs["seq"], runs["inputs"]
    out = tmp_path / "shutter"
    assert main(["run", str(inputs["video"]), "-o", str(out), "--stream", "off", "--max-frames", "4",
                 "--rolling-shutter", "30", *runs["common"]]) == 0
    assert json.loads((out / "report.json").read_text())["poses"]["rolling_shutter"]["frames_resampled"] == 4
    export_colmap(out, options=ExportOptions(image_format="png", progress=False))
    trajectory = read_poses(out / "trajectory.txt", "tum")
    omega = angular_velocity(trajectory.poses, trajectory.timestamps)
    cap = cv2.VideoCapture(str(inputs["video"]))
    for index in range(4):
        ok, recorded = cap.read()
        assert ok
        recorded = cv2.cvtColor(recorded, cv2.COLOR_BGR2RGB)
        unrolled = unroll_images(recorded[None], recorded_positions(omega[index:index + 1], seq.intrinsics,
                                                                    (HEIGHT, WIDTH), 0.030))[0]
        exported = cv2.cvtColor(cv2.imread(str(out / f"colmap/images/frame_{index:06d}.png")), cv2.COLOR_BGR2RGB)
        assert np.abs(exported.astype(int) - unrolled).max() <= 1
        assert np.abs(exported.astype(int) - recorded).mean() > 1.0
    cap.release()


def test_segments_are_exported_each_into_its_folder(runs, tmp_path):
    """A run written as segments: `recon export OUT` exports every segment folder into its
    own OUT/segment_NN/<format>/; the single-folder functions refuse the summary folder."""
    out = tmp_path / "segmented"
    out.mkdir()
    for name in ("segment_00", "segment_01"):
        _copy(runs["one_shot"], out / name)
    report = json.loads((runs["one_shot"] / "report.json").read_text())
    report["segments"] = [{"folder": "segment_00", "frames": [0, 7]}, {"folder": "segment_01", "frames": [0, 7]}]
    (out / "report.json").write_text(json.dumps(report))
    with pytest.raises(ReconInputError, match="written as segments"):
        export_colmap(out, options=QUIET)
    assert main(["export", str(out), "--to", "colmap", "--quiet", "--max-points", "100"]) == 0
    for name in ("segment_00", "segment_01"):
        assert len((out / name / "colmap/sparse/0/points3D.txt").read_text().splitlines()) == 3 + 100
    assert not (out / "colmap").exists()


def test_per_frame_intrinsics_give_a_camera_each(tmp_path):
    """Frames with different intrinsics: a COLMAP camera per distinct camera, each image on
    its own; in transforms.json the intrinsics go into the frames instead of the top."""
    pycolmap = pytest.importorskip("pycolmap")
    poses = random_poses(3)
    intrinsics = np.array([[100.0, 101.0, 31.5, 23.5], [120.0, 121.0, 32.0, 24.0], [100.0, 101.0, 31.5, 23.5]])
    names = ["a.jpg", "b.jpg", "c.jpg"]
    model = tmp_path / "sparse"
    model.mkdir()
    for name, text in colmap_text_model(poses, names, intrinsics, (48, 64), np.zeros((0, 3)),
                                        np.zeros((0, 3), np.uint8)).items():
        (model / name).write_text(text)
    rec = pycolmap.Reconstruction(str(model))
    assert len(rec.cameras) == 2 and len(rec.points3D) == 0
    for image in rec.images.values():
        k = names.index(image.name)
        np.testing.assert_allclose(rec.cameras[image.camera_id].params, intrinsics[k] + [0, 0, 0.5, 0.5])
        np.testing.assert_allclose(np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0, 0, 0, 1]])),
                                   poses[k], atol=1e-9)
    data = nerfstudio_transforms(poses, names, intrinsics, (48, 64))
    assert not {"fl_x", "fl_y", "cx", "cy", "depth_unit_scale_factor", "ply_file_path"} & set(data)
    assert (data["w"], data["h"]) == (64, 48)
    for frame, k in zip(data["frames"], intrinsics):
        assert [frame[n] for n in ("fl_x", "fl_y", "cx", "cy")] == list(k + [0, 0, 0.5, 0.5])


# --------------------------------------------------------------------------- command line


def test_export_command_and_its_errors(runs, tmp_path, capsys):
    """`recon export`: exit 0 and a line per export; a folder that is not an output folder, an
    unknown format, an existing export without --overwrite and an input that has gone are
    one `recon: error:` line each, exit 2; nothing already written is lost."""
    run = _copy(runs["one_shot"], tmp_path / "run")
    assert main(["export", str(run), "--to", "colmap", "--to", "nerfstudio", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert f"wrote colmap: {run / 'colmap'}" in out and f"wrote nerfstudio: {run / 'nerfstudio'}" in out
    before = (run / "colmap/sparse/0/images.txt").read_text()

    empty = tmp_path / "empty"
    empty.mkdir()
    _run_fails(capsys, ["export", str(empty), "--to", "colmap"], str(empty), "not an output folder")
    _run_fails(capsys, ["export", str(tmp_path / "missing"), "--to", "colmap"], "missing", "no such output folder")
    _run_fails(capsys, ["export", str(run), "--to", "ply"], "unknown export format 'ply'")
    _run_fails(capsys, ["export", str(run), "--to", "colmap", "--image-format", "gif"], "image format")
    _run_fails(capsys, ["export", str(run), "--to", "nerfstudio,colmap"], str(run / "nerfstudio"), "already exists")
    assert (run / "colmap/sparse/0/images.txt").read_text() == before
    assert main(["export", str(run), "--to", "colmap", "--overwrite", "--quiet", "--image-format", "png"]) == 0
    assert len(list((run / "colmap/images").glob("*.png"))) == FRAMES and not list((run / "colmap").rglob("*.jpg"))
    assert no_temp_files(run)

    gone = tmp_path / "gone.mp4"
    moved = _copy(runs["one_shot"], tmp_path / "moved", edit=lambda r: r["input"].update(path=str(gone)))
    _run_fails(capsys, ["export", str(moved), "--to", "colmap"], str(gone), "input is gone", "--input")
    assert not (moved / "colmap").exists() and no_temp_files(moved)
    assert main(["export", str(moved), "--to", "colmap", "--input", str(runs["inputs"]["video"]), "-o",
                 str(tmp_path / "dest"), "--quiet"]) == 0
    assert (tmp_path / "dest/colmap/sparse/0/cameras.txt").is_file()


def test_run_refuses_an_unknown_export_format_before_running(runs, tmp_path, capsys):
    out = tmp_path / "out"
    _run_fails(capsys, ["run", str(runs["inputs"]["video"]), "-o", str(out), "--export", "colmap,obj",
                        *runs["common"]], "unknown export format 'obj'")
    assert not out.exists()
