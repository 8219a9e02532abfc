"""Joining the stretches of a trajectory across a scale break: where one sits against the next.

The frames either side of a break (``recon.poses.checks.scale_watch``) see the same place, so
the stretch after it is located in the one before as ORB-SLAM relocalises (Mur-Artal et
al., T-RO 2015): frames after the break posed by ORB matches and PnP against the depth
before it (``recon.poses.matching.features``) give a similarity with the scale the break
slipped by. A join is accepted only when its frames agree (``min_views``,
``max_residual``, ``max_turn_deg``); :func:`recon.geometry.rigid.apply_similarity` applies it.
More: docs/poses.md#how-a-join-is-made
why: docs/decisions.md#joining-across-a-break
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from recon.poses.matching.features import FeatureConfig, Keypoints, detect, match, pnp_pose, sample_depth


@dataclass(frozen=True)
class JoinConfig:
    """views: frames tried on each side of the break (the last before it, the first after);
    min_views: frames after the break that must be posed in the stretch before it;
    max_residual: largest camera-centre residual after the similarity, as a share of the
        scene's distance (the median depth of the views before the break): what moves the
        scene's projection by that share;
    max_turn_deg: largest disagreement of a posed frame's rotation with the similarity's;
    min_spread_m: centres spread less than this (in the stretch before) fix no scale: the
        join then keeps the scale the depth prior gave both stretches (1)."""

    views: int = 4
    min_views: int = 2
    max_residual: float = 0.05
    max_turn_deg: float = 5.0
    min_spread_m: float = 0.05
    features: FeatureConfig = field(default_factory=lambda: FeatureConfig(num_features=2000, min_inliers=40))


@dataclass
class View:
    """One frame of a stretch: rgb (H, W, 3) uint8, depth (h, w) metres (0 invalid; None for
    frames only posed), pose (4, 4) camera-to-world in its stretch's frame of reference."""

    rgb: np.ndarray
    depth: np.ndarray | None
    pose: np.ndarray


@dataclass
class Join:
    """The similarity taking the stretch after a break into the frame of the one before:
    x_before = scale * rotation @ x_after + translation; posed: frames after the break posed
    in the stretch before (their positions in ``after``); inliers: PnP inliers of each;
    residual: largest centre residual (share of the scene's distance); turn_deg: largest rotation
    disagreement."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    posed: list[int]
    inliers: list[int]
    residual: float
    turn_deg: float

    def to_dict(self) -> dict:
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist(),
                "posed": self.posed, "inliers": self.inliers, "residual": self.residual, "turn_deg": self.turn_deg}


def _grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


def pose_in_before(before: list[View], keys: list[Keypoints], frame: View, frame_keys: Keypoints, intrinsics,
                   cfg: FeatureConfig) -> tuple[np.ndarray | None, int, float]:
    """A frame posed in the frame of reference of the stretch `before` (its views with depth
    and their keypoints `keys`), by PnP against the view it matches best (most inliers):
    (camera-to-world pose (4, 4) or None, inliers, the median ratio of the inliers' depth in
    the frame by that pose to the frame's own depth: how much larger the stretch before
    measures the scene than the frame's depth does; NaN without frame depth)."""
    shape = frame.rgb.shape[:2]
    fx, fy, cx, cy = intrinsics
    best = (None, 0, float("nan"))
    for view, key in zip(before, keys):
        if view.depth is None:
            continue
        ia, ib = match(key, frame_keys, cfg)
        if len(ia) < cfg.min_matches:
            continue
        z = sample_depth(view.depth, key.uv[ia], shape)
        ok = z > 0
        u, v = key.uv[ia, 0][ok], key.uv[ia, 1][ok]
        points = np.stack([(u - cx) / fx * z[ok], (v - cy) / fy * z[ok], z[ok]], axis=1)
        uv = frame_keys.uv[ib][ok]
        T_fv, inliers = pnp_pose(points, uv, intrinsics, cfg)
        if T_fv is None or inliers <= best[1]:
            continue
        in_frame = points @ T_fv[:3, :3].T + T_fv[:3, 3]
        projected = in_frame[:, :2] / in_frame[:, 2:3] * (fx, fy) + (cx, cy)
        near = (in_frame[:, 2] > 0) & (np.linalg.norm(projected - uv, axis=1) < cfg.reprojection)
        ratio = float("nan")
        if frame.depth is not None:
            own = sample_depth(frame.depth, uv[near], shape)
            ratio = float(np.median(in_frame[near, 2][own > 0] / own[own > 0])) if (own > 0).any() else ratio
        best = (view.pose @ np.linalg.inv(T_fv), inliers, ratio)
    return best


def rotation_disagreement(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angles (degrees) between rotations R_a and R_b (..., 3, 3)."""
    cos = (np.trace(np.swapaxes(R_a, -1, -2) @ R_b, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def mean_rotation(rotations: np.ndarray) -> np.ndarray:
    """The rotation nearest the mean of rotations (M, 3, 3) in the chordal sense (SVD)."""
    u, _, vt = np.linalg.svd(rotations.sum(axis=0))
    return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt


def depth_scale(ratios: list[float], after: list[View], posed: list[int]) -> float:
    """The scale from the stretch after a break to the one before it, from the posed
    frames' depth ratios (:func:`pose_in_before`: the stretch before's depth of the matched
    points over the frame's own): the frame's depth is in its own stretch's units
    (recon.poses.checks.scale_watch brought each stretch to the depth prior's), so the median ratio
    is the scale, measured on hundreds of points, where the camera centres after a break lie
    too close together to fix it. NaN when no frame had depth."""
    good = [r for r in ratios if np.isfinite(r) and r > 0]
    return float(np.median(good)) if good else float("nan")


def similarity_scale(src: np.ndarray, dst: np.ndarray, rotation: np.ndarray) -> float:
    """Least-squares s of dst ~ s R src + t (t free) for a known rotation R; src, dst (M, 3)."""
    xs, xd = (src - src.mean(0)) @ rotation.T, dst - dst.mean(0)
    return float((xs * xd).sum() / max((xs * xs).sum(), 1e-12))


def join_stretches(before: list[View], after: list[View], intrinsics, cfg: JoinConfig | None = None) -> Join | None:
    """The join of the stretch `after` a break onto the stretch `before` it (module
    docstring), or None when too few of its frames are posed or they disagree. intrinsics:
    (fx, fy, cx, cy) of the views' images."""
    cfg = cfg or JoinConfig()
    keys = [detect(_grey(v.rgb), cfg.features) for v in before]
    posed, inliers, in_before, ratios = [], [], [], []
    for k, view in enumerate(after):
        pose, count, ratio = pose_in_before(before, keys, view, detect(_grey(view.rgb), cfg.features), intrinsics,
                                            cfg.features)
        if pose is not None:
            posed.append(k)
            inliers.append(count)
            in_before.append(pose)
            ratios.append(ratio)
    if len(posed) < cfg.min_views:
        return None
    in_before = np.stack(in_before)
    in_after = np.stack([after[k].pose for k in posed])
    rotation = mean_rotation(in_before[:, :3, :3] @ np.swapaxes(in_after[:, :3, :3], -1, -2))
    src, dst = in_after[:, :3, 3], in_before[:, :3, 3]
    spread = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    scale = depth_scale(ratios, after, posed)
    if not np.isfinite(scale):
        scale = similarity_scale(src, dst, rotation) if spread >= cfg.min_spread_m else 1.0
    translation = dst.mean(0) - scale * rotation @ src.mean(0)
    moved = scale * src @ rotation.T + translation
    distance = float(np.median([np.median(v.depth[v.depth > 0]) for v in before if v.depth is not None]))
    residual = float(np.linalg.norm(moved - dst, axis=1).max() / distance)
    turn = float(rotation_disagreement(rotation @ in_after[:, :3, :3], in_before[:, :3, :3]).max())
    if residual > cfg.max_residual or turn > cfg.max_turn_deg:
        return None
    return Join(float(scale), rotation, translation, posed, inliers, residual, turn)


__all__ = ["Join", "JoinConfig", "View", "join_stretches", "mean_rotation", "pose_in_before",
           "rotation_disagreement", "similarity_scale"]
