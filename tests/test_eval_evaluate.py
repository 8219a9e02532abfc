"""`recon eval` on an output folder made from a synthetic ScanNet-style recording with known errors."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.eval.evaluate import EvalOptions, evaluate_output, format_evaluation
from recon.export import export_reconstruction
from recon.fusion import FusionOptions, fuse
from recon.io.output_folder import OutputFolder, load_output
from recon.synthetic import render_sequence


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A ScanNet-export layout (colour, depth in mm, 4x4 poses, intrinsics) of the synthetic room."""
    seq = render_sequence(num_frames=12, width=160, height=120, seed=5)
    root = tmp_path_factory.mktemp("scannet")
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir()
    fx, fy, cx, cy = seq.intrinsics
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", [[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    for i in range(len(seq.rgb)):
        cv2.imwrite(str(root / "color" / f"{i}.png"), seq.rgb[i][..., ::-1])
        cv2.imwrite(str(root / "depth" / f"{i}.png"), np.round(seq.depth[i] * 1000).astype(np.uint16))
        np.savetxt(root / "pose" / f"{i}.txt", seq.poses[i])
    return seq, root


def _output(tmp_path, seq, indices, depth, poses, pose_source):
    mesh = fuse(depth, seq.rgb[indices], poses, seq.intrinsics, FusionOptions(progress=False)).mesh
    report = {"frames": {"indices": list(map(int, indices))}, "poses": {"source": pose_source}}
    export_reconstruction(OutputFolder(tmp_path / "out"), mesh=mesh, poses=poses, intrinsics=seq.intrinsics,
                          shape=(120, 160), depth=depth, report=report, glb=False)
    return tmp_path / "out"


def test_known_errors_are_measured(tmp_path, recording):
    seq, root = recording
    indices = np.arange(0, 12, 2)
    # Depth 10 % too far everywhere, ground-truth poses.
    out = _output(tmp_path, seq, indices, seq.depth[indices] * 1.1, seq.poses[indices], "gt")
    result = evaluate_output(out, root, EvalOptions(progress=False, mesh_points=20_000))
    assert result["depth"]["metric"]["abs_rel"] == pytest.approx(0.1, abs=2e-3)
    assert result["depth"]["median_frame"]["abs_rel"] < 2e-3
    assert result["trajectory"]["ate_se3"]["rmse"] < 1e-6
    assert result["mesh_align"] == "none"
    # A mesh from depth scaled by 10 % sits centimetres off the reference: accuracy shows it.
    assert 0.01 < result["mesh"]["accuracy"] < 0.5
    text = format_evaluation(result)
    assert "median_frame" in text and "F-score@5cm" in text


def test_an_output_without_a_mesh_says_so(tmp_path, recording):
    seq, root = recording
    indices = np.arange(0, 12, 2)
    out = _output(tmp_path, seq, indices, seq.depth[indices], seq.poses[indices], "gt")
    (out / "mesh.ply").unlink()
    result = evaluate_output(out, root, EvalOptions(progress=False))
    assert "mesh" not in result and "no mesh" in result["mesh_missing"]
    assert result["depth"]["metric"]["abs_rel"] < 1e-3
    assert "mesh: no mesh in" in format_evaluation(result)


def test_estimated_poses_are_aligned_before_the_mesh_is_compared(tmp_path, recording):
    seq, root = recording
    indices = np.arange(12)
    # An up-to-scale reconstruction: the whole world scaled by 0.5 and shifted.
    poses = seq.poses[indices].copy()
    poses[:, :3, 3] = 0.5 * poses[:, :3, 3] + np.array([1.0, -2.0, 0.5])
    out = _output(tmp_path, seq, indices, seq.depth[indices] * 0.5, poses, "estimate")
    result = evaluate_output(out, root, EvalOptions(progress=False, mesh_points=20_000))
    assert result["trajectory"]["ate_sim3"]["rmse"] < 1e-6
    assert result["trajectory"]["ate_sim3"]["scale"] == pytest.approx(2.0, rel=1e-6)
    assert result["trajectory"]["ate_se3"]["rmse"] > 0.01  # a rigid fit cannot undo the scale
    assert result["depth"]["median_sequence"]["abs_rel"] < 2e-3
    assert result["mesh_align"] == "sim3"
    assert result["mesh"]["fscore"] > 0.9


def test_icp_registers_a_right_mesh_whose_trajectory_is_off(tmp_path, recording):
    """Tanks and Temples' two-step registration: the mesh is right, but the camera centres are
    spread 8 % too wide, so the trajectory's Sim(3) shrinks the mesh with them; ICP on the
    surface puts it back."""
    seq, root = recording
    indices = np.arange(12)
    mesh = fuse(seq.depth[indices], seq.rgb[indices], seq.poses[indices], seq.intrinsics,
                FusionOptions(progress=False)).mesh
    poses = seq.poses[indices].copy()
    centre = poses[:, :3, 3].mean(0)
    poses[:, :3, 3] = centre + 1.08 * (poses[:, :3, 3] - centre)
    report = {"frames": {"indices": list(map(int, indices))}, "poses": {"source": "estimate"}}
    export_reconstruction(OutputFolder(tmp_path / "out"), mesh=mesh, poses=poses, intrinsics=seq.intrinsics,
                          shape=(120, 160), depth=seq.depth[indices], report=report, glb=False)
    by_trajectory = evaluate_output(tmp_path / "out", root, EvalOptions(progress=False, mesh_points=20_000))
    refined = evaluate_output(tmp_path / "out", root,
                              EvalOptions(progress=False, mesh_points=20_000, mesh_align="sim3+icp"))
    assert by_trajectory["trajectory"]["ate_sim3"]["scale"] == pytest.approx(1 / 1.08, rel=1e-3)
    assert by_trajectory["mesh_align"] == "sim3" and by_trajectory["mesh"]["fscore"] < 0.7
    assert refined["mesh_align"] == "sim3+icp" and refined["mesh"]["fscore"] > 0.9
    assert refined["mesh_icp"]["scale"] == pytest.approx(1.08, rel=0.01)
    # The same evaluation keeps the trajectory-only score, equal to the plain run's.
    assert refined["mesh_before_icp"]["fscore"] == pytest.approx(by_trajectory["mesh"]["fscore"], abs=1e-9)
    assert f"before ICP {refined['mesh_before_icp']['fscore']:.4f}" in format_evaluation(refined)
    assert f"alignment: scale {refined['mesh_icp']['scale']:.4f}" in format_evaluation(refined)


def test_an_icp_that_collapses_the_mesh_is_refused(monkeypatch):
    """Scaled ICP on surfaces that barely overlap can shrink the mesh towards a point; the
    evaluation then keeps the trajectory's alignment and says so."""
    import recon.eval.mesh as mesh_module

    square = (np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    collapse = np.diag([0.05, 0.05, 0.05, 1.0])
    monkeypatch.setattr(mesh_module, "icp_similarity", lambda pred, gt: collapse)
    mesh, icp = mesh_module.icp_registered(square, square, 1000)
    assert not icp["accepted"] and icp["scale"] == pytest.approx(0.05)
    np.testing.assert_array_equal(mesh[0], square[0])
    monkeypatch.setattr(mesh_module, "icp_similarity", lambda pred, gt: np.diag([1.1, 1.1, 1.1, 1.0]))
    mesh, icp = mesh_module.icp_registered(square, square, 1000)
    assert icp["accepted"] and icp["rotation_deg"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(mesh[0], 1.1 * square[0])


def test_bad_folders(tmp_path, recording):
    _, root = recording
    with pytest.raises(ReconInputError, match="report.json"):
        load_output(tmp_path)
    (tmp_path / "report.json").write_text(json.dumps({"frames": {"indices": [0, 50]}}))
    with pytest.raises(ReconInputError, match="do not fit"):
        evaluate_output(tmp_path, root)


def test_cli_writes_eval_json_and_refuses_to_overwrite(tmp_path, recording, capsys):
    from recon.commands.cli import main

    seq, root = recording
    indices = np.arange(0, 12, 3)
    out = _output(tmp_path, seq, indices, seq.depth[indices], seq.poses[indices], "gt")
    assert main(["eval", str(out), "--gt", str(root), "--quiet"]) == 0
    saved = json.loads((out / "eval.json").read_text())
    assert saved["depth"]["metric"]["abs_rel"] < 1e-3
    assert saved["frames"] == len(indices)
    assert main(["eval", str(out), "--gt", str(root), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err
