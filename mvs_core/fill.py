"""Spreading the refinement into pixels the images could not match.

Where the plane sweep found no trustworthy match (flat walls, dark corners, occlusions),
the input depth is kept, corrected by the confidence-weighted local average of the
correction ``log(refined / input)`` of its confident neighbours (normalised convolution,
Knutsson and Westin 1993): the input's shape, moved to where the surrounding evidence put
the surface. Far from any evidence the weight vanishes and the input depth stays as it is.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def gaussian_blur(maps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur with replicated borders.

    Args:
        maps: (N, H, W) maps to blur.
        sigma: Gaussian standard deviation in pixels; the kernel reaches
            max(1, round(3 sigma)) pixels either side.

    Returns:
        (N, H, W) blurred maps.
    """
    radius = max(1, int(round(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=maps.dtype, device=maps.device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    out = F.conv2d(F.pad(maps[:, None], (radius, radius, 0, 0), mode="replicate"), kernel.view(1, 1, 1, -1))
    out = F.conv2d(F.pad(out, (0, 0, radius, radius), mode="replicate"), kernel.view(1, 1, -1, 1))
    return out[:, 0]


def propagate_log_ratio(
    log_ratio: torch.Tensor, weight: torch.Tensor, sigma: float, min_weight: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Confidence-weighted spread of a correction field.

    Args:
        log_ratio: (N, H, W) log(refined / input) where known.
        weight: (N, H, W) confidence in [0, 1], 0 where unknown.
        sigma: Gaussian sigma in pixels.
        min_weight: smallest local weight at which the spread field is kept.

    Returns:
        The spread field (N, H, W) (0 where the local weight is below min_weight) and the
        local weight (N, H, W), the Gaussian-weighted share of confident pixels around each
        pixel.
    """
    support = gaussian_blur(weight, sigma)
    spread = gaussian_blur(log_ratio * weight, sigma) / support.clamp(min=1e-6)
    return torch.where(support >= min_weight, spread, torch.zeros_like(spread)), support
