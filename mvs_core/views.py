"""Which neighbours each frame is matched against: view selection by triangulation angle
and overlap, in the spirit of COLMAP's and ACMM's source-image scores.

A good source sees much of the reference frame's surface (overlap) from a direction that
differs enough to triangulate (angle), but not so much that patches change appearance.
Both are measured on the reference frame's current depth, on a coarse pixel lattice.
"""

from __future__ import annotations

import torch

# Pixels per lattice row used to measure overlap and angles (16 x 12 for 4:3 frames).
LATTICE = 16


def lattice_points(depth: torch.Tensor, intrinsics: torch.Tensor, poses: torch.Tensor, lattice: int = LATTICE):
    """World points of a coarse pixel lattice of every frame.

    Args:
        depth: (N, H, W) depth in metres, 0 = invalid.
        intrinsics: (4,) fx, fy, cx, cy in pixels of depth's resolution.
        poses: (N, 4, 4) camera-to-world, float64.
        lattice: lattice columns; rows follow the aspect ratio (at least 2).

    Returns:
        World points (N, M, 3) float64 and validity (N, M) bool (depth > 0).
    """
    num, height, width = depth.shape
    rows = torch.linspace(0, height - 1, max(2, lattice * height // max(width, 1)), device=depth.device).round().long()
    cols = torch.linspace(0, width - 1, lattice, device=depth.device).round().long()
    d = depth[:, rows][:, :, cols].double()  # (N, ly, lx)
    fx, fy, cx, cy = intrinsics.double().tolist()
    v, u = torch.meshgrid(rows.double(), cols.double(), indexing="ij")
    rays = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)  # (ly, lx, 3)
    world = (rays[None] * d[..., None]) @ poses[:, None, :3, :3].transpose(-1, -2) + poses[:, None, None, :3, 3]
    return world.reshape(num, -1, 3), (d > 0).reshape(num, -1)


def view_scores(
    points: torch.Tensor,
    valid: torch.Tensor,
    ref_centres: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    size: tuple[int, int],
    min_angle: float,
    max_angle: float,
) -> torch.Tensor:
    """Scores in [0, 1] of every frame as a source for R reference frames.

    A point scores 1 when it projects inside the source, in front of it, and its rays from
    the two centres meet at an angle in [min_angle, max_angle] degrees; less outside
    (linearly below, as (max / angle)^2 above). A frame's score is the mean over the
    reference's valid points.

    Args:
        points: (R, M, 3) world points of the references' lattices.
        valid: (R, M) bool validity of those points.
        ref_centres: (R, 3) the references' camera centres.
        poses: (N, 4, 4) camera-to-world of all frames.
        intrinsics: (4,) fx, fy, cx, cy in pixels of images of `size`.
        size: (H, W) of the images the intrinsics belong to.
        min_angle: smallest full-score triangulation angle in degrees.
        max_angle: largest full-score triangulation angle in degrees.

    Returns:
        (R, N) float64 scores.
    """
    height, width = size
    fx, fy, cx, cy = intrinsics.double().tolist()
    world_to_cam = torch.linalg.inv(poses)
    cam = torch.einsum("jab,rmb->rjma", world_to_cam[:, :3, :3], points) + world_to_cam[None, :, None, :3, 3]
    z = cam[..., 2]
    safe = z.clamp(min=1e-6)
    u, v = fx * cam[..., 0] / safe + cx, fy * cam[..., 1] / safe + cy
    inside = (z > 1e-3) & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1) & valid[:, None]
    ray_ref = points - ref_centres[:, None]  # (R, M, 3)
    ray_src = points[:, None] - poses[None, :, None, :3, 3]  # (R, N, M, 3)
    cos = (ray_ref[:, None] * ray_src).sum(-1) / (ray_ref.norm(dim=-1)[:, None] * ray_src.norm(dim=-1)).clamp(min=1e-12)
    angle = torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
    weight = torch.where(angle < min_angle, angle / max(min_angle, 1e-9),
                         torch.where(angle > max_angle, (max_angle / angle.clamp(min=1e-9)) ** 2,
                                     torch.ones_like(angle)))
    return (weight * inside).sum(-1) / valid.sum(-1, keepdim=True).clamp(min=1)


def select_sources(
    depth: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    num_sources: int,
    min_angle: float = 3.0,
    max_angle: float = 20.0,
    chunk: int = 16,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The best `num_sources` neighbours of every frame.

    A frame is never its own source; with fewer than S + 1 frames the missing slots repeat
    the best source (its score is kept, so callers can see it).

    Args:
        depth: (N, H, W) depth in metres, 0 = invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) fx, fy, cx, cy in pixels of depth's resolution.
        num_sources: S, sources per frame.
        min_angle: smallest full-score triangulation angle in degrees.
        max_angle: largest full-score triangulation angle in degrees.
        chunk: reference frames scored at once.

    Returns:
        indices (N, S) int64 and scores (N, S) float32 in [0, 1], best first.
    """
    num = depth.shape[0]
    poses = poses.double().to(depth.device)
    points, valid = lattice_points(depth, intrinsics, poses)
    centres = poses[:, :3, 3]
    scores = torch.empty(num, num, dtype=torch.float64, device=depth.device)
    for start in range(0, num, chunk):
        sl = slice(start, min(start + chunk, num))
        scores[sl] = view_scores(points[sl], valid[sl], centres[sl], poses, intrinsics, tuple(depth.shape[-2:]),
                                 min_angle, max_angle)
    scores.fill_diagonal_(-1.0)
    k = min(num_sources, num - 1)
    top = scores.topk(k, dim=1)
    index, value = top.indices, top.values
    if k < num_sources:
        pad = num_sources - k
        index = torch.cat([index, index[:, :1].expand(-1, pad)], 1)
        value = torch.cat([value, value[:, :1].expand(-1, pad)], 1)
    return index, value.float()
