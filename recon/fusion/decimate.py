"""A mesh thinned to a triangle budget by vertex clustering (Rossignac and Borrel 1993): the
vertices in each cell of a grid merged into their mean, vertex colours averaged with them.

Web viewers and phone AR stall on meshes of millions of triangles. A TSDF mesh is already a
grid surface, so a coarser grid thins it evenly. The clustering is vectorised over the whole
mesh (Open3D's ``simplify_vertex_clustering`` builds the same mesh one vertex at a time in
hash maps, ~1.8 s for 1.6 M triangles on one core; this takes about a quarter of that).
why: docs/decisions.md#the-triangle-budget
"""

from __future__ import annotations

import logging
import math

import numpy as np
import open3d as o3d

from .volume import canonical_mesh

log = logging.getLogger(__name__)

# The triangle budget (within_budget): a thinned mesh keeps at least this share of the
# budget, found in at most BUDGET_TRIES clusterings.
BUDGET_FILL = 0.8
BUDGET_TRIES = 3


def cluster_vertices(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None,
                     cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Merge the vertices in each cell of a grid into their mean.

    The grid's cells are ``cell`` wide, its origin half a cell below the lowest vertex. A
    triangle whose corners fall into fewer than three cells is dropped, the others join
    their cells' vertices (winding kept), and a triangle made twice with the same winding
    is kept once. Every cell holding a vertex becomes one, used by a triangle or not.

    Args:
        vertices: (V, 3) float64 positions, V >= 1.
        triangles: (T, 3) integer vertex indices.
        colors: (V, 3) vertex colours, or None.
        cell: grid cell size in the vertices' units, > 0.

    Returns:
        (vertices (C, 3) float64: each cell's mean, triangles (T', 3) int32 into them, each
        starting at its lowest index, colours (C, 3) float64: each cell's mean, or None).
    """
    corner = vertices.min(axis=0) - 0.5 * cell
    index = np.floor((vertices - corner) / cell).astype(np.int64)
    span = index.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:
        key = (index[:, 0] * span[1] + index[:, 1]) * span[2] + index[:, 2]
        cells, of_vertex = np.unique(key, return_inverse=True)
    else:  # a grid too fine for one int64 key
        cells, of_vertex = np.unique(index, axis=0, return_inverse=True)
    of_vertex = of_vertex.reshape(-1)
    count = np.bincount(of_vertex, minlength=len(cells)).astype(np.float64)

    def cell_mean(values: np.ndarray) -> np.ndarray:
        sums = [np.bincount(of_vertex, weights=values[:, d], minlength=len(cells)) for d in range(values.shape[1])]
        return np.stack(sums, axis=1) / count[:, None]

    first, second, third = of_vertex[np.asarray(triangles)].T
    kept = (first != second) & (second != third) & (first != third)
    first, second, third = first[kept], second[kept], third[kept]
    start = np.argmin(np.stack([first, second, third]), axis=0)
    rotated = np.stack([np.choose(start, turn) for turn in ((first, second, third), (second, third, first),
                                                            (third, first, second))], axis=1)
    joined = _unique_rows(rotated, len(cells))
    return (cell_mean(vertices), joined.astype(np.int32),
            None if colors is None else cell_mean(np.asarray(colors, dtype=np.float64)))


def _unique_rows(rows: np.ndarray, base: int) -> np.ndarray:
    """The distinct rows (R', 3), sorted, of rows (R, 3) of integers in [0, base)."""
    if len(rows) == 0:
        return rows.reshape(0, 3)
    if float(base) ** 3 >= 2.0**62:
        return np.unique(rows, axis=0)
    key = (rows[:, 0].astype(np.int64) * base + rows[:, 1]) * base + rows[:, 2]
    key = np.sort(key)
    key = key[np.concatenate([[True], key[1:] != key[:-1]])]
    return np.stack([key // (base * base), (key // base) % base, key % base], axis=1)


def clustered_mesh(mesh: o3d.geometry.TriangleMesh, cell: float) -> o3d.geometry.TriangleMesh:
    """``cluster_vertices`` of a legacy TriangleMesh (its colours carried, normals not).

    Args:
        mesh: legacy TriangleMesh with at least one vertex.
        cell: grid cell size in metres, > 0.

    Returns:
        A new TriangleMesh.
    """
    colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    vertices, triangles, colors = cluster_vertices(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colors, cell)
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    if colors is not None:
        out.vertex_colors = o3d.utility.Vector3dVector(colors)
    return out


def within_budget(mesh: o3d.geometry.TriangleMesh, max_triangles: int) -> o3d.geometry.TriangleMesh:
    """The mesh thinned to at most `max_triangles` triangles by vertex clustering.

    The cell size is chosen from the mesh's mean edge length so that the triangles land
    between BUDGET_FILL and 1 of the budget (a triangle count falls with the square of the
    cell).

    Args:
        mesh: legacy TriangleMesh.
        max_triangles: triangle budget; 0 = no limit.

    Returns:
        The mesh itself when within budget, else a thinned mesh in canonical order
        (``volume.canonical_mesh``) with vertex normals, colours clipped to [0, 1].
    """
    if max_triangles <= 0 or len(mesh.triangles) <= max_triangles:
        return mesh
    cell = mean_edge_length(mesh) * math.sqrt(len(mesh.triangles) / max_triangles)
    small = mesh
    for _ in range(BUDGET_TRIES):
        small = clustered_mesh(mesh, cell)
        count = max(len(small.triangles), 1)
        if BUDGET_FILL * max_triangles <= count <= max_triangles:
            break
        # Aim at the middle of the band: the count follows 1 / cell^2.
        cell *= math.sqrt(count / (0.5 * (1.0 + BUDGET_FILL) * max_triangles))
    while len(small.triangles) > max_triangles:  # the band missed on every try: thin until it fits
        cell *= math.sqrt(len(small.triangles) / max_triangles) * 1.05
        small = clustered_mesh(mesh, cell)
    log.info("mesh thinned from %d to %d triangles (--max-triangles; 0 keeps the full mesh)",
             len(mesh.triangles), len(small.triangles))
    if small.has_vertex_colors():
        small.vertex_colors = o3d.utility.Vector3dVector(np.clip(np.asarray(small.vertex_colors), 0, 1))
    small.compute_vertex_normals()
    return canonical_mesh(small)


def mean_edge_length(mesh: o3d.geometry.TriangleMesh, sample: int = 100_000) -> float:
    """Mean length of the mesh's triangle edges (each edge counted once per triangle).

    Args:
        mesh: legacy TriangleMesh with at least one triangle.
        sample: about this many triangles are taken evenly through the list (all of a
            smaller mesh).

    Returns:
        The mean edge length in the mesh's units (metres).
    """
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    corners = vertices[triangles[:: max(1, len(triangles) // sample)]]  # (T', 3, 3)
    return float(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).mean())


__all__ = ["cluster_vertices", "clustered_mesh", "mean_edge_length", "within_budget"]
