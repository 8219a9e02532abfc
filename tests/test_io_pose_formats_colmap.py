"""COLMAP models as pose files (recon.io.pose_formats.colmap): world-to-camera storage, and the text
reader/writer agreeing with pycolmap's binary and text models."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.geometry.rigid import make_poses
from recon.io.pose_formats.trajectories import read_poses, write_poses
from recon.poses.result import invert_poses

from helpers import POSE_FILE_INTRINSICS, random_poses


def _no_pycolmap(monkeypatch):
    # A None entry makes `import pycolmap` raise ImportError.
    monkeypatch.setitem(sys.modules, "pycolmap", None)


def test_colmap_stores_world_to_camera(tmp_path, monkeypatch):
    _no_pycolmap(monkeypatch)
    pose = make_poses(Rotation.from_rotvec([[0.2, -0.4, 0.1]]).as_matrix(), np.array([[1.0, 2.0, 3.0]]))
    write_poses(tmp_path / "m", pose, "colmap", names=["a.png"], intrinsics=POSE_FILE_INTRINSICS)
    line = [ln for ln in (tmp_path / "m" / "images.txt").read_text().splitlines() if ln and not ln.startswith("#")][0]
    qw, qx, qy, qz, tx, ty, tz = map(float, line.split()[1:8])
    rot = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
    np.testing.assert_allclose(rot, pose[0, :3, :3].T, atol=1e-12)
    np.testing.assert_allclose([tx, ty, tz], -pose[0, :3, :3].T @ pose[0, :3, 3], atol=1e-12)
    np.testing.assert_allclose(invert_poses(invert_poses(pose)), pose, atol=1e-12)


def test_colmap_text_and_pycolmap_agree(tmp_path, monkeypatch):
    pycolmap = pytest.importorskip("pycolmap")
    poses = random_poses(4, seed=5)
    names = [f"{i}.jpg" for i in range(4)]
    write_poses(tmp_path / "by_pycolmap", poses, "colmap", names=names, intrinsics=POSE_FILE_INTRINSICS)
    rec = pycolmap.Reconstruction(str(tmp_path / "by_pycolmap"))
    assert rec.num_images() == 4
    with monkeypatch.context() as m:
        _no_pycolmap(m)
        np.testing.assert_allclose(read_poses(tmp_path / "by_pycolmap").poses, poses, atol=1e-10)
        write_poses(tmp_path / "by_text", poses, "colmap", names=names, intrinsics=POSE_FILE_INTRINSICS)
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
