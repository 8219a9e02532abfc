"""Resampling recorded frames into the pinhole image of a lens with radial distortion.

The front end estimates the lens' radial term k1 (``recon.geometry.projective.undistort``:
a normalised pinhole point x is recorded at ``x (1 + k1 |x|^2)``) and its poses describe
the pinhole camera with the same intrinsics. Everything after it (MEDeA, fusion) assumes
a pinhole camera, so the frames, the prior depth and the prior's features are resampled
once: pinhole pixel p takes the recorded value at ``distort(p)``. Pixels whose source
falls outside the recorded image become 0 (invalid depth, black colour).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from recon.geometry import projective as pj

# A lens that moves no pixel of the frame by this much is left alone: resampling would
# blur the frames more than the lens distorts them (an estimate on a pinhole camera lands
# at |k1| ~ 0.002, about 0.5 px at the corners of a 640 px frame).
MIN_SHIFT_PX = 0.5


def largest_shift(intrinsics, shape: tuple[int, int], k1: float) -> float:
    """Largest distance between a pixel and its recorded position, over a frame's corners.

    The corners are where the radial term moves pixels most.

    Args:
        intrinsics: (fx, fy, cx, cy) in pixels of the frame.
        shape: (H, W) of the frame.
        k1: radial distortion term on normalised coordinates.

    Returns:
        The largest shift in pixels.
    """
    height, width = shape
    corners = torch.tensor([[0.0, 0.0], [width - 1, 0.0], [0.0, height - 1], [width - 1, height - 1]],
                           dtype=torch.float64)
    moved = pj.distort(corners, torch.tensor(intrinsics, dtype=torch.float64), k1)
    return float((moved - corners).norm(dim=-1).max())


def worth_undistorting(intrinsics, shape: tuple[int, int], k1: float) -> bool:
    """Whether the lens moves some pixel of a frame by at least MIN_SHIFT_PX.

    Args:
        intrinsics: (fx, fy, cx, cy) in pixels of the frame.
        shape: (H, W) of the frame.
        k1: radial distortion term on normalised coordinates.

    Returns:
        True when largest_shift >= MIN_SHIFT_PX.
    """
    return largest_shift(intrinsics, shape, k1) >= MIN_SHIFT_PX


def _source_map(width: int, height: int, intrinsics, k1: float, recording: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) float32 maps (height, width): for every pinhole pixel its recorded position
    (``distort``), or with recording=True for every recorded pixel its pinhole position
    (``undistort``)."""
    intr = torch.tensor(intrinsics, dtype=torch.float64)
    grid = pj.pixel_grid(height, width)
    src = pj.undistort(grid, intr, k1)[0] if recording else pj.distort(grid, intr, k1)
    return src[..., 0].float().numpy(), src[..., 1].float().numpy()


def _remap(images: np.ndarray, maps: tuple[np.ndarray, np.ndarray], nearest: bool, **border) -> np.ndarray:
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return np.stack([cv2.remap(im, *maps, mode, **border) for im in images])


def undistort_images(images: np.ndarray, intrinsics, k1: float, nearest: bool = False) -> np.ndarray:
    """Frames resampled into the pinhole image; pixels from outside the recording become 0.

    Args:
        images: (N, H, W) or (N, H, W, C) frames as recorded.
        intrinsics: (fx, fy, cx, cy) in pixels of the frames.
        k1: radial distortion term on normalised coordinates.
        nearest: no interpolation (depth, where mixing across edges invents surfaces).

    Returns:
        (N, H, W[, C]) pinhole frames, the input's dtype.
    """
    height, width = images.shape[1:3]
    return _remap(images, _source_map(width, height, intrinsics, k1), nearest,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def distort_images(images: np.ndarray, intrinsics, k1: float, nearest: bool = False) -> np.ndarray:
    """The inverse of :func:`undistort_images`: what a camera with radial term k1 records.

    Recorded pixel p shows the pinhole image at ``undistort(p)``; reflected at the border,
    so that a simulated recording has no black margin. For simulating lenses in tests and
    benchmarks.

    Args:
        images: (N, H, W) or (N, H, W, C) pinhole frames.
        intrinsics: (fx, fy, cx, cy) in pixels of the frames.
        k1: radial distortion term on normalised coordinates.
        nearest: no interpolation.

    Returns:
        (N, H, W[, C]) recorded frames, the input's dtype.
    """
    height, width = images.shape[1:3]
    return _remap(images, _source_map(width, height, intrinsics, k1, recording=True), nearest,
                  borderMode=cv2.BORDER_REFLECT)


def undistort_features(features: np.ndarray, intrinsics, shape: tuple[int, int], k1: float) -> np.ndarray:
    """Feature maps covering recorded frames, resampled into the pinhole image.

    Bilinear, zeros outside the recorded image.

    Args:
        features: (N, C, h, w) float32 feature maps covering the whole frame.
        intrinsics: (fx, fy, cx, cy) in pixels of the frames.
        shape: (H, W) of the frames.
        k1: radial distortion term on normalised coordinates.

    Returns:
        (N, C, h, w) float32 pinhole feature maps.
    """
    n, c, h, w = features.shape
    height, width = shape
    intr = pj.scale_intrinsics(intrinsics, w / width, h / height)
    mx, my = _source_map(w, h, intr, k1)
    grid = torch.from_numpy(np.stack([mx / max(w - 1, 1), my / max(h - 1, 1)], -1) * 2 - 1)[None]
    out = F.grid_sample(torch.from_numpy(features), grid.expand(n, -1, -1, -1).to(torch.float32),
                        mode="bilinear", padding_mode="zeros", align_corners=True)
    return out.numpy()
