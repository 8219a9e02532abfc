"""The focal length of a camera that turns: self-calibration from the homographies between
its frames.

A camera rotating about its centre maps frame onto frame by H = K R K^-1 whatever the depth,
so K^-1 H K is a rotation, which fixes f (R. Hartley, "Self-calibration from multiple views
with a rotating camera", ECCV 1994; de Agapito, Hayman and Reid, IJCV 2001); square pixels
and the principal point at the image centre leave f the one unknown. SIFT matches, per pair
a homography against a fundamental matrix (Torr's model selection), and the f that makes the
rotating pairs' K^-1 H K most a rotation (:func:`estimate_focal_rotation`, with its range).
More: docs/poses.md#the-homographies-of-a-turning-camera
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from recon.threads import map_on_cores


@dataclass(frozen=True)
class RotationFocalConfig:
    """Settings of :func:`estimate_focal_rotation`.

    scale: frames are measured at this share of their size (SIFT at half size: the same
        focal length on TUM fr1/rpy, a quarter of the time);
    max_features: SIFT keypoints per frame; ratio: Lowe's ratio test;
    min_matches: fewer matches than this and a pair is not fitted;
    gaps: pairs of frames this many apart (in the frames given), each gap's pairs half a gap
        apart, so that both slow and fast turns have pairs that turned;
    inlier_px: RANSAC threshold of both models, pixels of the full-size frames;
    min_flow: a pair whose matches moved less than this share of the width (median) says
        nothing and is not counted;
    rotation_inliers: a pair is a rotation where its homography explains this share of the
        matches its fundamental matrix explains;
    focal_range: candidate focal lengths, as multiples of the width (log grid of
        ``candidates``);
    flat: focal lengths whose summed cost is within this factor of the minimum are not
        ruled out (the range);
    min_rotation_share, min_pairs, max_range: trusted when at least this share of the
        counted pairs are rotations, at least this many, and the range's ends lie within
        this factor. why: docs/validation.md#the-focal-length-of-a-camera-that-turns"""

    scale: float = 0.5
    max_features: int = 1500
    ratio: float = 0.8
    min_matches: int = 30
    gaps: tuple[int, ...] = (2, 4, 8, 16)
    inlier_px: float = 3.0
    min_flow: float = 0.02
    rotation_inliers: float = 0.8
    focal_range: tuple[float, float] = (0.25, 4.0)
    candidates: int = 300
    flat: float = 2.0
    min_rotation_share: float = 0.6
    min_pairs: int = 10
    max_range: float = 1.35


@dataclass
class RotationFocal:
    """Result of :func:`estimate_focal_rotation`: focal (pixels of the frames given; 0 when no
    pair was a rotation), the range (low, high) its summed cost leaves open, the pairs
    counted (matched and moved) and those that were rotations, their share, and whether it
    is trusted."""

    focal: float
    low: float
    high: float
    pairs: int
    rotations: int
    share: float
    trusted: bool

    def to_dict(self) -> dict:
        return asdict(self)


def sift_features(gray: np.ndarray, cfg: RotationFocalConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT keypoints of a grey image (H, W) uint8, measured at ``cfg.scale`` of its size:
    (points (P, 2) float32 in pixels of the full-size image, descriptors (P, 128) or None)."""
    sift = cv2.SIFT_create(nfeatures=cfg.max_features)
    small = gray if cfg.scale == 1 else cv2.resize(gray, None, fx=cfg.scale, fy=cfg.scale,
                                                   interpolation=cv2.INTER_AREA)
    keypoints, descriptors = sift.detectAndCompute(small, None)
    points = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2) / np.float32(cfg.scale)
    return points, descriptors


def matched_points(a, b, cfg: RotationFocalConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Matched points ((M, 2), (M, 2)) of two frames' :func:`sift_features` that pass the
    ratio test, or None for fewer than ``cfg.min_matches``."""
    (pa, da), (pb, db) = a, b
    if da is None or db is None or len(pa) < 2 or len(pb) < 2:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < cfg.ratio * p[1].distance]
    if len(good) < cfg.min_matches:
        return None
    return pa[[m.queryIdx for m in good]], pb[[m.trainIdx for m in good]]


def pair_homography(pa: np.ndarray, pb: np.ndarray, centre: np.ndarray, inlier_px: float
                    ) -> tuple[np.ndarray | None, float]:
    """The homography (3, 3) taking points pa to pb (M, 2), both relative to the principal
    point `centre` (2,), and how many matches it explains against a fundamental matrix
    fitted to them (the ratio of RANSAC inliers, each within `inlier_px`; 1 for a rotation).
    (None, 0) where either model cannot be fitted."""
    H, h_inliers = cv2.findHomography(pa - centre, pb - centre, cv2.RANSAC, inlier_px)
    if H is None or h_inliers is None:
        return None, 0.0
    F, f_inliers = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, inlier_px, 0.999)
    if F is None or f_inliers is None:
        return H, 1.0
    return H, float(h_inliers.mean()) / max(float(f_inliers.mean()), 1e-6)


def rotation_cost(H: np.ndarray, focals: np.ndarray) -> np.ndarray:
    """(F,) ||M M^T - I||_F^2 of M = K^-1 H K scaled to det M = 1, K = diag(f, f, 1) for each
    focal length of `focals` (F,); H (3, 3) in coordinates relative to the principal point.
    Zero where H is K R K^-1 for a rotation R."""
    k = np.stack([focals, focals, np.ones_like(focals)], axis=1)  # (F, 3): K's diagonal
    M = H[None] * k[:, None, :] / k[:, :, None]  # (K^-1 H K)_ij = H_ij k_j / k_i
    det = np.linalg.det(M)
    M = M / np.cbrt(det)[:, None, None]
    P = M @ np.transpose(M, (0, 2, 1)) - np.eye(3)
    return (P * P).sum(axis=(1, 2))


def frame_pairs(count: int, gaps: tuple[int, ...]) -> list[tuple[int, int]]:
    """Pairs (i, i + gap) of `count` frames for each gap, the first frames half a gap apart."""
    return [(i, i + gap) for gap in gaps for i in range(0, count - gap, max(1, gap // 2))]


def estimate_focal_rotation(frames, cfg: RotationFocalConfig | None = None) -> RotationFocal:
    """The focal length (pixels, principal point at the centre) of frames (list of (H, W, 3)
    uint8 RGB, one camera, in order) from the homographies of the pairs that turned
    (module docstring)."""
    cfg = cfg or RotationFocalConfig()
    height, width = frames[0].shape[:2]
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0], np.float32)
    # SIFT releases the GIL: the frames' features on every core (each frame's are its own).
    features = map_on_cores(lambda f: sift_features(cv2.cvtColor(np.asarray(f), cv2.COLOR_RGB2GRAY), cfg), frames)
    focals = width * np.exp(np.linspace(math.log(cfg.focal_range[0]), math.log(cfg.focal_range[1]), cfg.candidates))
    counted, curves = 0, []
    for i, j in frame_pairs(len(frames), cfg.gaps):
        matched = matched_points(features[i], features[j], cfg)
        if matched is None:
            continue
        pa, pb = matched
        if np.median(np.linalg.norm(pb - pa, axis=1)) < cfg.min_flow * width:
            continue
        H, explained = pair_homography(pa, pb, centre, cfg.inlier_px)
        if H is None:
            continue
        counted += 1
        if explained >= cfg.rotation_inliers:
            curves.append(rotation_cost(H, focals))
    if not curves:
        return RotationFocal(0.0, 0.0, 0.0, counted, 0, 0.0, False)
    total = np.sum(curves, axis=0)
    best = int(np.argmin(total))
    near = focals[total <= cfg.flat * total[best]]
    share = len(curves) / counted
    low, high = float(near.min()), float(near.max())
    trusted = share >= cfg.min_rotation_share and len(curves) >= cfg.min_pairs and high <= cfg.max_range * low
    return RotationFocal(parabola_minimum(focals, total, best), low, high, counted, len(curves), float(share),
                         bool(trusted))


def parabola_minimum(focals: np.ndarray, cost: np.ndarray, best: int) -> float:
    """The minimum of a parabola in log f through the grid's best point and its neighbours
    (focals, cost (F,) on a log grid; best: the index of the smallest cost); the grid point
    itself at an end of the grid."""
    if not 0 < best < len(focals) - 1:
        return float(focals[best])
    a, b, c = cost[best - 1:best + 2]
    curvature = a - 2 * b + c
    step = 0.5 * (a - c) / curvature if curvature > 0 else 0.0
    spacing = math.log(focals[best + 1] / focals[best])
    return float(focals[best] * math.exp(float(np.clip(step, -1.0, 1.0)) * spacing))


__all__ = ["RotationFocal", "RotationFocalConfig", "estimate_focal_rotation", "frame_pairs", "matched_points",
           "pair_homography", "parabola_minimum", "rotation_cost", "sift_features"]
