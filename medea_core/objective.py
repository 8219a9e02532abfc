"""The MEDeA objective for a batch of frame pairs: warp frame j into view i with the
current depths, then score colour, depth and features (paper, "Losses").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .config import MedeaConfig
from .frames import FrameData, Level
from .geometry import depth_in_view_i, reproject, sample
from .grid import scale_field
from .losses import depth_loss, feature_loss_m, feature_loss_s, photometric_loss


@dataclass
class PairBatch:
    """A batch of pairs (i, j) with their precomputed relative transforms.

    i, j: (B,) frame indices; i_to_j, j_to_i: (B, 4, 4).
    """

    i: torch.Tensor
    j: torch.Tensor
    i_to_j: torch.Tensor
    j_to_i: torch.Tensor


def warp_level(level: Level, batch: PairBatch, log_scales_i: torch.Tensor, log_scales_j: torch.Tensor, min_validity: float):
    """Warp frame j's maps and depth into view i at one level.

    Returns:
        depth_i (B, H, W), warped maps (B, C, H, W), D_{j->i} (B, H, W), mask (B, H, W).
    """
    size = level.size
    depth_i = level.prior[batch.i] * scale_field(log_scales_i, size)
    depth_j = level.prior[batch.j] * scale_field(log_scales_j, size)
    rep = reproject(depth_i, level.intrinsics[batch.i], level.intrinsics[batch.j], batch.i_to_j, size)
    # One grid_sample for everything that lives in frame j: maps, depth and validity.
    stacked = torch.cat([level.maps[batch.j], depth_j[:, None], level.valid[batch.j, None].float()], dim=1)
    sampled = sample(stacked, rep.uv_j)
    warped_maps, sampled_depth, sampled_valid = sampled[:, :-2], sampled[:, -2], sampled[:, -1]
    mask = rep.valid & level.valid[batch.i] & (sampled_valid >= min_validity)
    depth_j_in_i = depth_in_view_i(sampled_depth, rep.uv_j, level.intrinsics[batch.j], batch.j_to_i)
    return depth_i, warped_maps, depth_j_in_i, mask


def pair_losses(data: FrameData, batch: PairBatch, log_scales_i: torch.Tensor, log_scales_j: torch.Tensor, config: MedeaConfig) -> dict[str, torch.Tensor]:
    """Per-pair loss terms (B,) and "total" (weighted sum of the enabled terms).

    Also returns "valid_fraction" (B,), the share of view i's pixels that j covers.
    """
    level = data.image
    depth_i, warped, depth_j_in_i, mask = warp_level(level, batch, log_scales_i, log_scales_j, config.min_sample_validity)
    terms: dict[str, torch.Tensor] = {}
    total = torch.zeros(batch.i.shape[0], device=depth_i.device)
    if config.use_photometric:
        terms["photometric"] = photometric_loss(level.maps[batch.i], warped, mask)
        total = total + config.photometric_weight * terms["photometric"]
    if config.use_depth:
        terms["depth"] = depth_loss(depth_i, depth_j_in_i, mask)
        total = total + config.depth_weight * terms["depth"]
    if config.use_features and data.features is not None:
        feat = data.features
        _, warped_feat, _, feat_mask = warp_level(feat, batch, log_scales_i, log_scales_j, config.min_sample_validity)
        if config.feature_loss == "S":
            terms["feature"] = feature_loss_s(feat.maps[batch.i], warped_feat, feat_mask, config.feature_eps)
        else:
            terms["feature"] = feature_loss_m(feat.maps[batch.i], warped_feat, feat_mask)
        total = total + config.feature_weight * terms["feature"]
    terms["total"] = total
    terms["valid_fraction"] = mask.flatten(1).float().mean(1)
    return terms
