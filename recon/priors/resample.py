"""Bringing per-frame maps to the frame size, the way each kind of map needs.

Measured depth with holes is resized with nearest neighbours (a hole never blends into
its neighbours); dense network output is resized bilinearly.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

# A map whose aspect differs from the frame's by more than this is for some other image
# (a crop, a rotated frame), not a scaled copy.
MAX_ASPECT_CHANGE = 0.02


def check_aspect(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> None:
    """Raise ValueError when the two sizes are not (nearly) the same shape."""
    ratio = (src_hw[1] / src_hw[0]) / (dst_hw[1] / dst_hw[0])
    if abs(ratio - 1.0) > MAX_ASPECT_CHANGE:
        raise ValueError(
            f"depth map is {src_hw[0]}x{src_hw[1]} but the frame is {dst_hw[0]}x{dst_hw[1]} (different aspect ratio)"
        )


def resize_nearest(maps: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """maps (N, h, w) or (h, w) -> (N, H, W) / (H, W), nearest neighbour (pixel centres)."""
    maps = np.asarray(maps)
    if tuple(maps.shape[-2:]) == tuple(size):
        return maps
    check_aspect(maps.shape[-2:], size)
    h, w = maps.shape[-2:]
    rows = np.minimum(((np.arange(size[0]) + 0.5) * h / size[0]).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(size[1]) + 0.5) * w / size[1]).astype(np.int64), w - 1)
    return maps[..., rows[:, None], cols[None, :]]


def resize_bilinear(maps: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """maps (N, h, w) float -> (N, H, W), bilinear (antialiased when shrinking)."""
    if tuple(maps.shape[-2:]) == tuple(size):
        return maps
    shrink = maps.shape[-2] > size[0] or maps.shape[-1] > size[1]
    return F.interpolate(maps[:, None].float(), size=size, mode="bilinear", align_corners=False,
                         antialias=shrink)[:, 0]
