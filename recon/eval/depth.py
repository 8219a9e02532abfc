"""Depth accuracy and multi-view consistency metrics.

Accuracy follows the usual protocol (DeepVideoMVS, used by the MEDeA paper): pixels with
valid ground truth inside the evaluated range; metrics per frame, then averaged over
frames. `align` chooses metric evaluation (no alignment) or per-frame / per-sequence
median scaling (for up-to-scale depth).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch

from medea_core.frames import prepare_frames
from medea_core.geometry import pair_transforms
from medea_core.objective import PairBatch, warp_level
from medea_core.pairs import hierarchical_pairs

METRIC_NAMES = ("abs_diff", "abs_rel", "sq_rel", "rmse", "log_rmse", "delta1", "delta2", "delta3")


def _per_frame(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """Metrics (F,) of each frame from pred, gt (F, P) and mask (F, P)."""
    count = np.maximum(mask.sum(1), 1)
    safe_pred = np.where(mask, pred, 1.0)
    safe_gt = np.where(mask, gt, 1.0)
    diff = np.where(mask, safe_pred - safe_gt, 0.0)
    log_diff = np.where(mask, np.log(np.maximum(safe_pred, 1e-6)) - np.log(safe_gt), 0.0)
    ratio = np.maximum(safe_pred / safe_gt, safe_gt / np.maximum(safe_pred, 1e-6))
    out = {
        "abs_diff": np.abs(diff).sum(1) / count,
        "abs_rel": (np.abs(diff) / safe_gt).sum(1) / count,
        "sq_rel": (diff**2 / safe_gt).sum(1) / count,
        "rmse": np.sqrt((diff**2).sum(1) / count),
        "log_rmse": np.sqrt((log_diff**2).sum(1) / count),
    }
    for k, name in enumerate(("delta1", "delta2", "delta3"), start=1):
        out[name] = ((ratio < 1.25**k) & mask).sum(1) / count
    return out


def depth_metrics(
    pred,
    gt,
    min_depth: float = 1e-3,
    max_depth: float = np.inf,
    align: Literal["none", "median_frame", "median_sequence"] = "none",
) -> dict[str, float]:
    """Depth metrics of pred against gt, both (N, H, W) or (H, W) in metres.

    Pixels count where gt is finite and within [min_depth, max_depth] and pred is finite
    and positive (a missing prediction is scored as an error only through coverage,
    reported as "coverage"). Returns the frame-averaged metrics plus "frames" and
    "coverage" (valid predicted share of valid ground truth) and, when aligned, "scale".
    """
    pred = np.asarray(pred.cpu() if isinstance(pred, torch.Tensor) else pred, dtype=np.float64)
    gt = np.asarray(gt.cpu() if isinstance(gt, torch.Tensor) else gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"depth_metrics: prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    if pred.ndim == 2:
        pred, gt = pred[None], gt[None]
    pred = pred.reshape(pred.shape[0], -1)
    gt = gt.reshape(gt.shape[0], -1)
    gt_valid = np.isfinite(gt) & (gt >= min_depth) & (gt <= max_depth)
    mask = gt_valid & np.isfinite(pred) & (pred > 0)
    scale = 1.0
    if align == "median_frame":
        ratios = [np.median(g[m]) / np.median(p[m]) if m.any() else 1.0 for p, g, m in zip(pred, gt, mask)]
        scale = np.asarray(ratios)[:, None]
    elif align == "median_sequence":
        scale = np.median(gt[mask]) / np.median(pred[mask]) if mask.any() else 1.0
    per_frame = _per_frame(pred * scale, gt, mask)
    keep = mask.any(1)
    out = {name: float(values[keep].mean()) if keep.any() else float("nan") for name, values in per_frame.items()}
    out["frames"] = int(keep.sum())
    out["coverage"] = float(mask.sum() / max(gt_valid.sum(), 1))
    if align != "none":
        out["scale"] = float(np.median(scale))
    return out


def multiview_inconsistency(
    depth: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    levels: tuple[int, int] = (0, 4),
    image_scale: float = 0.25,
    batch_size: int = 128,
) -> float:
    """How much depth maps disagree where frames overlap.

    For every pair (i, j) in Pairs(levels) the depth of frame j is warped into view i
    (the same reprojection MEDeA uses) and compared with frame i's depth; a pair scores
    the median of |D_i - D_{j->i}| / D_i over the pixels both frames see (the median
    ignores the minority of occluded pixels), and the result is the mean over pairs.
    Ground-truth depth scores close to 0.

    Args:
        depth: (N, H, W) metres, 0 where invalid.
        poses: (N, 4, 4) camera-to-world; intrinsics: (4,) or (N, 4) at depth's resolution.
    """
    depth = torch.as_tensor(depth, dtype=torch.float32)
    num, height, width = depth.shape
    pairs = hierarchical_pairs(num, *levels)
    if pairs.numel() == 0:
        return float("nan")
    placeholder = torch.zeros((num, 1, height, width))
    data = prepare_frames(placeholder, depth, torch.as_tensor(poses), torch.as_tensor(intrinsics), None, image_scale,
                          "cpu")
    i_to_j, j_to_i = pair_transforms(data.poses, pairs)
    zeros = torch.zeros((num, 2, 2))
    scores = []
    with torch.no_grad():
        for chunk in torch.arange(pairs.shape[0]).split(batch_size):
            batch = PairBatch(pairs[chunk, 0], pairs[chunk, 1], i_to_j[chunk], j_to_i[chunk])
            _, depth_i, _, depth_j_in_i, mask = warp_level(data.image, batch, zeros[batch.i], zeros[batch.j], 0.999)
            rel = ((depth_i - depth_j_in_i).abs() / depth_i.clamp(min=1e-6)).masked_fill(~mask, float("nan"))
            per_pair = rel.flatten(1).nanmedian(dim=1).values
            scores.append(per_pair[mask.flatten(1).any(1)])
    return float(torch.cat(scores).mean())
