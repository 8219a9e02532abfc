"""Pose file formats (recon.io.pose_formats.trajectories): round trips with auto-detection, conventions
(OpenGL axes, invalid poses, Open3D's log), and one-line errors naming the file and line.
COLMAP models have their own tests (test_io_colmap.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.io.pose_formats.trajectories import FORMATS, detect_pose_format, read_poses, write_poses

from helpers import POSE_FILE_INTRINSICS, random_poses

TARGETS = {
    "tum": "traj.txt",
    "colmap": "sparse",
    "nerfstudio": "transforms.json",
    "matrices": "pose",
    "log": "traj.log",
    "kitti": "poses.txt",
}


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_with_auto_detection(tmp_path, fmt):
    poses = random_poses()
    names = [f"frame_{i:03d}.png" for i in range(len(poses))] if fmt in ("colmap", "nerfstudio") else None
    stamps = 1305031229.5 + np.arange(len(poses)) / 30.0
    target = tmp_path / TARGETS[fmt]
    write_poses(target, poses, fmt, names=names, timestamps=stamps, intrinsics=POSE_FILE_INTRINSICS)
    assert detect_pose_format(target) == fmt
    data = read_poses(target)
    assert data.fmt == fmt and len(data) == len(poses) and data.valid.all()
    np.testing.assert_allclose(data.poses, poses, atol=1e-8)
    if fmt == "tum":
        np.testing.assert_allclose(data.timestamps, stamps, atol=1e-6)
    if names is not None:
        assert data.names == names
    if fmt in ("colmap", "nerfstudio"):
        assert {k: data.intrinsics[k] for k in POSE_FILE_INTRINSICS} == POSE_FILE_INTRINSICS
    # Written through a temp name: nothing but the result is left behind.
    assert not [p for p in tmp_path.rglob(".*")]


def test_matrices_keep_names_and_invalid_poses(tmp_path):
    poses = random_poses(3)
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


def test_log_matches_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    poses = random_poses(3, seed=7)
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
    np.savetxt(tmp_path / "pose" / "1.txt", np.round(random_poses(1)[0], 6))
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
        write_poses(tmp_path / "x.txt", random_poses(2), "tum", names=["a"])


def test_tum_file_is_recognised_by_all_its_lines_and_errors_say_the_format(tmp_path):
    """A TUM trajectory whose first data line happens to have 4 numbers is still a TUM file
    (the format is decided by all lines), and the error names that line and the format
    assumed, instead of "expected 4 numbers per row of a 4x4 pose"."""
    from recon.errors import ReconInputError
    from recon.io.pose_formats.trajectories import detect_pose_format, read_poses

    rows = [f"{k / 30:.4f} {0.1 * k:.3f} 0 0 0 0 0 1" for k in range(6)]
    good = tmp_path / "ok.txt"
    good.write_text("\n".join(rows) + "\n")
    assert detect_pose_format(good) == "tum" and len(read_poses(good)) == 6
    odd = tmp_path / "odd.txt"
    odd.write_text("0.0 1.0 2.0 3.0\n" + "\n".join(rows) + "\n")
    assert detect_pose_format(odd) == "tum"
    with pytest.raises(ReconInputError) as info:
        read_poses(odd)
    message = str(info.value)
    assert "odd.txt" in message and "TUM" in message and "6 of 7 lines have 8 numbers" in message
    assert "4x4" not in message
    matrix = tmp_path / "pose.txt"
    matrix.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    assert detect_pose_format(matrix) == "matrices"
    mixed = tmp_path / "mixed.txt"
    mixed.write_text("1 2 3\n1 2 3 4 5\n1 2\n")
    with pytest.raises(ReconInputError, match="unknown pose file format"):
        detect_pose_format(mixed)


def test_kitti_pose_file(tmp_path):
    """KITTI's 3x4 row-major camera-to-world per line, as KITTI writes it (%e); detected by
    its 12-number lines, one odd line named with the format assumed."""
    poses = random_poses(4)
    text = "".join(" ".join(f"{v:e}" for v in pose[:3].ravel()) + "\n" for pose in poses)
    path = _write(tmp_path / "00.txt", text)
    assert detect_pose_format(path) == "kitti"
    data = read_poses(path)
    assert data.fmt == "kitti" and data.timestamps is None and data.names is None
    np.testing.assert_allclose(data.poses, poses, atol=1e-5)  # %e keeps 7 digits
    lines = text.splitlines()
    bad = _write(tmp_path / "bad.txt", "\n".join([*lines[:2], lines[2].rsplit(" ", 1)[0], lines[3]]) + "\n")
    with pytest.raises(ReconInputError, match=r"bad\.txt:3: expected 12 columns .* \(read as a KITTI pose file: "
                                              r"3 of 4 lines have 12 numbers\)"):
        read_poses(bad)
    scaled = _write(tmp_path / "scaled.txt", "2 0 0 0 0 2 0 0 0 0 2 0\n")
    with pytest.raises(ReconInputError, match=r"scaled\.txt: line 1: rotation is not orthonormal"):
        read_poses(scaled)
