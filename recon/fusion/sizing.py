"""The size of a TSDF volume, chosen from the depth before any voxel is allocated: the voxel
and the depth range from the depth's statistics, and the voxel blocks integration will
allocate, counted in advance so that the voxel grows to fit a memory budget (with a
warning) instead of running out of memory mid-way.
More: docs/fusion.md#the-volume
"""

from __future__ import annotations

import logging
import math
from typing import Sequence

import numpy as np

log = logging.getLogger(__name__)

MIN_VOXEL = 0.005
MAX_VOXEL = 0.05
VOXEL_PER_DEPTH = 1.0 / 200.0
MAX_DEPTH_PERCENTILE = 99.0
MAX_DEPTH_MARGIN = 1.1
STAT_FRAMES = 64  # frames sampled for the depth statistics
STAT_STEP = 4  # pixel lattice step for the depth statistics
BYTES_PER_VOXEL = 20  # tsdf + weight + rgb, float32


def frame_intrinsics(intrinsics, n: int) -> np.ndarray:
    """The intrinsics of each of `n` frames.

    Args:
        intrinsics: (4,) shared or (N, 4) per-frame fx, fy, cx, cy in pixels.
        n: the number of frames N.

    Returns:
        (N, 4) float64 fx, fy, cx, cy per frame.

    Raises:
        ValueError: intrinsics of another shape.
    """
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape == (4,):
        return np.broadcast_to(k, (n, 4))
    if k.shape == (n, 4):
        return k
    raise ValueError(f"intrinsics must be (4,) or ({n}, 4), got {k.shape}")


def depth_sample(depth, frames: Sequence[int], step: int = STAT_STEP, max_frames: int = STAT_FRAMES) -> np.ndarray:
    """Valid depth values from a pixel lattice of up to `max_frames` evenly spaced frames.

    Args:
        depth: (N, H, W) depth in metres (any indexable of (H, W) arrays).
        frames: indices of the frames to sample from.
        step: lattice step in pixels.
        max_frames: the most frames read.

    Returns:
        (M,) finite depth values > 0 in metres.
    """
    frames = np.asarray(frames)
    if len(frames) > max_frames:
        frames = frames[np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
    values = [np.asarray(depth[int(i)])[::step, ::step].ravel() for i in frames]
    v = np.concatenate(values) if values else np.zeros(0, np.float32)
    return v[np.isfinite(v) & (v > 0)]


def auto_max_depth(values: np.ndarray) -> float:
    """The automatic depth limit: 1.1 x the 99th percentile of valid depth values.

    Args:
        values: (M,) valid depth in metres, M >= 1.

    Returns:
        The limit in metres.
    """
    return float(MAX_DEPTH_MARGIN * np.percentile(values, MAX_DEPTH_PERCENTILE))


def auto_voxel_size(median_depth: float, metric: bool = True, per_depth: float = VOXEL_PER_DEPTH) -> float:
    """The automatic voxel size: clamp(median depth x per_depth, 5 mm, 5 cm).

    Args:
        median_depth: median valid depth in metres.
        metric: the depth's metres are to be trusted; False drops the bounds.
        per_depth: the voxel as a share of the median depth (default 1/200).

    Returns:
        The voxel size in metres.
    """
    voxel = median_depth * per_depth
    return float(np.clip(voxel, MIN_VOXEL, MAX_VOXEL) if metric else voxel)


def _pack(blocks: np.ndarray) -> np.ndarray:
    """(M, 3) int64 block coordinates -> (M,) int64 keys (21 bits per axis)."""
    b = blocks + (1 << 20)
    return (b[:, 0] << 42) | (b[:, 1] << 21) | b[:, 2]


def estimate_block_count(
    depth,
    poses: np.ndarray,
    intrinsics,
    voxel_size: float,
    trunc: float,
    max_depth: float,
    block_resolution: int = 8,
    frames: Sequence[int] | None = None,
) -> int:
    """Number of voxel blocks integration will allocate, predicted from the depth maps.

    Each frame's pixels on a lattice finer than half a block's footprint at `max_depth`
    are lifted to world points at depth d - trunc, d and d + trunc along their rays (the
    band TSDF integration touches); the distinct blocks of all those points are counted.

    Args:
        depth: (N, H, W) depth in metres, 0 = invalid (any indexable of (H, W) arrays).
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) or (N, 4) fx, fy, cx, cy in pixels of the depth maps.
        voxel_size: voxel side in metres.
        trunc: truncation distance in metres.
        max_depth: depth beyond it (metres) is ignored.
        block_resolution: voxels per block side.
        frames: which frames (default all).

    Returns:
        The predicted number of blocks.
    """
    n = len(poses)
    frames = range(n) if frames is None else frames
    k_all = frame_intrinsics(intrinsics, n)
    block = voxel_size * block_resolution
    unique = np.zeros(0, np.int64)
    chunk: list[np.ndarray] = []
    grids: dict[tuple, tuple] = {}
    offsets = np.array([-trunc, 0.0, trunc])

    def flush():
        nonlocal unique, chunk
        if chunk:
            unique = np.union1d(unique, np.unique(np.concatenate(chunk)))
            chunk = []

    for i in frames:
        d_full = np.asarray(depth[int(i)])
        fx, fy, cx, cy = k_all[int(i)]
        # Block footprint in pixels at the far limit; sampling at half of it misses few blocks.
        step = int(np.clip(min(fx, fy) * block / max_depth / 2.0, 1, 16))
        h, w = d_full.shape
        key = (h, w, step, fx, fy, cx, cy)
        if key not in grids:
            v, u = np.mgrid[0:h:step, 0:w:step]
            grids[key] = ((u.ravel() - cx) / fx, (v.ravel() - cy) / fy)
        rx, ry = grids[key]
        d = d_full[::step, ::step].ravel().astype(np.float64)
        ok = np.isfinite(d) & (d > 0) & (d <= max_depth)
        if not ok.any():
            continue
        d = d[ok]
        z = np.maximum(d[None, :] + offsets[:, None], 1e-3).ravel()  # (3 * M,)
        cam = np.stack([np.tile(rx[ok], 3) * z, np.tile(ry[ok], 3) * z, z], axis=1)
        pose = poses[int(i)]
        world = cam @ pose[:3, :3].T + pose[:3, 3]
        chunk.append(_pack(np.floor(world / block).astype(np.int64)))
        if sum(len(c) for c in chunk) > 2_000_000:
            flush()
    flush()
    return int(len(unique))


def fit_to_budget(
    depth, poses, intrinsics, voxel_size: float, trunc: float, max_depth: float, block_resolution: int, budget: int,
    frames,
) -> tuple[float, float, int]:
    """Grow the voxel (and truncation) until the block estimate fits `budget`.

    Each try scales both by 1.05 sqrt(estimate / budget), with a warning; at most 8 tries.

    Args:
        depth: (N, H, W) depth in metres, 0 = invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) or (N, 4) fx, fy, cx, cy in pixels of the depth maps.
        voxel_size: starting voxel side in metres.
        trunc: starting truncation distance in metres.
        max_depth: depth limit in metres.
        block_resolution: voxels per block side.
        budget: the most blocks allowed.
        frames: which frames count.

    Returns:
        (voxel_size, trunc, estimated blocks), sizes in metres.
    """
    estimate = estimate_block_count(depth, poses, intrinsics, voxel_size, trunc, max_depth, block_resolution, frames)
    for _ in range(8):
        if estimate <= budget:
            break
        factor = math.sqrt(estimate / budget) * 1.05
        log.warning(
            "TSDF fusion: about %d voxel blocks needed at voxel %.1f mm, over the budget of %d "
            "(block_count option); using voxel %.1f mm instead",
            estimate, voxel_size * 1e3, budget, voxel_size * factor * 1e3,
        )
        voxel_size, trunc = voxel_size * factor, trunc * factor
        estimate = estimate_block_count(depth, poses, intrinsics, voxel_size, trunc, max_depth, block_resolution,
                                        frames)
    return voxel_size, trunc, estimate
