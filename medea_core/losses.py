"""The MEDeA loss terms for a batch of frame pairs (i, j), each a per-pair mean over the
pixels where the reprojection of j into i is valid (the paper's |I_{j->i}|).

Every function takes per-pixel maps (B, C, H, W) or (B, H, W) and a mask (B, H, W) and
returns (B,) per-pair losses.
"""

from __future__ import annotations

import torch


def masked_mean(per_pixel: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of per-pixel values over a mask, per pair.

    Args:
        per_pixel: (B, H, W) values.
        mask: (B, H, W) bool or 0/1 weights.

    Returns:
        (B,) mean over the masked pixels; 0 where the mask is empty.
    """
    mask = mask.to(per_pixel.dtype)
    count = mask.flatten(1).sum(1)
    return (per_pixel * mask).flatten(1).sum(1) / count.clamp(min=1.0)


def photometric_loss(image_i: torch.Tensor, warped_j: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_photo = mean over valid pixels and the channels of |I_i - I_{j->i}|.

    Args:
        image_i: (B, C, H, W) image of view i (RGB in [0, 1]).
        warped_j: (B, C, H, W) image of frame j warped into view i.
        mask: (B, H, W) bool, valid reprojections.

    Returns:
        (B,) per-pair loss.
    """
    return masked_mean((image_i - warped_j).abs().mean(dim=1), mask)


def depth_loss(depth_i: torch.Tensor, depth_j_in_i: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_depth = mean over valid pixels of |D_i - D_{j->i}| (metres).

    Args:
        depth_i: (B, H, W) depth of view i in metres.
        depth_j_in_i: (B, H, W) D_{j->i}, frame j's depth as z in camera i, in metres.
        mask: (B, H, W) bool, valid reprojections.

    Returns:
        (B,) per-pair loss in metres.
    """
    return masked_mean((depth_i - depth_j_in_i).abs(), mask)


def relative_depth_loss(depth_i: torch.Tensor, depth_j_in_i: torch.Tensor, mask: torch.Tensor,
                        eps: float = 1e-6) -> torch.Tensor:
    """L_depth made scale-free: mean over valid pixels of |D_i - D_{j->i}| / (D_i + D_{j->i}).

    The paper's term in metres is smallest for a smaller scene: with the poses fixed it
    pulls every depth towards the cameras. Divided by the two depths' sum it scores the
    same disagreement at any scale (the form of the S feature distance).

    Args:
        depth_i: (B, H, W) depth of view i in metres.
        depth_j_in_i: (B, H, W) D_{j->i}, frame j's depth as z in camera i, in metres.
        mask: (B, H, W) bool, valid reprojections.
        eps: added to the denominator.

    Returns:
        (B,) per-pair loss (a fraction).
    """
    return masked_mean((depth_i - depth_j_in_i).abs() / (depth_i + depth_j_in_i).abs().clamp(min=eps), mask)


def feature_loss_s(feat_i: torch.Tensor, warped_j: torch.Tensor, mask: torch.Tensor, eps: float = 0.01) -> torch.Tensor:
    """MEDeA-S: mean over valid pixels and channels of |Fi - Fj->i| / (|Fi + Fj->i| + eps).

    Args:
        feat_i: (B, C, H, W) features of view i.
        warped_j: (B, C, H, W) features of frame j warped into view i.
        mask: (B, H, W) bool, valid reprojections.
        eps: keeps the ratio smooth where both features are near zero
            (MedeaConfig.feature_eps).

    Returns:
        (B,) per-pair loss.
    """
    ratio = (feat_i - warped_j).abs() / ((feat_i + warped_j).abs() + eps)
    return masked_mean(ratio.mean(dim=1), mask)


def feature_loss_m(feat_i: torch.Tensor, warped_j: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """MEDeA-M: negative mean over valid pixels of the dot product Fi . Fj->i.

    Args:
        feat_i: (B, C, H, W) features of view i.
        warped_j: (B, C, H, W) features of frame j warped into view i.
        mask: (B, H, W) bool, valid reprojections.

    Returns:
        (B,) per-pair loss.
    """
    return -masked_mean((feat_i * warped_j).sum(dim=1), mask)
