"""Depth-scale propagation from keyframes to the other frames (paper, "Depth Scale
Propagation"): l_i := log(MedianPool(D_{j->i} / D0_i, h, w)) with j the temporally
nearest keyframe of frame i.
"""

from __future__ import annotations

import torch

from .frames import FrameData
from .geometry import pair_transforms
from .grid import median_pool_to_grid
from .objective import PairBatch, warp_level


def propagate_scales(
    data: FrameData,
    log_scales: torch.Tensor,
    targets: torch.Tensor,
    sources: torch.Tensor,
    batch_size: int = 128,
    min_validity: float = 0.999,
) -> torch.Tensor:
    """Initial log-scale grids of `targets` from the adjusted depth of `sources`.

    The reprojection uses the target's prior depth (its scale is still 1). A target that
    sees nothing of its source keeps the source's median log scale, so at least the
    global scale correction carries over.

    Args:
        data: frames at working resolution.
        log_scales: (N, h, w) current grids (sources already optimised).
        targets: (T,) frame indices to initialise.
        sources: (T,) frame indices; sources[k] is the keyframe of targets[k].
        batch_size: pairs warped at once.
        min_validity: smallest bilinearly sampled validity of the source's prior for a
            pixel to count.

    Returns:
        (T, h, w) log-scale grids for the targets: log of the median, per grid vertex, of
        D_{source->target} / D0_target.
    """
    grid = tuple(log_scales.shape[-2:])
    pairs = torch.stack([targets, sources], dim=1).to(log_scales.device)
    i_to_j, j_to_i = pair_transforms(data.poses, pairs)
    out = []
    for chunk in torch.arange(pairs.shape[0], device=pairs.device).split(batch_size):
        batch = PairBatch(pairs[chunk, 0], pairs[chunk, 1], i_to_j[chunk], j_to_i[chunk])
        _, depth_i, _, depth_j_in_i, mask = warp_level(
            data.image, batch, torch.zeros_like(log_scales[batch.i]), log_scales[batch.j], min_validity
        )
        mask = mask & (depth_j_in_i > 0)
        ratio = depth_j_in_i / depth_i.clamp(min=1e-6)
        pooled = median_pool_to_grid(ratio, mask, grid).log()
        fallback = log_scales[batch.j].flatten(1).median(dim=1).values
        out.append(torch.where(torch.isnan(pooled), fallback[:, None, None], pooled))
    return torch.cat(out) if out else log_scales.new_zeros((0, *grid))
