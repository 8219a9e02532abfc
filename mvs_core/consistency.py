"""Multi-view geometric consistency: does another view's depth agree with a pixel's?

A pixel p of frame i with depth d is lifted to 3D, projected into source j, and j's depth
there is lifted back and projected into i. The views agree when that round trip returns
within `pixels` of p and at a depth within `rel_depth` of d (the check of COLMAP's and
MVSNet's depth-map fusion). The number of agreeing sources is the pixel's evidence; its
depth can be averaged over them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from medea_core.geometry import pixel_grid

from .sweep import hypothesis_grid


def _lift(uv: torch.Tensor, depth: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Camera points (..., 3) of pixels uv (..., 2) at z-depth (...)."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    return torch.stack([(uv[..., 0] - cx) / fx * depth, (uv[..., 1] - cy) / fy * depth, depth], -1)


def consistent_views(
    depth: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    sources: torch.Tensor,
    rel_depth: float = 0.02,
    pixels: float = 1.0,
    targets: range | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Agreeing sources per pixel and the depth averaged over them.

    Args:
        depth: (N, H, W) depth in metres, 0 = invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) fx, fy, cx, cy in pixels of depth's resolution, shared by all frames.
        sources: (N, S) the views to check each frame against.
        rel_depth: largest |z_back - d| / d of an agreeing source.
        pixels: largest round-trip error in pixels of an agreeing source.
        targets: the frames to check (default all N; T of them).

    Returns:
        count (T, H, W) of agreeing sources (depth's dtype) and mean (T, H, W) in metres:
        the pixel's own depth averaged with the agreeing sources' depths expressed in
        frame i (0 where invalid).
    """
    num, height, width = depth.shape
    poses = poses.double().to(depth.device)
    intr = intrinsics.to(depth.dtype)
    uv_i = pixel_grid(height, width, dtype=depth.dtype, device=depth.device)
    targets = range(num) if targets is None else targets
    count = depth.new_zeros(len(targets), height, width)
    mean = torch.zeros_like(count)
    for row, i in enumerate(targets):
        src = sources[i]
        ref_to_src = torch.linalg.solve(poses[src], poses[i].expand(len(src), 4, 4))
        d_i = depth[i]
        grid, seen = hypothesis_grid(d_i.clamp(min=1e-6), d_i.new_zeros(1), intr, ref_to_src)
        grid, seen = grid[:, 0], seen[:, 0]  # (S, H, W, 2), (S, H, W)
        uv_j = (grid + 1.0) * grid.new_tensor([width / 2.0, height / 2.0]) - 0.5
        d_j = F.grid_sample(depth[src][:, None], grid, mode="nearest", padding_mode="zeros", align_corners=False)[:, 0]
        # j's surface point, back in camera i.
        src_to_ref = torch.linalg.inv(ref_to_src).to(depth.dtype)
        back = _lift(uv_j, d_j, intr) @ src_to_ref[:, None, :3, :3].transpose(-1, -2) + src_to_ref[:, None, None, :3, 3]
        z_back = back[..., 2]
        uv_back = intr[:2] * back[..., :2] / z_back.clamp(min=1e-6)[..., None] + intr[2:]
        error = (uv_back - uv_i).norm(dim=-1)
        agree = (d_i > 0) & (d_j > 0) & seen & (z_back > 1e-3) & (error < pixels) \
            & ((z_back - d_i).abs() < rel_depth * d_i)
        count[row] = agree.sum(0).to(depth.dtype)
        mean[row] = torch.where(d_i > 0, (d_i + (z_back * agree).sum(0)) / (1.0 + count[row]), torch.zeros_like(d_i))
    return count, mean
