"""What the SfM fallback reads from COLMAP's model (``recon.poses.sfm.mapper`` builds it): the
poses and camera, how well each registered image's pose explains its matches, and the
prior / SfM depth ratios that fix the metric scale and correct the keyframes' prior depth.

Functions take the pycolmap module or its objects as arguments; pycolmap is imported only
where the pipeline runs (``sfm._import_pycolmap``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon.poses.result import PriorSource


def model_poses(rec) -> tuple[dict[int, np.ndarray], tuple[float, float, float, float], float]:
    """World-to-camera 4x4 poses {frame index: T_cw}, the camera's (fx, fy, cx, cy) and its
    radial term k1 (0 for the pinhole models; SIMPLE_RADIAL's k is OpenCV's k1, as
    ``projective.undistort``)."""
    poses = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        T = np.eye(4)
        T[:3] = image.cam_from_world().matrix()
        poses[int(Path(image.name).stem)] = T
    cam = next(iter(rec.cameras.values()))
    p = np.asarray(cam.params, dtype=np.float64)
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name.startswith("SIMPLE") else (p[0], p[1], p[2], p[3])
    k1 = float(p[3]) if cam.model.name == "SIMPLE_RADIAL" else 0.0
    return poses, (float(fx), float(fy), float(cx) - 0.5, float(cy) - 0.5), k1


def model_evidence(pycolmap, db_path: Path, rec, min_inliers: int, max_error: float = 4.0) -> dict[int, float]:
    """{frame index: the share of its 2D-3D correspondences that its pose explains} for the
    registered images: a keypoint with a verified match (``min_inliers`` or more per pair)
    to a keypoint of another registered image that observes a model point should see that
    point; it counts as explained within `max_error` pixels (COLMAP's filter threshold).
    NaN without such correspondences.

    A PnP inlier ratio over the verified matches: 0.93-1.0 (median 0.97) on every 12th
    7-Scenes frame. The share of keypoints that observe a model point would not do (median
    0.32, tenth percentile 0.19 there; TUM fr1/rpy down to 0.14): most SIFT keypoints match
    nothing, and under pure rotation matched points are not triangulated."""
    images = {im.image_id: im for im in rec.images.values() if im.has_pose}
    keypoints = {i: (np.array([p.xy for p in im.points2D], dtype=np.float64).reshape(-1, 2),
                     np.array([p.point3D_id if p.has_point3D() else -1 for p in im.points2D], dtype=np.int64))
                 for i, im in images.items()}
    # COLMAP's scratch database (see sfm._colmap_pipeline), read through pycolmap.
    db = pycolmap.Database.open(db_path)
    try:
        pair_ids, geometries = db.read_two_view_geometries()
    finally:
        db.close()
    corr: dict[int, list[np.ndarray]] = {i: [] for i in images}  # rows (keypoint, point id)
    for pair, geometry in zip(pair_ids, geometries):
        a, b = pycolmap.pair_id_to_image_pair(pair)
        m = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
        if a not in images or b not in images or len(m) < min_inliers:
            continue
        for i, j, ki, kj in ((a, b, m[:, 0], m[:, 1]), (b, a, m[:, 1], m[:, 0])):
            pid = keypoints[j][1][kj]
            corr[i].append(np.stack([ki[pid >= 0], pid[pid >= 0]], 1))
    point_ids = np.array(sorted(rec.points3D), dtype=np.int64)
    xyz = np.array([rec.points3D[int(p)].xyz for p in point_ids]).reshape(-1, 3)
    out = {}
    for i, im in images.items():
        rows = np.unique(np.concatenate(corr[i]), axis=0) if corr[i] else np.zeros((0, 2), np.int64)
        if not len(rows):
            out[int(Path(im.name).stem)] = float("nan")
            continue
        X = xyz[np.searchsorted(point_ids, rows[:, 1])]
        T = im.cam_from_world().matrix()
        uv = rec.cameras[im.camera_id].img_from_cam(X @ T[:, :3].T + T[:, 3])
        err = np.linalg.norm(uv - keypoints[i][0][rows[:, 0]], axis=1)
        out[int(Path(im.name).stem)] = float(np.mean(np.nan_to_num(err, nan=np.inf) < max_error))
    return out


@dataclass
class PointDepths:
    """One registered image's triangulated points: u, v (P,) int their pixel in the prior's
    depth map of ``shape`` (h, w); z (P,) their depth in the camera (SfM units); d (P,) the
    prior's depth there (metres, > 0)."""

    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    d: np.ndarray
    shape: tuple[int, int]


def point_depths(rec, prior: PriorSource, frames: list[np.ndarray], min_points: int = 10) -> dict[int, PointDepths]:
    """Per registered image with at least ``min_points`` points the prior has depth at: the
    SfM depth and the prior's depth of its triangulated points (:class:`PointDepths`)."""
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        i = int(Path(image.name).stem)
        pts = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
        if len(pts) < min_points:
            continue
        xy = np.array([a for a, _ in pts])
        xyz = np.array([b for _, b in pts])
        T = image.cam_from_world().matrix()
        z = xyz @ T[:, :3].T + T[:, 3]
        depth = prior.get(i, frames[i])
        height, width = frames[i].shape[:2]
        # COLMAP pixel coordinates start at the image corner: floor() gives the pixel.
        u = np.clip((xy[:, 0] * depth.shape[1] / width).astype(int), 0, depth.shape[1] - 1)
        v = np.clip((xy[:, 1] * depth.shape[0] / height).astype(int), 0, depth.shape[0] - 1)
        d = depth[v, u]
        ok = (d > 0) & (z[:, 2] > 1e-6)
        if ok.sum() >= min_points:
            out[i] = PointDepths(u[ok], v[ok], z[ok, 2], d[ok], depth.shape[:2])
    return out


def depth_ratios(points: dict[int, PointDepths], grid: tuple[int, int]) -> dict[int, tuple[float, np.ndarray]]:
    """Per image of ``points`` (:func:`point_depths`): the median ratio prior depth / SfM depth
    over its points, and the same median per cell of a coarse (rows, cols) grid over the image
    (the image median where a cell has fewer than 5 points). Network depth errors are mostly
    smooth, so the grid corrects the prior's shape as well as its scale."""
    out = {}
    rows, cols = grid
    for i, p in points.items():
        ratio = p.d / p.z
        total = float(np.median(ratio))
        cell = (p.v * rows // p.shape[0]) * cols + (p.u * cols // p.shape[1])
        cells = np.full(rows * cols, total)
        for c in range(rows * cols):
            if (cell == c).sum() >= 5:
                cells[c] = np.median(ratio[cell == c])
        out[i] = (total, cells.reshape(rows, cols))
    return out


def corrected_disp(depth: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Inverse depth (h, w) in SfM units of a pooled prior depth (h, w) and its per-cell
    ratios (rows, cols) prior / SfM depth (bilinear between cell centres)."""
    h, w = depth.shape
    ratio = np.exp(cv2.resize(np.log(cells).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR))
    fill = np.median(depth[depth > 0])
    return ratio / np.where(depth > 0, depth, fill)
