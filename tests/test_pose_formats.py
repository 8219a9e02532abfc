"""Pose file formats: round trips, conventions (OpenGL, world-to-camera), validation errors."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.poses.formats import (
    FORMATS,
    associate_timestamps,
    detect_pose_format,
    interpolate_poses,
    invert_poses,
    make_poses,
    read_poses,
    write_poses,
)

INTR = {"fx": 500.0, "fy": 510.0, "cx": 320.5, "cy": 239.5, "width": 640, "height": 480}
TARGETS = {
    "tum": "traj.txt",
    "colmap": "sparse",
    "nerfstudio": "transforms.json",
    "matrices": "pose",
    "log": "traj.log",
}


def _random_poses(n=6, seed=0):
    rng = np.random.default_rng(seed)
    return make_poses(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(size=(n, 3)))


def _no_pycolmap(monkeypatch):
    # A None entry makes `import pycolmap` raise ImportError.
    monkeypatch.setitem(sys.modules, "pycolmap", None)


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_with_auto_detection(tmp_path, fmt):
    poses = _random_poses()
    names = [f"frame_{i:03d}.png" for i in range(len(poses))] if fmt in ("colmap", "nerfstudio") else None
    stamps = 1305031229.5 + np.arange(len(poses)) / 30.0
    target = tmp_path / TARGETS[fmt]
    write_poses(target, poses, fmt, names=names, timestamps=stamps, intrinsics=INTR)
    assert detect_pose_format(target) == fmt
    data = read_poses(target)
    assert data.fmt == fmt and len(data) == len(poses) and data.valid.all()
    np.testing.assert_allclose(data.poses, poses, atol=1e-8)
    if fmt == "tum":
        np.testing.assert_allclose(data.timestamps, stamps, atol=1e-6)
    if names is not None:
        assert data.names == names
    if fmt in ("colmap", "nerfstudio"):
        assert {k: data.intrinsics[k] for k in INTR} == INTR
    # Written through a temp name: nothing but the result is left behind.
    assert not [p for p in tmp_path.rglob(".*")]


def test_matrices_keep_names_and_invalid_poses(tmp_path):
    poses = _random_poses(3)
    poses[1] = np.nan
    names = ["frame-000000.pose", "frame-000001.pose", "frame-000002.pose"]
    write_poses(tmp_path / "pose", poses, "matrices", names=names)
    assert (tmp_path / "pose" / "frame-000001.pose.txt").read_text().startswith("-inf")
    data = read_poses(tmp_path / "pose")
    assert data.names == names
    assert data.valid.tolist() == [True, False, True]
    np.testing.assert_allclose(data.poses[[0, 2]], poses[[0, 2]], atol=1e-8)
    with pytest.raises(ValueError, match="only 'matrices'"):
        write_poses(tmp_path / "t.txt", poses, "tum")


def test_nerfstudio_converts_opengl_axes(tmp_path):
    # An identity OpenGL camera looks down world -z with +y up: in OpenCV axes its z axis
    # (forward) is world -z and its y axis (down) is world -y.
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"fl_x": 100, "fl_y": 100, "cx": 5, "cy": 4, "w": 10, "h": 8,
                                "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}))
    pose = read_poses(path).poses[0]
    np.testing.assert_allclose(pose[:3, 2], [0, 0, -1])
    np.testing.assert_allclose(pose[:3, 1], [0, -1, 0])


def test_colmap_stores_world_to_camera(tmp_path, monkeypatch):
    _no_pycolmap(monkeypatch)
    pose = make_poses(Rotation.from_rotvec([[0.2, -0.4, 0.1]]).as_matrix(), np.array([[1.0, 2.0, 3.0]]))
    write_poses(tmp_path / "m", pose, "colmap", names=["a.png"], intrinsics=INTR)
    line = [ln for ln in (tmp_path / "m" / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")][0]
    qw, qx, qy, qz, tx, ty, tz = map(float, line.split()[1:8])
    rot = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    np.testing.assert_allclose(rot, pose[0, :3, :3].T, atol=1e-12)
    np.testing.assert_allclose([tx, ty, tz], -pose[0, :3, :3].T @ pose[0, :3, 3], atol=1e-12)
    np.testing.assert_allclose(invert_poses(invert_poses(pose)), pose, atol=1e-12)


def test_colmap_text_and_pycolmap_agree(tmp_path, monkeypatch):
    pycolmap = pytest.importorskip("pycolmap")
    poses = _random_poses(4, seed=5)
    names = [f"{i}.jpg" for i in range(4)]
    write_poses(tmp_path / "by_pycolmap", poses, "colmap", names=names, intrinsics=INTR)
    rec = pycolmap.Reconstruction(str(tmp_path / "by_pycolmap"))
    assert rec.num_images() == 4
    with monkeypatch.context() as m:
        _no_pycolmap(m)
        np.testing.assert_allclose(read_poses(tmp_path / "by_pycolmap").poses, poses, atol=1e-10)
        write_poses(tmp_path / "by_text", poses, "colmap", names=names, intrinsics=INTR)
    np.testing.assert_allclose(read_poses(tmp_path / "by_text").poses, poses, atol=1e-10)
    # Binary model, read from the project folder layout sparse/0.
    binary_dir = tmp_path / "proj" / "sparse" / "0"
    binary_dir.mkdir(parents=True)
    rec.write_binary(str(binary_dir))
    np.testing.assert_allclose(read_poses(tmp_path / "proj").poses, poses, atol=1e-10)
    with monkeypatch.context() as m:
        _no_pycolmap(m)
        with pytest.raises(ReconInputError, match="pip install pycolmap"):
            read_poses(tmp_path / "proj")


def test_log_matches_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    poses = _random_poses(3, seed=7)
    write_poses(tmp_path / "t.log", poses, "log")
    traj = o3d.io.read_pinhole_camera_trajectory(str(tmp_path / "t.log"))
    # Open3D keeps the inverse (world-to-camera) as `extrinsic`.
    np.testing.assert_allclose(np.linalg.inv(traj.parameters[2].extrinsic), poses[2], atol=1e-8)


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("# t x y z qx qy qz qw\n0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", r"traj\.txt:3: expected 8 columns"),
        ("0 1 2 3 0 0 0 1\n1 1 2 abc 0 0 0 1\n", r"traj\.txt:2: non-numeric value 'abc'"),
        ("0 1 2 3 0 0 0 0\n", r"traj\.txt:1: quaternion has near-zero norm"),
        ("0 1 2 nan 0 0 0 1\n", r"traj\.txt:1: non-finite"),
        ("# only a comment\n", r"traj\.txt: no data lines"),
    ],
)
def test_tum_errors_name_file_and_line(tmp_path, text, match):
    with pytest.raises(ReconInputError, match=match) as info:
        read_poses(_write(tmp_path / "traj.txt", text), fmt="tum")
    assert "\n" not in str(info.value)


def test_tum_quaternions_are_normalised(tmp_path):
    data = read_poses(_write(tmp_path / "traj.txt", "0 0 0 0 0 0 0 2\n1 0 0 0 0 0 3 3\n"))
    np.testing.assert_allclose(data.poses[0], np.eye(4))
    yaw90 = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    np.testing.assert_allclose(data.poses[1, :3, :3], yaw90, atol=1e-12)


def test_non_orthonormal_rotations_are_rejected(tmp_path):
    scaled = np.diag([1.01, 1.0, 1.0, 1.0])
    (tmp_path / "pose").mkdir()
    np.savetxt(tmp_path / "pose" / "0.txt", np.eye(4))
    np.savetxt(tmp_path / "pose" / "1.txt", scaled)
    with pytest.raises(ReconInputError, match=r"file 1\.txt: rotation is not orthonormal"):
        read_poses(tmp_path / "pose")
    mirrored = np.diag([1.0, 1.0, -1.0, 1.0])
    _write(tmp_path / "t.log", "0 0 1\n" + "\n".join(" ".join(map(str, r)) for r in mirrored) + "\n")
    with pytest.raises(ReconInputError, match=r"t\.log: line 2: .*reflection"):
        read_poses(tmp_path / "t.log")
    frames = [{"file_path": "x.png", "transform_matrix": scaled.tolist()}]
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    with pytest.raises(ReconInputError, match=r"frame 0 \('x\.png'\): rotation is not orthonormal"):
        read_poses(tmp_path / "transforms.json")
    # Within tolerance (7 printed digits) is fine.
    np.savetxt(tmp_path / "pose" / "1.txt", np.round(_random_poses(1)[0], 6))
    assert read_poses(tmp_path / "pose").valid.all()


def test_structural_errors(tmp_path):
    with pytest.raises(ReconInputError, match=r"t\.log:1: truncated pose"):
        read_poses(_write(tmp_path / "t.log", "0 0 1\n1 0 0 0\n0 1 0 0\n"))
    with pytest.raises(ReconInputError, match=r"0\.txt:2: expected 4 numbers"):
        (tmp_path / "p").mkdir()
        read_poses(_write(tmp_path / "p" / "0.txt", "1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n"))
    with pytest.raises(ReconInputError, match=r"bad\.json:1: invalid JSON"):
        read_poses(_write(tmp_path / "bad.json", "{frames: ["))
    with pytest.raises(ReconInputError, match=r"frame 1 \('b\.png'\): transform_matrix must be 4x4"):
        frames = [
            {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
            {"file_path": "b.png", "transform_matrix": [[1, 0], [0, 1]]},
        ]
        read_poses(_write(tmp_path / "two.json", json.dumps({"frames": frames})))
    with pytest.raises(ReconInputError, match="no such file"):
        read_poses(tmp_path / "missing.txt")
    with pytest.raises(ReconInputError, match="unknown pose file format"):
        read_poses(_write(tmp_path / "odd.txt", "1 2 3 4 5\n"))
    with pytest.raises(ValueError, match="names has 1 entries for 2 poses"):
        write_poses(tmp_path / "x.txt", _random_poses(2), "tum", names=["a"])


def test_associate_timestamps_is_one_to_one_within_tolerance():
    query = np.array([0.00, 0.033, 0.066, 0.100, 0.500])
    ref = np.array([0.005, 0.030, 0.031, 0.110, 0.2])
    qi, ri = associate_timestamps(query, ref, max_diff=0.02)
    assert qi.tolist() == [0, 1, 3]
    assert ri.tolist() == [0, 2, 3]  # 0.033 takes the closer 0.031; 0.066 has nothing left within 20 ms
    # Order of the reference list does not matter.
    perm = np.array([4, 2, 0, 3, 1])
    qi2, ri2 = associate_timestamps(query, ref[perm], max_diff=0.02)
    assert qi2.tolist() == qi.tolist() and perm[ri2].tolist() == ri.tolist()
    q3, _ = associate_timestamps(query, ref + 10.0, max_diff=0.02)
    assert q3.size == 0


def test_interpolate_poses_slerp_and_nearest():
    ref_ts = np.array([0.0, 0.1, 1.0])
    rot = Rotation.from_euler("z", [[0.0], [20.0], [20.0]], degrees=True).as_matrix()
    ref = make_poses(rot, [[0, 0, 0], [1, 0, 0], [1, 0, 0]])
    out, valid = interpolate_poses([0.025, 0.05, 1.01, 0.5, -0.5], ref_ts, ref, max_gap=0.2, max_diff=0.02)
    assert valid.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(out[1, :3, 3], [0.5, 0, 0])
    np.testing.assert_allclose(out[0, :3, :3], Rotation.from_euler("z", 5, degrees=True).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(out[2], ref[2])
    assert np.isnan(out[3]).all()


def test_interpolate_poses_snaps_to_rounded_timestamps():
    ref = make_poses(Rotation.from_euler("z", [[0.0], [40.0]], degrees=True).as_matrix(), [[0, 0, 0], [1, 0, 0]])
    out, _ = interpolate_poses([0.001, 0.05], [0.0, 0.1], ref, snap=0.005)
    np.testing.assert_allclose(out[0], ref[0])
    np.testing.assert_allclose(out[1, :3, 3], [0.5, 0, 0])
