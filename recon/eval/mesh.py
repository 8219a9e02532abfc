"""Mesh reconstruction metrics (NeuralRecon / TransformerFusion protocol).

This module owns uniform surface sampling (same point count for both meshes, fixed seed),
optional culling to what the cameras saw, the point-set metrics (accuracy pred -> gt,
completeness gt -> pred, chamfer, and precision, recall and F-score at ``threshold``, 5 cm by
default; nearest-neighbour distances by scipy's cKDTree) and the registration of a mesh
onto a reference surface by ICP (Tanks and Temples' refinement step).
More: docs/eval.md#how-the-scores-are-computed
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

DEFAULT_THRESHOLD = 0.05
DEFAULT_POINTS = 200_000


@dataclass(frozen=True)
class MeshMetrics:
    """Distances in metres; precision, recall, fscore in [0, 1]; points actually compared."""

    accuracy: float
    completeness: float
    chamfer: float
    precision: float
    recall: float
    fscore: float
    threshold: float
    pred_points: int
    gt_points: int

    def to_dict(self) -> dict:
        return asdict(self)


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, triangles (F, 3) int64) of an Open3D mesh (legacy or tensor),
    a trimesh.Trimesh, or a (vertices, triangles) pair."""
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v, t = mesh
    elif hasattr(mesh, "vertex") and hasattr(mesh, "triangle"):  # open3d.t.geometry.TriangleMesh
        v, t = mesh.vertex.positions.cpu().numpy(), mesh.triangle.indices.cpu().numpy()
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):  # trimesh (its .triangles are corner coordinates)
        v, t = mesh.vertices, mesh.faces
    elif hasattr(mesh, "vertices") and hasattr(mesh, "triangles"):  # legacy open3d
        v, t = mesh.vertices, mesh.triangles
    else:
        raise TypeError(f"expected a mesh or (vertices, triangles), got {type(mesh).__name__}")
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(t, dtype=np.int64).reshape(-1, 3)
    return v, t


class _SurfaceSampler:
    """Area-weighted point sampling on one mesh (triangle areas computed once)."""

    def __init__(self, mesh):
        v, t = mesh_arrays(mesh)
        self.a, self.b, self.c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        area = 0.5 * np.linalg.norm(np.cross(self.b - self.a, self.c - self.a), axis=1)
        self.area = float(area.sum())
        self.cdf = np.cumsum(area) / self.area if self.area > 0 else None

    def __call__(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) points; (0, 3) for a mesh without area."""
        if self.cdf is None:
            return np.zeros((0, 3))
        tri = np.minimum(np.searchsorted(self.cdf, rng.random(n), side="right"), len(self.cdf) - 1)
        # Uniform on a triangle: reflect (u, w) from the unit square into the lower-left half.
        u, w = rng.random(n), rng.random(n)
        flip = u + w > 1
        u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
        a = self.a[tri]
        return a + u[:, None] * (self.b[tri] - a) + w[:, None] * (self.c[tri] - a)


def sample_surface(
    mesh,
    num_points: int = DEFAULT_POINTS,
    seed: int = 0,
    point_filter: Callable[[np.ndarray], np.ndarray] | None = None,
    max_rounds: int = 30,
) -> np.ndarray:
    """(num_points, 3) points uniformly distributed over the mesh surface (by area).

    With `point_filter` ((M, 3) -> (M,) bool), sampling is repeated until `num_points`
    points pass it (or `max_rounds` batches were drawn): the points are then uniform over
    the kept part of the surface, as dense as if that part had been sampled alone.
    Returns fewer points (possibly (0, 3)) when the mesh has no area or too little passes.
    """
    sampler = _SurfaceSampler(mesh)
    rng = np.random.default_rng(seed)
    if point_filter is None:
        return sampler(num_points, rng)
    kept, have, drawn = [], 0, 0
    for _ in range(max_rounds):
        # Draw what the pass rate seen so far says is missing, with 10 % to spare.
        rate = have / drawn if drawn else 1.0
        batch = int(min(max(num_points, 1.1 * (num_points - have) / max(rate, 1e-3)), 4_000_000))
        points = sampler(batch, rng)
        if len(points) == 0:
            break
        points = points[np.asarray(point_filter(points), dtype=bool)]
        kept.append(points)
        have, drawn = have + len(points), drawn + batch
        if have >= num_points:
            break
    return np.concatenate(kept)[:num_points] if kept else np.zeros((0, 3))


def visible_mask(points: np.ndarray, depth, poses: np.ndarray, intrinsics, margin: float = 0.05) -> np.ndarray:
    """(M,) bool: points that some frame saw, i.e. project inside it onto valid depth and
    are not hidden behind the observed surface (z <= depth + margin).

    Points in front of the surface stay visible, so floaters in a prediction still count
    against its precision. points: (M, 3) world; depth: (N, H, W) metres (0 invalid);
    poses: (N, 4, 4) camera-to-world; intrinsics: (4,) or (N, 4).
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(poses)
    k_all = np.asarray(intrinsics, dtype=np.float64)
    k_all = np.broadcast_to(k_all, (n, 4)) if k_all.shape == (4,) else k_all
    seen = np.zeros(len(points), dtype=bool)
    todo = np.arange(len(points))  # points no frame has seen yet: the only ones left to test
    for i in range(n):
        pose = np.asarray(poses[i], dtype=np.float64)
        if not np.isfinite(pose).all() or todo.size == 0:
            continue
        d = np.asarray(depth[i])
        h, w = d.shape
        fx, fy, cx, cy = k_all[i]
        cam = ((points[todo] - pose[:3, 3]) @ pose[:3, :3]).astype(np.float32)  # R^T (X - t)
        front = cam[:, 2] > 1e-6
        idx, cam = todo[front], cam[front]
        u = np.round(fx * cam[:, 0] / cam[:, 2] + cx)
        v = np.round(fy * cam[:, 1] / cam[:, 2] + cy)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        idx, z = idx[inside], cam[inside, 2]
        observed = d[v[inside].astype(np.int64), u[inside].astype(np.int64)]
        ok = (observed > 0) & (z <= observed + margin)
        seen[idx[ok]] = True
        todo = np.flatnonzero(~seen)
    return seen


def point_metrics(pred_points: np.ndarray, gt_points: np.ndarray, threshold: float = DEFAULT_THRESHOLD) -> MeshMetrics:
    """Accuracy, completeness, chamfer, precision, recall, F-score of two point sets (M, 3), (K, 3).

    An empty set has infinite distances and zero precision/recall.
    """
    pred_points = np.asarray(pred_points, dtype=np.float64).reshape(-1, 3)
    gt_points = np.asarray(gt_points, dtype=np.float64).reshape(-1, 3)
    if len(pred_points) == 0 or len(gt_points) == 0:
        return MeshMetrics(np.inf, np.inf, np.inf, 0.0, 0.0, 0.0, float(threshold), len(pred_points), len(gt_points))
    d_pred, _ = cKDTree(gt_points).query(pred_points, workers=-1)
    d_gt, _ = cKDTree(pred_points).query(gt_points, workers=-1)
    precision = float(np.mean(d_pred < threshold))
    recall = float(np.mean(d_gt < threshold))
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    acc, comp = float(d_pred.mean()), float(d_gt.mean())
    return MeshMetrics(
        acc, comp, (acc + comp) / 2, precision, recall, float(fscore), float(threshold), len(pred_points),
        len(gt_points),
    )


def icp_similarity(pred_points: np.ndarray, gt_points: np.ndarray, radii: tuple[float, ...] = (0.2, 0.1, 0.05),
                   iterations: int = 50) -> np.ndarray:
    """The similarity (4, 4: s R | t) that moves pred_points (M, 3) onto gt_points (K, 3) by
    point-to-point ICP with a scale (Umeyama's estimate in each step), coarse to fine over
    the correspondence `radii` in metres. This is the refinement step of Tanks and Temples'
    evaluation (Knapitsch et al., SIGGRAPH 2017): a reconstruction is first registered by
    its camera trajectory, then by its surface, so that the trajectory's own scale and drift
    are not scored as errors of the surface. The points must already be roughly aligned."""
    import open3d as o3d

    def cloud(points):
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))

    source, target = cloud(pred_points), cloud(gt_points)
    estimate = o3d.pipelines.registration.TransformationEstimationPointToPoint(with_scaling=True)
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    transform = np.eye(4)
    for radius in radii:
        transform = o3d.pipelines.registration.registration_icp(source, target, radius, transform, estimate,
                                                                criteria).transformation
    return np.asarray(transform)


# The most ICP may change the trajectory's alignment: a refinement, not a search. Where the
# two surfaces barely overlap, ICP with a scale can shrink the mesh towards a point (on TUM
# fr1/rpy with estimated poses it went to scale 0.05); such a result is refused.
ICP_MAX_SCALE_CHANGE = 1.25
ICP_MAX_ROTATION_DEG = 10.0


def icp_registered(mesh: tuple[np.ndarray, np.ndarray], reference,
                   num_points: int = DEFAULT_POINTS) -> tuple[tuple, dict]:
    """The mesh (vertices, triangles) moved by the similarity ICP finds onto the reference
    surface (:func:`icp_similarity`), and that similarity's size: scale,
    rotation in degrees, translation in metres, and whether it was accepted (within
    ICP_MAX_SCALE_CHANGE and ICP_MAX_ROTATION_DEG; if not, the mesh is returned as it came)."""
    similarity = icp_similarity(sample_surface(mesh, num_points, 0), sample_surface(reference, num_points, 1))
    linear = similarity[:3, :3]
    scale = float(np.cbrt(max(np.linalg.det(linear), 1e-12)))
    angle = float(np.degrees(np.arccos(np.clip((np.trace(linear / scale) - 1) / 2, -1.0, 1.0))))
    accepted = 1 / ICP_MAX_SCALE_CHANGE <= scale <= ICP_MAX_SCALE_CHANGE and angle <= ICP_MAX_ROTATION_DEG
    if accepted:
        mesh = (mesh[0] @ linear.T + similarity[:3, 3], mesh[1])
    return mesh, {"scale": scale, "rotation_deg": angle, "translation_m": float(np.linalg.norm(similarity[:3, 3])),
                  "accepted": bool(accepted)}


def mesh_metrics(
    pred,
    gt,
    threshold: float = DEFAULT_THRESHOLD,
    num_points: int = DEFAULT_POINTS,
    seed: int = 0,
    point_filter: Callable[[np.ndarray], np.ndarray] | None = None,
) -> MeshMetrics:
    """Compare a predicted mesh with a ground-truth mesh.

    Args:
        pred, gt: Open3D / trimesh meshes or (vertices (V, 3), triangles (F, 3)) pairs.
        threshold: precision / recall distance in metres (5 cm).
        num_points: points sampled on each mesh (same number for both, fixed seed).
        point_filter: optional (M, 3) -> (M,) bool restricting both surfaces, e.g.
            ``lambda p: visible_mask(p, depth, poses, intrinsics)`` to evaluate only what
            the cameras saw. Sampling continues until `num_points` pass on each mesh, so a
            ground truth much larger than the observed part is not left sparse there
            (sparse samples would inflate nearest-neighbour distances).

    Compare meshes covering similar areas (or use `point_filter`): with a fixed count, a
    mesh with 10x the area of the other gets 10x sparser samples.
    """
    pred_points = sample_surface(pred, num_points, seed, point_filter)
    gt_points = sample_surface(gt, num_points, seed + 1, point_filter)
    return point_metrics(pred_points, gt_points, threshold)


__all__ = ["ICP_MAX_ROTATION_DEG", "ICP_MAX_SCALE_CHANGE", "MeshMetrics", "icp_registered", "icp_similarity",
           "mesh_arrays", "mesh_metrics", "point_metrics", "sample_surface", "visible_mask"]
