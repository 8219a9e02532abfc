"""The refinement stage of the pipeline: numpy frames and MEDeA's depth in, per-pixel
multi-view depth and its confidence out, with a progress bar. The method lives in
`mvs_core`; this module adapts arrays, resizes the frames once and summarises the result
for report.json.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from medea_core.frames import working_size
from mvs_core import MvsConfig, RefineResult, refine_depth

from ..choices import REFINE_CHOICES

# Filled (not reconstructed) pixels get this times their support, the Gaussian share of
# reconstructed pixels around them: always below a reconstructed pixel's confidence
# (min_consistent / num_sources, 1/3 by default), so one fusion threshold picks the policy.
FILLED_CONFIDENCE = 0.1
# Fusion thresholds: reconstructed pixels only with given poses; with estimated poses also
# the filled pixels with support >= 0.1. why: docs/decisions.md#which-refined-pixels-are-fused
MIN_CONFIDENCE_GIVEN = FILLED_CONFIDENCE
MIN_CONFIDENCE_ESTIMATED = 0.01

# Frames converted to grey and resized per batch (keeps full-size float copies small).
_CHUNK = 32


def grey_at(rgb, size: tuple[int, int], device: str = "cpu") -> torch.Tensor:
    """RGB frames (N, H, W, 3) uint8 -> grey (N, h, w) float32 in [0, 1] at size (h, w),
    antialiased (Rec. 601 luma)."""
    weights = torch.tensor([0.299, 0.587, 0.114], device=device)
    out = []
    for start in range(0, len(rgb), _CHUNK):
        block = torch.as_tensor(np.ascontiguousarray(rgb[start : start + _CHUNK]), device=device).float() / 255.0
        grey = (block @ weights)[:, None]
        if tuple(grey.shape[-2:]) != tuple(size):
            grey = F.interpolate(grey, size=size, mode="bilinear", antialias=True, align_corners=False)
        out.append(grey[:, 0])
    return torch.cat(out)


def refine_sequence(
    rgb, depth, poses, intrinsics, config: MvsConfig | None = None, progress: bool = True,
    known: torch.Tensor | None = None,
) -> RefineResult:
    """Multi-view stereo refinement of a sequence's depth.

    rgb: (N, H', W', 3) uint8 frames (any size with the depth's aspect); depth: (N, H, W)
    metres (MEDeA's output; 0 invalid); poses: (N, 4, 4) camera-to-world; intrinsics:
    (fx, fy, cx, cy) in pixels of the depth; known: swept depth of the first K frames from
    an earlier call, which are then only sources (mvs_core.refine_depth). Returns
    mvs_core.RefineResult (tensors on the CPU).
    """
    config = config or MvsConfig()
    depth_t = torch.as_tensor(np.asarray(depth, np.float32))
    size = working_size(*depth_t.shape[-2:], config.image_scale)
    grey = grey_at(rgb, size, config.device)
    to_sweep = len(depth_t) - (0 if known is None else len(known))
    with tqdm(total=to_sweep, desc="MVS refinement", unit="frame", disable=not progress, leave=False) as bar:
        result = refine_depth(grey, depth_t, torch.as_tensor(np.asarray(poses, np.float64)),
                              torch.as_tensor(intrinsics, dtype=torch.float32), config, progress=bar.update,
                              known=known)
    result.depth, result.confidence = result.depth.cpu(), result.confidence.cpu()
    result.reconstructed = result.reconstructed.cpu()
    if result.support is not None:
        result.support = result.support.cpu()
    if result.swept is not None:
        result.swept = result.swept.cpu()
    return result


def fusion_confidence(result: RefineResult) -> np.ndarray:
    """Per-pixel confidence for TSDF fusion (N, H, W) float32 in [0, 1]: the refinement's
    confidence on reconstructed pixels, FILLED_CONFIDENCE x support on the other valid
    pixels, and 1 on every valid pixel of the frames it could not support (their filled
    depth is fused whole: a scatter of reconstructed pixels would leave those views empty).
    The sparse frames (``RefineResult.sparse``) give FILLED_CONFIDENCE to their filled
    pixels that the estimated-pose threshold fuses (support >= 0.1), so that the given-pose
    threshold fuses them too."""
    confidence = result.confidence.numpy().astype(np.float32, copy=True)
    if result.support is not None:
        filled = ~result.reconstructed.numpy() & (result.depth.numpy() > 0)
        confidence[filled] = FILLED_CONFIDENCE * np.clip(result.support.numpy()[filled], 0.0, 0.999)
        if result.sparse is not None:
            sparse = result.sparse.numpy()[:, None, None] & filled & (confidence >= MIN_CONFIDENCE_ESTIMATED)
            confidence[sparse] = FILLED_CONFIDENCE
    unsupported = result.unsupported.numpy()
    if unsupported.any():
        confidence[unsupported] = (result.depth.numpy()[unsupported] > 0).astype(np.float32)
    return confidence


def default_min_confidence(poses_estimated: bool) -> float:
    """The fusion threshold on fusion_confidence when the user gives none."""
    return MIN_CONFIDENCE_ESTIMATED if poses_estimated else MIN_CONFIDENCE_GIVEN


def default_weight_threshold(poses_estimated: bool, refined: bool) -> float:
    """The frames that must see a voxel for it to be meshed when the user gives none: 1 with
    given poses and the refinement (each fused pixel already agrees with min_consistent
    other views: a second fused frame would drop half of what they confirmed), else 2."""
    return 1.0 if refined and not poses_estimated else 2.0


def refine_summary(result: RefineResult | None) -> dict:
    """What report.json says of the refinement: reconstructed share per frame and overall,
    the typical correction, the frames fused whole (unsupported) and with their fill
    (sparse; fusion_confidence), the source views."""
    if result is None:
        return {}
    share = result.stats.get("reconstructed", torch.zeros(0)).numpy()
    moved = result.stats.get("median_abs_log_correction", torch.zeros(0)).numpy()
    return {
        "reconstructed": float(result.reconstructed.float().mean()),
        "reconstructed_per_frame": [round(float(v), 4) for v in share],
        "median_abs_log_correction": float(np.nanmedian(moved)) if np.isfinite(moved).any() else None,
        "unsupported_frames": np.flatnonzero(result.unsupported.numpy()).tolist(),
        "sparse_frames": [] if result.sparse is None else np.flatnonzero(result.sparse.numpy()).tolist(),
        "sources": result.sources.tolist(),
    }


__all__ = ["FILLED_CONFIDENCE", "REFINE_CHOICES", "default_min_confidence", "fusion_confidence", "grey_at",
           "refine_sequence", "refine_summary"]
