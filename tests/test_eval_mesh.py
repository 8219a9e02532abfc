"""Mesh metrics against values computed by hand on tiny meshes."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from recon.eval.mesh import mesh_arrays, mesh_metrics, point_metrics, sample_surface, visible_mask

SQUARE_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
SQUARE_T = np.array([[0, 1, 2], [0, 2, 3]])
N = 100_000  # ~3 mm spacing on 1 m^2: lateral offsets add < 1 mm to the distances below


def _square(shift_z: float = 0.0, length_x: float = 1.0):
    v = SQUARE_V.copy()
    v[:, 0] *= length_x
    v[:, 2] += shift_z
    return v, SQUARE_T


def test_identical_meshes():
    m = mesh_metrics(_square(), _square(), num_points=N)
    assert m.accuracy < 0.003 and m.completeness < 0.003
    assert m.precision == 1.0 and m.recall == 1.0 and m.fscore == 1.0


def test_shift_3cm_inside_threshold():
    # Every point's nearest neighbour is straight across the 3 cm gap.
    m = mesh_metrics(_square(), _square(0.03), num_points=N)
    assert m.accuracy == pytest.approx(0.03, abs=1e-3)
    assert m.completeness == pytest.approx(0.03, abs=1e-3)
    assert m.chamfer == pytest.approx(0.03, abs=1e-3)
    assert (m.precision, m.recall, m.fscore) == (1.0, 1.0, 1.0)
    # Below the gap nothing matches.
    m = mesh_metrics(_square(), _square(0.03), threshold=0.02, num_points=N)
    assert (m.precision, m.recall, m.fscore) == (0.0, 0.0, 0.0)


def test_shift_7cm_outside_threshold():
    m = mesh_metrics(_square(), _square(0.07), num_points=N)
    assert m.accuracy == pytest.approx(0.07, abs=1e-3)
    assert m.completeness == pytest.approx(0.07, abs=1e-3)
    assert (m.precision, m.recall, m.fscore) == (0.0, 0.0, 0.0)
    assert m.threshold == 0.05 and m.pred_points == N and m.gt_points == N


def test_partial_coverage():
    # Prediction covers half of a 2 m x 1 m ground truth in the same plane. Ground-truth
    # points with x in (1, 2) are x - 1 away: completeness = 0.5 * 0 + 0.5 * 0.5 = 0.25;
    # recall = P(x < 1.05) = 0.525; precision = 1; F = 2 * 0.525 / 1.525.
    m = mesh_metrics(_square(), _square(length_x=2.0), num_points=N)
    assert m.accuracy < 0.003
    assert m.completeness == pytest.approx(0.25, abs=0.005)
    assert m.precision == 1.0
    assert m.recall == pytest.approx(0.525, abs=0.005)
    assert m.fscore == pytest.approx(2 * 0.525 / 1.525, abs=0.005)


def test_mesh_types_agree():
    v, t = _square(0.03)
    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    tensor = o3d.t.geometry.TriangleMesh.from_legacy(legacy)
    tm = trimesh.Trimesh(v, t, process=False)
    ref = mesh_metrics(_square(), (v, t), num_points=10_000)
    for other in (legacy, tm):
        assert mesh_metrics(_square(), other, num_points=10_000) == ref
    # The tensor mesh stores float32 vertices.
    assert mesh_metrics(_square(), tensor, num_points=10_000).to_dict() == pytest.approx(ref.to_dict(), rel=1e-5)
    assert np.allclose(mesh_arrays(tensor)[0], v)


def test_sampling_is_uniform_and_seeded():
    p = sample_surface(_square(length_x=2.0), 50_000, seed=3)
    assert p.shape == (50_000, 3)
    assert np.all((p[:, 0] >= 0) & (p[:, 0] <= 2) & (p[:, 1] >= 0) & (p[:, 1] <= 1)) and np.all(p[:, 2] == 0)
    # Uniform by area: the mean is the centre and each half holds half the points.
    assert p[:, :2].mean(0) == pytest.approx([1.0, 0.5], abs=0.01)
    assert np.mean(p[:, 0] < 1) == pytest.approx(0.5, abs=0.01)
    assert np.array_equal(p, sample_surface(_square(length_x=2.0), 50_000, seed=3))
    assert sample_surface((np.zeros((0, 3)), np.zeros((0, 3), int)), 10).shape == (0, 3)


def test_empty_prediction():
    m = point_metrics(np.zeros((0, 3)), np.ones((5, 3)))
    assert m.accuracy == np.inf and m.fscore == 0.0


def test_visible_mask():
    # Camera at the origin looking down +z at a wall 2 m away.
    h, w, intr = 20, 20, (10.0, 10.0, 9.5, 9.5)
    depth = np.full((1, h, w), 2.0, np.float32)
    depth[0, :, :5] = 0.0  # a hole on the left: nothing observed there
    poses = np.eye(4)[None]
    points = np.array(
        [
            [0.0, 0.0, 2.0],  # on the wall
            [0.0, 0.0, 1.0],  # in front of it (a floater): still counts
            [0.0, 0.0, 3.0],  # hidden behind the wall
            [0.0, 0.0, -1.0],  # behind the camera
            [5.0, 0.0, 2.0],  # outside the image
            [-1.6, 0.0, 2.0],  # projects into the hole (u ~ 1.5)
        ]
    )
    assert visible_mask(points, depth, poses, intr).tolist() == [True, True, False, False, False, False]
