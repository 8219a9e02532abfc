"""Rolling shutter: frames whose rows were exposed one after another, resampled to one instant.

Rotation-only, after Forssén and Ringaby ("Rectifying rolling shutter video from hand-held
devices", CVPR 2010): row v of a frame H rows high is exposed ``t_v = (v / H - 1/2) * readout``
after the frame's timestamp, turned by ``exp([w] t_v)``, w the body angular velocity (rad/s)
taken from the poses by central differences; translation during the readout is ignored.
Off unless the readout is given. Shapes: N frames of (H, W); poses (N, 4, 4)
camera-to-world, OpenCV axes.
More: docs/input.md#rolling-shutter
why: docs/decisions.md#rolling-shutter
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from recon.geometry import lie
from recon.geometry import projective as pj

# Frames that the unrolling moves by less than this (pixels, anywhere) are left as they
# are: resampling would blur them more than the shutter bends them.
MIN_SHIFT_PX = 0.5


def angular_velocity(poses: np.ndarray, timestamps: np.ndarray) -> np.ndarray:
    """Body angular velocity of every frame, from its poses and timestamps.

    The turn from the previous to the next frame over their time apart (one-sided at the
    ends). Frames without a finite pose, or whose neighbours share their timestamp, get 0.

    Args:
        poses: (N, 4, 4) camera-to-world poses.
        timestamps: (N,) seconds.

    Returns:
        (N, 3) float64 angular velocity in rad/s, in each camera's axes.
    """
    poses = np.asarray(poses, np.float64)
    stamps = np.asarray(timestamps, np.float64)
    count = len(poses)
    omega = np.zeros((count, 3))
    if count < 2:
        return omega
    prev = np.maximum(np.arange(count) - 1, 0)
    nxt = np.minimum(np.arange(count) + 1, count - 1)
    rel = np.einsum("nji,njk->nik", poses[prev, :3, :3], poses[nxt, :3, :3])  # R_prev^T R_next
    turn = lie.so3_log(torch.from_numpy(np.nan_to_num(rel))).numpy()
    gap = stamps[nxt] - stamps[prev]
    ok = np.isfinite(poses[prev]).all(axis=(1, 2)) & np.isfinite(poses[nxt]).all(axis=(1, 2)) & (gap > 0)
    omega[ok] = turn[ok] / gap[ok, None]
    return omega


def recorded_position(omega: np.ndarray, intrinsics, shape: tuple[int, int], readout: float) -> np.ndarray:
    """For every pixel of a frame at its timestamp, where the rolling shutter recorded it.

    Args:
        omega: (3,) body angular velocity in rad/s.
        intrinsics: (fx, fy, cx, cy) in pixels of frames of `shape`.
        shape: (H, W) of the frames.
        readout: time in seconds from the first row to the last.

    Returns:
        (H, W, 2) float32 recorded pixel coordinates (u, v).
    """
    height, width = shape
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    grid = pj.pixel_grid(height, width)  # (H, W, 2) float64
    rays = torch.stack([(grid[..., 0] - cx) / fx, (grid[..., 1] - cy) / fy, torch.ones_like(grid[..., 0])], -1)
    t_row = (torch.arange(height, dtype=torch.float64) / height - 0.5) * readout  # (H,)
    turn = lie.so3_exp(-t_row[:, None] * torch.as_tensor(np.asarray(omega, np.float64)))  # (H, 3, 3)
    seen = torch.einsum("hij,hwj->hwi", turn, rays)
    out = torch.stack([fx * seen[..., 0] / seen[..., 2] + cx, fy * seen[..., 1] / seen[..., 2] + cy], -1)
    return out.float().numpy()


def recorded_positions(omega: np.ndarray, intrinsics, shape: tuple[int, int], readout: float) -> np.ndarray:
    """:func:`recorded_position` of N frames.

    Args:
        omega: (N, 3) body angular velocities in rad/s.
        intrinsics: (fx, fy, cx, cy) in pixels of frames of `shape`.
        shape: (H, W) of the frames.
        readout: time in seconds from the first row to the last.

    Returns:
        (N, H, W, 2) float32 recorded pixel coordinates.
    """
    return np.stack([recorded_position(w, intrinsics, shape, readout) for w in np.asarray(omega)])


def largest_shift(positions: np.ndarray) -> np.ndarray:
    """The largest distance between a pixel and where it was recorded, per frame.

    Args:
        positions: (N, H, W, 2) from :func:`recorded_positions`.

    Returns:
        (N,) largest shift in pixels.
    """
    height, width = positions.shape[1:3]
    grid = pj.pixel_grid(height, width).numpy()
    return np.linalg.norm(positions - grid, axis=-1).reshape(len(positions), -1).max(axis=1)


def unroll_images(images: np.ndarray, positions: np.ndarray, nearest: bool = False) -> np.ndarray:
    """Frames resampled to their timestamps.

    Colour takes the nearest recorded pixel at the border (no black margin for the flow to
    match); depth (nearest=True, no interpolation across edges) is 0 where the recording
    has no pixel.

    Args:
        images: (N, H, W) or (N, H, W, C) frames as recorded.
        positions: (N, H, W, 2) float32 from :func:`recorded_positions`.
        nearest: nearest-neighbour sampling and zeros outside (for depth).

    Returns:
        (N, H, W[, C]) frames, the input's dtype.
    """
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    border = dict(borderMode=cv2.BORDER_CONSTANT, borderValue=0) if nearest else dict(borderMode=cv2.BORDER_REPLICATE)
    return np.stack([cv2.remap(im, pos[..., 0], pos[..., 1], mode, **border) for im, pos in zip(images, positions)])


def roll_images(images: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """The inverse of :func:`unroll_images` to first order: what a rolling shutter records.

    Recorded pixel q shows the instant's image at ``2 q - positions[q]``. For simulating
    rolling-shutter video in tests.

    Args:
        images: (N, H, W) or (N, H, W, C) frames taken at one instant.
        positions: (N, H, W, 2) float32 from :func:`recorded_positions`.

    Returns:
        (N, H, W[, C]) recorded frames, the input's dtype.
    """
    height, width = positions.shape[1:3]
    grid = pj.pixel_grid(height, width).numpy().astype(np.float32)
    back = 2 * grid[None] - positions
    return np.stack([cv2.remap(im, pos[..., 0], pos[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                     for im, pos in zip(images, back)])


def unroll_features(features: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Feature maps covering the frames, resampled like the frames (bilinear).

    Args:
        features: (N, C, h, w) feature maps covering the whole frame.
        positions: (N, H, W, 2) from :func:`recorded_positions` at the frames' size.

    Returns:
        (N, C, h, w) feature maps, the input's dtype.
    """
    h, w = features.shape[2:]
    height, width = positions.shape[1:3]
    pos = torch.from_numpy(positions).permute(0, 3, 1, 2)
    small = F.interpolate(pos, size=(h, w), mode="bilinear", align_corners=True).permute(0, 2, 3, 1)
    # Frame pixels to grid_sample's [-1, 1]: pixel centres at integers in both the frame and
    # the feature map (align_corners), so the frame's corners are the map's.
    grid = small / torch.tensor([max(width - 1, 1), max(height - 1, 1)]) * 2 - 1
    out = F.grid_sample(torch.from_numpy(features).float(), grid.float(), mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.numpy().astype(features.dtype, copy=False)


__all__ = ["MIN_SHIFT_PX", "angular_velocity", "largest_shift", "recorded_position", "recorded_positions",
           "roll_images", "unroll_features", "unroll_images"]
