"""The triangle budget: vertex clustering (recon.fusion.decimate)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from recon.fusion.decimate import cluster_vertices, clustered_mesh, within_budget


def _coloured_sphere(resolution: int) -> o3d.geometry.TriangleMesh:
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=resolution)
    sphere.vertex_colors = o3d.utility.Vector3dVector(np.abs(np.asarray(sphere.vertices)))
    return sphere


@pytest.mark.parametrize("cell", [0.02, 0.05, 0.13])
def test_the_clustering_makes_the_mesh_open3ds_vertex_clustering_makes(cell):
    """Against Open3D's simplify_vertex_clustering (Average): the same cells' means (to
    1e-12) with the same colours, and the same triangles, winding included."""
    sphere = _coloured_sphere(120)
    ours = clustered_mesh(sphere, cell)
    theirs = sphere.simplify_vertex_clustering(voxel_size=cell,
                                               contraction=o3d.geometry.SimplificationContraction.Average)
    assert len(ours.vertices) == len(theirs.vertices) and len(ours.triangles) == len(theirs.triangles)
    distance, match = cKDTree(np.asarray(theirs.vertices)).query(np.asarray(ours.vertices))
    assert distance.max() < 1e-12 and len(np.unique(match)) == len(match)
    np.testing.assert_allclose(np.asarray(ours.vertex_colors), np.asarray(theirs.vertex_colors)[match], atol=1e-12)

    def rotated(triangles):  # each triangle from its lowest index, winding kept
        turns = np.stack([np.roll(triangles, -k, axis=1) for k in range(3)])
        return turns[np.argmin(triangles, axis=1), np.arange(len(triangles))]

    mine = {tuple(t) for t in rotated(match[np.asarray(ours.triangles)])}
    assert mine == {tuple(t) for t in rotated(np.asarray(theirs.triangles))}


def test_a_triangle_in_fewer_than_three_cells_goes_and_a_repeated_one_stays_once():
    """Four vertices: two share a cell. The triangle over the shared cell is dropped, the two
    others become the same triangle (same winding) and are kept once; the merged vertex is
    the two's mean, with their mean colour."""
    vertices = np.array([[0.0, 0, 0], [0.1, 0, 0], [2.0, 0, 0], [0, 2.0, 0]])
    colors = np.array([[0.0, 0, 0], [1.0, 1, 1], [0.5, 0.5, 0.5], [0.2, 0.2, 0.2]])
    triangles = np.array([[0, 1, 2], [0, 2, 3], [1, 2, 3]])
    merged, joined, merged_colors = cluster_vertices(vertices, triangles, colors, 1.0)
    assert len(merged) == 3 and joined.shape == (1, 3)
    first = int(np.argmin(np.linalg.norm(merged - [0.05, 0, 0], axis=1)))
    np.testing.assert_allclose(merged[first], [0.05, 0, 0])
    np.testing.assert_allclose(merged_colors[first], [0.5, 0.5, 0.5])
    a, b, c = merged[joined[0]]
    assert np.cross(b - a, c - a)[2] > 0  # counter-clockwise, as the input's triangles


def test_a_mesh_over_the_triangle_budget_is_decimated_in_place():
    """A coloured sphere of 180 k triangles within a budget of 5 000: at most 5 000 triangles
    on the same surface (every vertex within 1 % of the radius), colours kept in [0, 1]; a
    budget of 0 or one it is under leaves it as it is."""
    sphere = _coloured_sphere(300)
    small = within_budget(sphere, 5000)
    assert 4000 <= len(small.triangles) <= 5000 and small.has_vertex_colors()
    radius = np.linalg.norm(np.asarray(small.vertices), axis=1)
    assert np.abs(radius - 1.0).max() < 0.01
    colours = np.asarray(small.vertex_colors)
    assert colours.min() >= 0 and colours.max() <= 1
    np.testing.assert_allclose(colours, np.abs(np.asarray(small.vertices)), atol=0.05)
    assert within_budget(sphere, 0) is sphere and within_budget(sphere, 10**7) is sphere
