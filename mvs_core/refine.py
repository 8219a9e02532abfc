"""The refinement, step by step: views, sweep, consistency, fill.

Each frame gets ``num_sources`` neighbours (:mod:`.views`); each pixel sweeps ``hypotheses``
depths in a log band of +-``band`` around its input depth, scored by patch NCC
(:mod:`.sweep`); it is reconstructed when ``min_consistent`` sources agree, taking their mean
depth and the share that agree as its confidence (:mod:`.consistency`); elsewhere the input
depth stays, moved by its neighbours' corrections (:mod:`.fill`). The output is at the
input depth's resolution: the input times the upsampled correction.
More: docs/depth.md#how-the-refinement-works
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F

from medea_core.frames import resize_depth
from medea_core.geometry import scale_intrinsics

from .config import MvsConfig
from .consistency import consistent_views
from .fill import propagate_log_ratio
from .sweep import patch_statistics, select_winner, sweep_cost
from .views import select_sources


@dataclass
class RefineResult:
    """depth: (N, H, W) refined depth at the input's resolution (0 where the input is 0).
    confidence: (N, H, W) share of sources that agree with the pixel (0: not reconstructed,
        the depth there is the filled input).
    reconstructed: (N, H, W) bool, at least `min_consistent` sources agree.
    sources: (N, S) the views each frame was matched against; source_scores (N, S).
    unsupported: (N,) bool, frames whose reconstructed share is below min_frame_share.
    sparse: (N,) bool, the other frames whose reconstructed share is below
        sparse_frame_share (None: none), whose filled depth near evidence is fused too.
    stats: per-frame summaries (reconstructed share, median |log correction|).
    support: (N, H, W) the Gaussian-weighted share of reconstructed pixels around each
        pixel (fill_sigma): how much evidence its filled depth leans on.
    swept: (N, h, w) the plane sweep's depth at the working resolution (0: no match), what
        a later call over overlapping frames can pass as ``known``.
    With ``known`` depth for the first K frames, every field covers frames K.. only (N - K
    of them); ``sources`` still index the whole input."""

    depth: torch.Tensor
    confidence: torch.Tensor
    reconstructed: torch.Tensor
    sources: torch.Tensor
    source_scores: torch.Tensor
    unsupported: torch.Tensor
    stats: dict = field(default_factory=dict)
    support: torch.Tensor | None = None
    swept: torch.Tensor | None = None
    sparse: torch.Tensor | None = None


def sweep_frames(
    grey: torch.Tensor, depth: torch.Tensor, poses: torch.Tensor, intrinsics: torch.Tensor, sources: torch.Tensor,
    config: MvsConfig, progress: Callable[[int], None] | None = None, frames: range | None = None,
) -> torch.Tensor:
    """Step 2 (the plane sweep) for the frames in ``frames``.

    All inputs are at the working resolution.

    Args:
        grey: (N, h, w) grey images in [0, 1].
        depth: (N, h, w) input depth in metres, 0 = invalid: the band's centre.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) fx, fy, cx, cy in pixels of (h, w).
        sources: (N, S) the views each frame is matched against.
        config: band, hypotheses, patch radius, keep_best, texture floor and max_cost.
        progress: called with 1 after each frame's sweep.
        frames: the frames to sweep (default all N; F of them).

    Returns:
        (F, h, w) multi-view depth in metres, 0 where no hypothesis matched (best cost above
        max_cost, or the winner on the band's edge, or the input invalid).
    """
    offsets = torch.linspace(-config.band, config.band, config.hypotheses, device=grey.device, dtype=grey.dtype)
    poses = poses.double()
    frames = range(depth.shape[0]) if frames is None else frames
    out = depth.new_zeros(len(frames), *depth.shape[1:])
    for row, i in enumerate(frames):
        src = sources[i]
        ref_to_src = torch.linalg.solve(poses[src], poses[i].expand(len(src), 4, 4))
        d_i = depth[i]
        cost = sweep_cost(grey[i], patch_statistics(grey[i], config.radius), d_i.clamp(min=1e-6), grey[src],
                          intrinsics, ref_to_src, offsets, config.radius, config.keep_best, config.texture_floor)
        offset, best, _, at_edge = select_winner(cost, offsets)
        matched = (d_i > 0) & ~at_edge & (best <= config.max_cost)
        out[row] = torch.where(matched, d_i * torch.exp(offset), torch.zeros_like(d_i))
        if progress is not None:
            progress(1)
    return out


def refine_depth(
    grey: torch.Tensor,
    depth: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    config: MvsConfig | None = None,
    progress: Callable[[int], None] | None = None,
    known: torch.Tensor | None = None,
) -> RefineResult:
    """Refine depth maps (N, H, W) by multi-view stereo around them.

    Args:
        grey: (N, h, w) grey images in [0, 1] at the working resolution (config.image_scale
            of the depth's size; resizing is the caller's, so that it happens once, from the
            frames).
        depth: (N, H, W) depth in metres, 0 = invalid (MEDeA's output).
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) fx, fy, cx, cy in pixels of depth's resolution.
        config: options; None: MvsConfig().
        progress: called with 1 after each frame's sweep.
        known: (K, h, w) swept depth of the first K frames from an earlier call (its
            ``RefineResult.swept``; a streamed window's frames shared with the window
            before): they serve as sources as they were matched then, and are neither swept
            nor refined again; the result covers frames K.. only.

    Returns:
        RefineResult with the refined depth (N - K, H, W) in metres at the input's
        resolution, its confidence and the views used. With fewer than 2 frames the depth
        is a copy of the input and nothing is reconstructed.

    Raises:
        ValueError: a setting of config is out of range, or ``known`` covers all N frames
            or is not at the working size (h, w).
    """
    config = config or MvsConfig()
    config.validate()
    device = torch.device(config.device)
    num, height, width = depth.shape
    depth = depth.to(device=device, dtype=torch.float32)
    grey = grey.to(device=device, dtype=torch.float32)
    poses = poses.to(device=device, dtype=torch.float64)
    small_h, small_w = grey.shape[-2:]
    intr = scale_intrinsics(intrinsics.to(device=device, dtype=torch.float32), small_w / width, small_h / height)
    small, _ = resize_depth(depth, (small_h, small_w))
    first = 0 if known is None else len(known)
    if first and (first >= num or tuple(known.shape[1:]) != (small_h, small_w)):
        raise ValueError(f"known swept depth {tuple(known.shape)} must cover fewer than the {num} frames at the "
                         f"working size {(small_h, small_w)}")
    if num < 2:
        zeros = torch.zeros_like(depth)
        empty = torch.zeros(num, 0, dtype=torch.long)
        return RefineResult(depth.clone(), zeros, zeros.bool(), empty, empty.float(), torch.ones(num, dtype=torch.bool))

    sources, scores = select_sources(small, poses, intr, config.num_sources, config.min_angle, config.max_angle,
                                     config.chunk)
    targets = range(first, num)
    swept = sweep_frames(grey, small, poses, intr, sources, config, progress, targets)
    if first:
        swept = torch.cat([known.to(swept), swept])
    count, mean = consistent_views(swept, poses, intr, sources, config.consistency_depth, config.consistency_pixels,
                                   targets)
    depth, small, sources, scores = depth[first:], small[first:], sources[first:], scores[first:]
    reconstructed = (count >= config.min_consistent) & (mean > 0) & (small > 0)
    log_ratio = torch.where(reconstructed, torch.log(mean.clamp(min=1e-6) / small.clamp(min=1e-6)),
                            torch.zeros_like(small))
    spread, support = propagate_log_ratio(log_ratio, reconstructed.float(), config.fill_sigma, config.min_fill_weight)
    correction = torch.where(reconstructed, log_ratio, spread)
    full = F.interpolate(correction[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]
    confidence = torch.where(reconstructed, count / float(config.num_sources), torch.zeros_like(count))
    confidence = F.interpolate(confidence[:, None], size=(height, width), mode="nearest")[:, 0]
    refined = torch.where(depth > 0, depth * torch.exp(full), torch.zeros_like(depth))
    share = reconstructed.flatten(1).float().mean(1)
    moved = torch.where(reconstructed, log_ratio.abs(), torch.full_like(log_ratio, float("nan"))).flatten(1)
    stats = {"reconstructed": share.cpu(), "median_abs_log_correction": moved.nanmedian(1).values.cpu()}
    unsupported = (share < config.min_frame_share).cpu()
    sparse = (share < config.sparse_frame_share).cpu() & ~unsupported
    support = F.interpolate(support[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]
    return RefineResult(refined, confidence, confidence > 0, sources.cpu(), scores.cpu(), unsupported, stats, support,
                        swept[first:], sparse)
