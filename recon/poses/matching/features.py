"""Sparse features for the frames dense flow cannot start on: ORB keypoints matched between a
keyframe and a frame, and the frame's pose from those matches by PnP against the keyframe's
depth (RANSAC).

Dense flow (DIS) is coarse to fine from a zero or predicted start, so a fast turn, a big
step or motion blur can leave it in the wrong basin; binary features matched over the whole
image have no such range limit. The pose they give is only a starting point: the frame is
then aligned by flow seeded from it and must pass the same checks as any other (the
relocalisation-by-PnP of ORB-SLAM, Mur-Artal et al., T-RO 2015, in a dense tracker).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class FeatureConfig:
    """ORB and PnP settings.

    num_features: ORB keypoints per image; max_ratio: Lowe's ratio test on the two nearest
    Hamming distances; min_matches / min_inliers: matches needed before PnP and RANSAC
    inliers needed to accept its pose; reprojection: RANSAC threshold in pixels of the
    matching image.
    """

    num_features: int = 1500
    max_ratio: float = 0.8
    min_matches: int = 30
    min_inliers: int = 20
    reprojection: float = 3.0


@dataclass
class Keypoints:
    """ORB keypoints (P, 2) float32 pixel coordinates and descriptors (P, 32) uint8."""

    uv: np.ndarray
    descriptors: np.ndarray | None


_ORB: dict[int, cv2.ORB] = {}


def detect(gray: np.ndarray, cfg: FeatureConfig) -> Keypoints:
    """ORB keypoints of a grey image (h, w) uint8."""
    if cfg.num_features not in _ORB:
        _ORB[cfg.num_features] = cv2.ORB_create(nfeatures=cfg.num_features, fastThreshold=10)
    keypoints, descriptors = _ORB[cfg.num_features].detectAndCompute(gray, None)
    uv = np.array([k.pt for k in keypoints], dtype=np.float32).reshape(-1, 2)
    return Keypoints(uv, descriptors)


def match(a: Keypoints, b: Keypoints, cfg: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Indices (M,), (M,) of mutually consistent matches a -> b that pass the ratio test."""
    empty = np.zeros(0, dtype=np.int64)
    if a.descriptors is None or b.descriptors is None or len(a.uv) < 2 or len(b.uv) < 2:
        return empty, empty
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    ia, ib = [], []
    for p in pairs:
        if len(p) == 2 and p[0].distance < cfg.max_ratio * p[1].distance:
            ia.append(p[0].queryIdx)
            ib.append(p[0].trainIdx)
    if not ia:
        return empty, empty
    ia, ib = np.array(ia), np.array(ib)
    # One keypoint of b claimed by several of a: keep none of them (repeated texture).
    counts = np.bincount(ib, minlength=len(b.uv))
    keep = counts[ib] == 1
    return ia[keep], ib[keep]


def sample_depth(depth: np.ndarray, uv: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    """Depth (P,) at pixel coordinates uv (P, 2) of an image of image_shape (h, w), read from
    a depth map (h', w') of any resolution (nearest cell; 0 where invalid)."""
    h, w = depth.shape
    sx, sy = w / image_shape[1], h / image_shape[0]
    col = np.clip(((uv[:, 0] + 0.5) * sx).astype(np.int64), 0, w - 1)
    row = np.clip(((uv[:, 1] + 0.5) * sy).astype(np.int64), 0, h - 1)
    return depth[row, col]


def pnp_pose(points: np.ndarray, uv: np.ndarray, intrinsics, cfg: FeatureConfig) -> tuple[np.ndarray | None, int]:
    """Pose (4, 4) mapping the points' frame into the camera that sees them at uv, by EPnP
    in RANSAC refined on the inliers, and the inlier count (None when too few).

    points: (P, 3) float; uv: (P, 2) pixels of an image with intrinsics (fx, fy, cx, cy)."""
    if len(points) < max(cfg.min_matches, 6):
        return None, 0
    fx, fy, cx, cy = intrinsics
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(points.astype(np.float64), uv.astype(np.float64), K, None,
                                                 reprojectionError=cfg.reprojection, iterationsCount=200,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    count = 0 if inliers is None else len(inliers)
    if not ok or count < cfg.min_inliers:
        return None, count
    idx = inliers[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(points[idx].astype(np.float64), uv[idx].astype(np.float64), K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    return T, count


def relative_pose(kf: Keypoints, kf_depth: np.ndarray, frame: Keypoints, intrinsics, image_shape: tuple[int, int],
                  cfg: FeatureConfig) -> tuple[np.ndarray | None, int]:
    """Pose (4, 4) of a frame relative to a keyframe (keyframe camera -> frame camera) from
    ORB matches, the keyframe's depth (h', w') metres (0 invalid) and intrinsics of the
    keypoints' image (image_shape (h, w)); with the PnP inlier count (None when it fails)."""
    ia, ib = match(kf, frame, cfg)
    if len(ia) < cfg.min_matches:
        return None, len(ia)
    z = sample_depth(kf_depth, kf.uv[ia], image_shape)
    ok = z > 0
    fx, fy, cx, cy = intrinsics
    u, v = kf.uv[ia, 0][ok], kf.uv[ia, 1][ok]
    points = np.stack([(u - cx) / fx * z[ok], (v - cy) / fy * z[ok], z[ok]], axis=1)
    return pnp_pose(points, frame.uv[ib][ok], intrinsics, cfg)
