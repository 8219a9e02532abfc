"""The MEDeA objective for a batch of frame pairs: warp frame j into view i with the
current depths, then score colour, depth and features (paper, "Losses").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .config import MedeaConfig
from .frames import FrameData, Level
from .geometry import depth_in_view_i, pair_transforms, pixel_grid, reproject, sample
from .grid import sample_scale_field, scale_field
from .losses import depth_loss, feature_loss_m, feature_loss_s, photometric_loss, relative_depth_loss


@dataclass
class PairBatch:
    """A batch of pairs (i, j) with their precomputed relative transforms.

    i, j: (B,) frame indices; i_to_j, j_to_i: (B, 4, 4).
    """

    i: torch.Tensor
    j: torch.Tensor
    i_to_j: torch.Tensor
    j_to_i: torch.Tensor


def pixel_lattice(size: tuple[int, int], stride: int, generator: torch.Generator | None) -> tuple[slice, slice]:
    """Rows and columns of view i scored in one step.

    Every `stride`-th pixel, at a random phase so that successive steps cover the whole
    image.

    Args:
        size: (H, W) of view i in pixels.
        stride: keep every stride-th row and column; <= 1: all pixels.
        generator: draws the phase; None: torch's default generator.

    Returns:
        (row slice, column slice); (slice(None), slice(None)) for stride <= 1.
    """
    if stride <= 1:
        return slice(None), slice(None)
    dy, dx = torch.randint(0, stride, (2,), generator=generator).tolist()
    return slice(dy, size[0], stride), slice(dx, size[1], stride)


def warp_level(
    level: Level,
    batch: PairBatch,
    log_scales_i: torch.Tensor,
    log_scales_j: torch.Tensor,
    min_validity: float,
    lattice: tuple[slice, slice] | None = None,
):
    """Warp frame j's maps and depth into view i at one level.

    Args:
        level: the frames at this resolution (maps, prior, validity, intrinsics).
        batch: B pairs (i, j) with their relative transforms.
        log_scales_i: (B, h, w) log-scale grids of frames i.
        log_scales_j: (B, h, w) log-scale grids of frames j.
        min_validity: smallest bilinearly sampled validity of frame j's prior for a
            pixel to count.
        lattice: optional (rows, cols) slices of view i to score (see pixel_lattice);
            frame j is always sampled at full resolution.

    Returns:
        maps_i (B, C, H', W') of view i, depth_i (B, H', W') in metres, warped maps
        (B, C, H', W'), D_{j->i} (B, H', W') in metres, mask (B, H', W') bool; H', W'
        is the lattice (default H, W).
    """
    size = level.size
    lattice = lattice or (slice(None), slice(None))
    packed_i = level.packed[batch.i, :, lattice[0], lattice[1]]
    maps_i, prior_i, valid_i = packed_i[:, :-2], packed_i[:, -2], packed_i[:, -1] > 0.5
    depth_i = prior_i * scale_field(log_scales_i, size, lattice)
    pixels_i = pixel_grid(*size, dtype=depth_i.dtype, device=depth_i.device)[lattice[0], lattice[1]]
    rep = reproject(depth_i, level.intrinsics[batch.i], level.intrinsics[batch.j], batch.i_to_j, size, pixels_i)
    # One grid_sample fetches frame j's maps, prior depth and validity; none of them
    # needs a gradient, only the sampling positions do. Frame j's scale is smooth, so
    # it is sampled from its coarse grid: D_j(uv) = D0_j(uv) * S_j(uv).
    sampled = sample(level.packed[batch.j], rep.uv_j)
    warped_maps, sampled_prior, sampled_valid = sampled[:, :-2], sampled[:, -2], sampled[:, -1]
    sampled_depth = sampled_prior * sample_scale_field(log_scales_j, rep.uv_j, size)
    mask = rep.valid & valid_i & (sampled_valid >= min_validity)
    depth_j_in_i = depth_in_view_i(sampled_depth, rep.uv_j, level.intrinsics[batch.j], batch.j_to_i)
    return maps_i, depth_i, warped_maps, depth_j_in_i, mask


@torch.no_grad()
def pair_overlap(
    data: FrameData,
    pairs: torch.Tensor,
    log_scales: torch.Tensor,
    min_validity: float,
    stride: int = 2,
    chunk: int = 128,
) -> torch.Tensor:
    """The share of view i that frame j covers, per pair, at the current depths.

    The valid_fraction of pair_losses, measured once on a fixed lattice (every
    stride-th pixel, phase 0): how much of view i the pair can score at all.

    Args:
        data: the frames' levels and poses (see prepare_frames).
        pairs: (P, 2) frame pairs (i, j), on the frames' device.
        log_scales: (N, h, w) log-scale grids of every frame.
        min_validity: as MedeaConfig.min_sample_validity.
        stride: score every stride-th row and column of view i.
        chunk: pairs warped at once.

    Returns:
        (P,) share of view i's lattice pixels whose reprojection into j is valid.
    """
    level = data.image
    lattice = (slice(0, level.size[0], stride), slice(0, level.size[1], stride))
    i_to_j, j_to_i = pair_transforms(data.poses, pairs)
    shares = []
    for rows in torch.arange(pairs.shape[0], device=pairs.device).split(chunk):
        batch = PairBatch(pairs[rows, 0], pairs[rows, 1], i_to_j[rows], j_to_i[rows])
        *_, mask = warp_level(level, batch, log_scales[batch.i], log_scales[batch.j], min_validity, lattice)
        shares.append(mask.flatten(1).float().mean(1))
    return torch.cat(shares) if shares else torch.zeros(0, device=pairs.device)


def pair_losses(
    data: FrameData,
    batch: PairBatch,
    log_scales_i: torch.Tensor,
    log_scales_j: torch.Tensor,
    config: MedeaConfig,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """Per-pair loss terms and their weighted sum for a batch of pairs.

    Args:
        data: the frames' levels and poses (see prepare_frames).
        batch: B pairs (i, j) with their relative transforms.
        log_scales_i: (B, h, w) log-scale grids of frames i.
        log_scales_j: (B, h, w) log-scale grids of frames j.
        config: which terms are enabled, their weights, strides and epsilons.
        generator: draws the pixel lattice when config.pixel_stride or
            config.feature_stride > 1.

    Returns:
        dict of (B,) tensors: "photometric", "depth", "feature" (those enabled),
        "total" (weighted sum of the enabled terms) and "valid_fraction" (the share of
        view i's scored pixels that j covers).
    """
    level = data.image
    lattice = pixel_lattice(level.size, config.pixel_stride, generator)
    maps_i, depth_i, warped, depth_j_in_i, mask = warp_level(
        level, batch, log_scales_i, log_scales_j, config.min_sample_validity, lattice
    )
    terms: dict[str, torch.Tensor] = {}
    total = torch.zeros(batch.i.shape[0], device=depth_i.device)
    if config.use_photometric:
        terms["photometric"] = photometric_loss(maps_i, warped, mask)
        total = total + config.photometric_weight * terms["photometric"]
    if config.use_depth:
        score_depth = relative_depth_loss if config.depth_loss == "relative" else depth_loss
        terms["depth"] = score_depth(depth_i, depth_j_in_i, mask)
        total = total + config.depth_weight * terms["depth"]
    if config.use_features and data.features is not None:
        feat = data.features
        feat_i, _, warped_feat, _, feat_mask = warp_level(
            feat, batch, log_scales_i, log_scales_j, config.min_sample_validity,
            pixel_lattice(feat.size, config.feature_stride, generator),
        )
        if config.feature_loss == "S":
            terms["feature"] = feature_loss_s(feat_i, warped_feat, feat_mask, config.feature_eps)
        else:
            terms["feature"] = feature_loss_m(feat_i, warped_feat, feat_mask)
        total = total + config.feature_weight * terms["feature"]
    terms["total"] = total
    terms["valid_fraction"] = mask.flatten(1).float().mean(1)
    return terms
