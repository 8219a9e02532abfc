"""Pinhole geometry over batched tensors: intrinsics, back-projection, projection, and
the reprojection of frame j into view i that every MEDeA loss is built on.

Conventions: camera-to-world 4x4 poses, OpenCV camera axes (x right, y down, z forward),
z-depth in metres, intrinsics (fx, fy, cx, cy) in pixels with pixel centres at integer
coordinates (pixel (0, 0) covers [-0.5, 0.5]^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


def intrinsics_matrix(intrinsics: torch.Tensor) -> torch.Tensor:
    """Build the 3x3 camera matrix K from fx, fy, cx, cy.

    Args:
        intrinsics: (..., 4) fx, fy, cx, cy in pixels.

    Returns:
        (..., 3, 3) K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    rows = [fx, zero, cx, zero, fy, cy, zero, zero, one]
    return torch.stack(rows, dim=-1).reshape(*intrinsics.shape[:-1], 3, 3)


def scale_intrinsics(intrinsics: torch.Tensor, sx: float, sy: float) -> torch.Tensor:
    """Intrinsics of an image resized by (sx, sy), keeping pixel centres aligned.

    Args:
        intrinsics: (..., 4) fx, fy, cx, cy in pixels of the original image.
        sx: new width / old width.
        sy: new height / old height.

    Returns:
        (..., 4) fx, fy, cx, cy in pixels of the resized image.
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    return torch.stack([fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5], dim=-1)


def pixel_grid(height: int, width: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Pixel-centre coordinates (u, v) of an image of `height` x `width` pixels.

    Args:
        height: image height H in pixels.
        width: image width W in pixels.
        dtype: dtype of the result.
        device: device of the result; None: the default device.

    Returns:
        (H, W, 2) whose entry [v, u] is (u, v): u the column, v the row index.
    """
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def camera_rays(intrinsics: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Rays with unit z through every pixel centre.

    Args:
        intrinsics: (B, 4) fx, fy, cx, cy in pixels.
        height: image height H in pixels.
        width: image width W in pixels.

    Returns:
        (B, H, W, 3) ray directions (x, y, 1) in OpenCV camera axes; multiplying by a
        z-depth gives the camera-frame point.
    """
    uv = pixel_grid(height, width, dtype=intrinsics.dtype, device=intrinsics.device)
    fx, fy, cx, cy = (x[:, None, None] for x in intrinsics.unbind(-1))
    x = (uv[..., 0] - cx) / fx
    y = (uv[..., 1] - cy) / fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a rigid transform to a batch of point sets.

    Args:
        transform: (B, 4, 4) rigid transforms.
        points: (B, ..., 3) points.

    Returns:
        (B, ..., 3) transformed points R p + t.
    """
    batch = points.shape[0]
    flat = points.reshape(batch, -1, 3)
    out = flat @ transform[:, :3, :3].transpose(1, 2) + transform[:, None, :3, 3]
    return out.reshape(points.shape)


def relative_pose(pose_from: torch.Tensor, pose_to: torch.Tensor) -> torch.Tensor:
    """The transform taking camera `from` coordinates to camera `to` coordinates.

    Args:
        pose_from: (B, 4, 4) camera-to-world pose of camera `from`.
        pose_to: (B, 4, 4) camera-to-world pose of camera `to`.

    Returns:
        (B, 4, 4) inv(pose_to) @ pose_from.
    """
    return torch.linalg.solve(pose_to, pose_from)


def project(points: torch.Tensor, intrinsics: torch.Tensor, eps: float = 1e-6):
    """Project camera-frame points with intrinsics.

    Args:
        points: (B, H, W, 3) points in OpenCV camera axes.
        intrinsics: (B, 4) fx, fy, cx, cy in pixels.
        eps: smallest z used in the division.

    Returns:
        uv (B, H, W, 2) pixel coordinates and z (B, H, W). Points with z <= eps get
        uv computed with a clamped z and must be masked by the caller using z.
    """
    fx, fy, cx, cy = (x[:, None, None] for x in intrinsics.unbind(-1))
    z = points[..., 2]
    safe_z = z.clamp(min=eps)
    u = fx * points[..., 0] / safe_z + cx
    v = fy * points[..., 1] / safe_z + cy
    return torch.stack([u, v], dim=-1), z


def pixels_to_normalized(uv: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Convert pixel coordinates to grid_sample coordinates (align_corners=False).

    Args:
        uv: (..., 2) pixel coordinates (u, v), pixel centres at integers.
        height: height H of the sampled image in pixels.
        width: width W of the sampled image in pixels.

    Returns:
        (..., 2) coordinates in [-1, 1] over the image's outer edges.
    """
    scale = uv.new_tensor([2.0 / width, 2.0 / height])
    return (uv + 0.5) * scale - 1.0


def sample(maps: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample maps at pixel coordinates.

    Args:
        maps: (B, C, H, W) maps to sample.
        uv: (B, H', W', 2) pixel coordinates (u, v) in the maps.

    Returns:
        (B, C, H', W'); outside the image the result is 0 (zero padding).
    """
    grid = pixels_to_normalized(uv, maps.shape[-2], maps.shape[-1])
    return F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def inside_image(uv: torch.Tensor, height: int, width: int, tolerance: float = 1e-3) -> torch.Tensor:
    """Whether the bilinear footprint of each coordinate lies inside the image.

    The tolerance keeps border pixels that round-off moves a hair outside.

    Args:
        uv: (B, H', W', 2) pixel coordinates (u, v).
        height: image height H in pixels.
        width: image width W in pixels.
        tolerance: pixels allowed outside [0, W - 1] x [0, H - 1].

    Returns:
        (B, H', W') bool.
    """
    u, v = uv[..., 0], uv[..., 1]
    lo = -tolerance
    return (u >= lo) & (u <= width - 1 + tolerance) & (v >= lo) & (v <= height - 1 + tolerance)


@dataclass
class Reprojection:
    """Where the pixels of view i land in view j.

    uv_j: (B, H, W, 2) pixel coordinates in frame j.
    valid: (B, H, W) bool: positive depth in i, in front of j, inside j.
    """

    uv_j: torch.Tensor
    valid: torch.Tensor


def pair_transforms(poses: torch.Tensor, pairs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-i-to-camera-j and camera-j-to-camera-i transforms for pairs of frames.

    Computed in float64 so that large world coordinates do not cost precision, and
    returned as float32.

    Args:
        poses: (N, 4, 4) camera-to-world poses.
        pairs: (P, 2) frame indices (i, j).

    Returns:
        i_to_j (P, 4, 4) and j_to_i (P, 4, 4), float32.
    """
    world = poses.double()
    pose_i, pose_j = world[pairs[:, 0]], world[pairs[:, 1]]
    i_to_j = relative_pose(pose_i, pose_j)
    j_to_i = relative_pose(pose_j, pose_i)
    return i_to_j.float(), j_to_i.float()


def _pixel_homography(intrinsics_i: torch.Tensor, intrinsics_j: torch.Tensor, i_to_j: torch.Tensor):
    """M = K_j R K_i^-1 (B, 3, 3) and b = K_j t (B, 3): pixel (u, v) of view i at depth d
    lands at the homogeneous pixel d * M [u, v, 1] + b of view j."""
    k_i, k_j = intrinsics_matrix(intrinsics_i), intrinsics_matrix(intrinsics_j)
    m = k_j @ i_to_j[:, :3, :3] @ torch.linalg.inv(k_i)
    b = (k_j @ i_to_j[:, :3, 3:])[..., 0]
    return m, b


def reproject(
    depth_i: torch.Tensor,
    intrinsics_i: torch.Tensor,
    intrinsics_j: torch.Tensor,
    i_to_j: torch.Tensor,
    size_j: tuple[int, int],
    pixels_i: torch.Tensor | None = None,
) -> Reprojection:
    """Reproject every pixel of view i (with its depth) into view j.

    Written as per-pixel multiply-adds with per-pair scalars rather than batched 3x3
    matrix products: the gradient flows only through depth_i, and this is the hot path
    of the optimisation.

    Args:
        depth_i: (B, H, W) z-depth of view i in metres (<= 0 is invalid).
        intrinsics_i: (B, 4) fx, fy, cx, cy in pixels of depth_i's resolution.
        intrinsics_j: (B, 4) fx, fy, cx, cy in pixels of frame j's maps (size_j).
        i_to_j: (B, 4, 4) camera-i to camera-j transform (see pair_transforms).
        size_j: (H_j, W_j) of the maps that will be sampled in frame j.
        pixels_i: (H, W, 2) pixel coordinates of depth_i's samples in view i; default
            every pixel centre.

    Returns:
        Reprojection with uv_j (B, H, W, 2) pixel coordinates in frame j and valid
        (B, H, W) bool: positive depth in i, z > 1e-3 in j, inside frame j.
    """
    height, width = depth_i.shape[-2:]
    m, b = _pixel_homography(intrinsics_i, intrinsics_j, i_to_j)
    if pixels_i is None:
        pixels_i = pixel_grid(height, width, dtype=depth_i.dtype, device=depth_i.device)
    u, v = pixels_i[..., 0], pixels_i[..., 1]
    m = m[..., None, None]
    direction = m[:, :, 0] * u + m[:, :, 1] * v + m[:, :, 2]  # (B, 3, H, W), no gradient
    homogeneous = depth_i[:, None] * direction + b[:, :, None, None]
    z_j = homogeneous[:, 2]
    uv_j = (homogeneous[:, :2] / z_j.clamp(min=1e-6)[:, None]).permute(0, 2, 3, 1)
    valid = (depth_i > 0) & (z_j > 1e-3) & inside_image(uv_j, *size_j)
    return Reprojection(uv_j=uv_j, valid=valid)


def depth_in_view_i(
    sampled_depth_j: torch.Tensor,
    uv_j: torch.Tensor,
    intrinsics_j: torch.Tensor,
    j_to_i: torch.Tensor,
) -> torch.Tensor:
    """The pseudo depth D_{j->i}: z, in camera i, of frame j's surface point seen at uv_j.

    Args:
        sampled_depth_j: (B, H, W) D_j in metres sampled at uv_j.
        uv_j: (B, H, W, 2) pixel coordinates in frame j.
        intrinsics_j: (B, 4) fx, fy, cx, cy in pixels of frame j's maps.
        j_to_i: (B, 4, 4) camera-j to camera-i transform.

    Returns:
        (B, H, W) depth along camera i's z axis, in metres.
    """
    # Only the z row of j_to_i is needed: z_i = r3 . (D_j K_j^-1 [u, v, 1]) + t3.
    c = (j_to_i[:, 2:3, :3] @ torch.linalg.inv(intrinsics_matrix(intrinsics_j)))[:, 0, :, None, None]
    t3 = j_to_i[:, 2, 3, None, None]
    return sampled_depth_j * (c[:, 0] * uv_j[..., 0] + c[:, 1] * uv_j[..., 1] + c[:, 2]) + t3
