"""`recon eval` against recordings without sensor depth (KITTI odometry, a COLMAP project): the
trajectory is scored, depth and mesh are skipped with a note saying why, nothing raises."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from recon.eval.evaluate import EvalOptions, evaluate_output, format_evaluation
from recon.export import export_reconstruction
from recon.geometry.rigid import make_poses
from recon.io.output_folder import OutputFolder
from recon.io.pose_formats.trajectories import write_poses

from helpers import SHARED_DATA

H, W = 12, 16
INTRINSICS = (20.0, 20.0, 7.5, 5.5)


def _drive(n: int = 8) -> np.ndarray:
    """Camera-to-world poses of a car driving forward (+z) 1.2 m a frame while turning slowly."""
    yaw = Rotation.from_rotvec(np.outer(np.arange(n) * 0.02, [0.0, 1.0, 0.0])).as_matrix()
    return make_poses(yaw, np.column_stack([0.05 * np.arange(n) ** 2, np.zeros(n), 1.2 * np.arange(n)]))


def _images(folder: Path, names) -> None:
    folder.mkdir(parents=True)
    for i, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), np.full((H, W), 10 * i, np.uint8))


def make_kitti(root: Path, poses: np.ndarray) -> Path:
    _images(root / "image_0", [f"{i:06d}.png" for i in range(len(poses))])
    fx, fy, cx, cy = INTRINSICS
    p0 = f"{fx} 0 {cx} 0 0 {fy} {cy} 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    write_poses(root / "poses.txt", poses, "kitti")
    return root


def make_colmap_project(root: Path, poses: np.ndarray) -> Path:
    names = [f"frame_{i:03d}.png" for i in range(len(poses))]
    _images(root / "images", names)
    write_poses(root / "sparse" / "0", poses, "colmap", names=names, intrinsics=(*INTRINSICS, W, H))
    return root


def _output(folder: Path, indices, poses: np.ndarray) -> Path:
    """An output folder of `recon run` with depth maps, a mesh and estimated poses."""
    mesh = o3d.geometry.TriangleMesh.create_box(2.0, 1.0, 3.0)
    report = {"frames": {"indices": [int(i) for i in indices]}, "poses": {"source": "estimate"}}
    export_reconstruction(OutputFolder(folder), mesh=mesh, poses=poses, intrinsics=INTRINSICS, shape=(H, W),
                          depth=np.full((len(indices), H, W), 5.0, np.float32), report=report, glb=False)
    return folder


def _up_to_scale(poses: np.ndarray, scale: float) -> np.ndarray:
    """The same trajectory in another frame and at another scale (what monocular SfM returns)."""
    move = make_poses(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()[None], np.array([[1.0, -2.0, 0.5]]))[0]
    out = move @ poses
    out[:, :3, 3] = scale * (move[:3, :3] @ poses[:, :3, 3].T).T + move[:3, 3]
    return out


@pytest.mark.parametrize("make", [make_kitti, make_colmap_project], ids=["kitti", "colmap"])
def test_trajectory_is_scored_and_depth_and_mesh_are_skipped(tmp_path, make):
    gt = _drive()
    root = make(tmp_path / "gt", gt)
    indices = np.arange(1, 7)
    out = _output(tmp_path / "out", indices, _up_to_scale(gt[indices], 0.25))
    result = evaluate_output(out, root, EvalOptions(progress=False))
    assert result["dataset"]["kind"] == make.__name__.removeprefix("make_").removesuffix("_project")
    t = result["trajectory"]
    assert t["ate_sim3"]["rmse"] < 1e-6 and t["ate_sim3"]["scale"] == pytest.approx(4.0, rel=1e-6)
    assert t["ate_se3"]["rmse"] > 0.5  # a rigid fit cannot undo the scale
    assert "rpe" in t and "scale_error" in t
    assert "depth" not in result and "mesh" not in result
    assert "has no sensor depth" in result["depth_missing"] and "has no sensor depth" in result["mesh_missing"]
    text = format_evaluation(result)
    assert "ATE Sim(3)" in text and "depth: " in text and "mesh: " in text
    json.dumps(result)  # eval.json is written from it


def test_an_error_is_measured(tmp_path):
    gt = _drive()
    root = make_kitti(tmp_path / "gt", gt)
    est = gt.copy()
    est[3, :3, 3] += [0.0, 0.3, 0.0]  # one camera 30 cm off
    result = evaluate_output(_output(tmp_path / "out", np.arange(8), est), root, EvalOptions(progress=False))
    assert 0.05 < result["trajectory"]["ate_se3"]["rmse"] < 0.3


def test_cli_writes_the_notes_into_eval_json(tmp_path):
    from recon.commands.cli import main

    gt = _drive()
    root = make_colmap_project(tmp_path / "gt", gt)
    out = _output(tmp_path / "out", np.arange(4), gt[:4])
    assert main(["eval", str(out), "--gt", str(root), "--quiet"]) == 0
    saved = json.loads((out / "eval.json").read_text())
    assert saved["trajectory"]["ate_se3"]["rmse"] < 1e-6
    assert "no sensor depth" in saved["mesh_missing"] and "no sensor depth" in saved["depth_missing"]


@pytest.mark.skipif(not (SHARED_DATA / "kitti-odometry-seq1").is_dir(), reason="kitti-odometry-seq1 not present")
def test_real_kitti_slice(tmp_path):
    from recon.io.datasets import open_dataset

    root = SHARED_DATA / "kitti-odometry-seq1"
    gt = open_dataset(root).poses
    indices = np.arange(10, 16)
    out = _output(tmp_path / "out", indices, _up_to_scale(gt[indices], 0.5))
    result = evaluate_output(out, root, EvalOptions(progress=False))
    assert result["dataset"]["kind"] == "kitti" and result["frames"] == 6
    assert result["trajectory"]["ate_sim3"]["rmse"] < 1e-4  # KITTI's 7-digit pose file
    assert result["trajectory"]["ate_sim3"]["scale"] == pytest.approx(2.0, rel=1e-4)
    assert "mesh_missing" in result and "depth_missing" in result
