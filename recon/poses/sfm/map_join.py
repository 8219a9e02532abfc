"""Joining the stretches of a trajectory across a break through SfM's map.

Where the frames either side of a break share too little for the ORB join
(``recon.poses.checks.join``), views of both stretches go to COLMAP together
(``recon.poses.sfm.mapper``; incremental mapping registers each by PnP, Schönberger and
Frahm, CVPR 2016); each stretch's registered views give its similarity into the model, and
the join is the first followed by the inverse of the second. Accepted only when both
stretches sit well in the model (``min_views``, ``max_residual``, ``max_turn_deg``).
:func:`map_join` returns ``recon.poses.checks.join.Join``.
More: docs/poses.md#how-a-join-is-made
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from recon.poses.checks.join import Join, View, mean_rotation, rotation_disagreement, similarity_scale

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MapJoinConfig:
    """views: views taken from each stretch, evenly apart over its ``reach`` frames nearest
    the break; min_views: of each stretch's views that must be
    registered in the model; max_residual: largest RMSE of a stretch's centres after its
    similarity, as a share of their spread in the model; max_turn_deg: largest disagreement
    of a registered view's rotation with its stretch's similarity; min_spread: the views of
    a stretch must spread at least this share of the model's size (else they fix no scale);
    max_scale_jump: the join's scale must lie within [1 / this, this] (both stretches were
    brought to the depth prior's metres, so a larger jump is a model gone wrong);
    max_num_features: SIFT features per view."""

    views: int = 8
    reach: int = 48
    min_views: int = 4
    max_residual: float = 0.05
    max_turn_deg: float = 5.0
    min_spread: float = 0.05
    max_scale_jump: float = 3.0
    max_num_features: int = 4096


@dataclass
class StretchFit:
    """The similarity taking one stretch's poses into the model's frame: x_model = scale *
    rotation @ x + translation; residual: centres' RMSE after it over their spread in the
    model; turn_deg: largest rotation disagreement; spread: the centres' spread in the model
    over the model's size."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residual: float
    turn_deg: float
    spread: float


def fit_stretch(poses: np.ndarray, model_poses: np.ndarray) -> StretchFit:
    """The similarity from a stretch's camera-to-world poses (M, 4, 4) onto the same
    views' camera-to-world poses in the model (M, 4, 4), M >= 2, and how well it fits."""
    rotation = mean_rotation(model_poses[:, :3, :3] @ np.swapaxes(poses[:, :3, :3], -1, -2))
    src, dst = poses[:, :3, 3], model_poses[:, :3, 3]
    scale = similarity_scale(src, dst, rotation)
    translation = dst.mean(0) - scale * rotation @ src.mean(0)
    spread = float(np.sqrt(((dst - dst.mean(0)) ** 2).sum(1).mean()))
    moved = scale * src @ rotation.T + translation
    residual = float(np.sqrt(((moved - dst) ** 2).sum(1).mean()) / max(spread, 1e-12))
    turn = float(rotation_disagreement(rotation @ poses[:, :3, :3], model_poses[:, :3, :3]).max())
    return StretchFit(scale, rotation, translation, residual, turn, spread)


def compose_join(before: StretchFit, after: StretchFit) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation (3, 3), translation (3,)) of x_before = scale * rotation @ x_after +
    translation: ``after`` into the model, then out of it by the inverse of ``before``."""
    rotation = before.rotation.T @ after.rotation
    scale = after.scale / before.scale
    translation = before.rotation.T @ (after.translation - before.translation) / before.scale
    return float(scale), rotation, translation


def map_join(before: list[View], after: list[View], intrinsics, cfg: MapJoinConfig | None = None) -> Join | None:
    """The join of the stretch `after` a break onto the stretch `before` it through one SfM
    model of both stretches' views (module docstring), or None when the model does not hold
    enough of either or they do not fit it. intrinsics: (fx, fy, cx, cy) of the views' images
    (the views need no depth)."""
    cfg = cfg or MapJoinConfig()
    if len(before) < cfg.min_views or len(after) < cfg.min_views:
        return None
    from recon.poses.sfm.mapper import SfMConfig, views_model

    sfm_cfg = SfMConfig(loop_matching="exhaustive", calibrate_lens=False, max_num_features=cfg.max_num_features)
    in_model = views_model([v.rgb for v in before + after], intrinsics, sfm_cfg)
    sides = {"before": range(len(before)), "after": range(len(before), len(before) + len(after))}
    registered = {name: [i for i in ids if i in in_model] for name, ids in sides.items()}
    if any(len(ids) < cfg.min_views for ids in registered.values()):
        log.debug("map join: registered %s of %d + %d views", {k: len(v) for k, v in registered.items()},
                  len(before), len(after))
        return None
    views = before + after
    centres = np.stack([T[:3, 3] for T in in_model.values()])
    size = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    fits = {name: fit_stretch(np.stack([views[i].pose for i in ids]), np.stack([in_model[i] for i in ids]))
            for name, ids in registered.items()}
    for name, f in fits.items():
        if f.residual > cfg.max_residual or f.turn_deg > cfg.max_turn_deg or f.spread < cfg.min_spread * size:
            log.debug("map join: the stretch %s does not fit the model (residual %.3f, turn %.1f deg, spread %.3f)",
                      name, f.residual, f.turn_deg, f.spread / max(size, 1e-12))
            return None
    scale, rotation, translation = compose_join(fits["before"], fits["after"])
    if not 1.0 / cfg.max_scale_jump <= scale <= cfg.max_scale_jump:
        return None
    posed = [i - len(before) for i in registered["after"]]
    residual = max(f.residual for f in fits.values())
    turn = max(f.turn_deg for f in fits.values())
    return Join(scale, rotation, translation, posed, [], residual, turn)


__all__ = ["MapJoinConfig", "StretchFit", "compose_join", "fit_stretch", "map_join"]
