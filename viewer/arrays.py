"""What the Rerun logger accepts, as Rerun takes it: array-likes (torch tensors on any
device included) as numpy, intrinsics as (fx, fy, cx, cy), RGB as uint8, depth as float32
metres (0 = invalid), poses as 4x4 camera-to-world, and images resized to their logged
size (depth nearest-neighbour, so that valid depth never mixes with invalid).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def to_numpy(array: Any) -> np.ndarray:
    """numpy view of an array-like, torch tensors (any device, with grad) included."""
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    return np.asarray(array)


def as_intrinsics(intrinsics: Any) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from a 4-sequence or a 3x3 camera matrix."""
    k = to_numpy(intrinsics).astype(np.float64)
    if k.shape == (3, 3):
        return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    if k.shape == (4,):
        return tuple(float(v) for v in k)  # type: ignore[return-value]
    raise ValueError(f"intrinsics must be (fx, fy, cx, cy) or a 3x3 matrix, got shape {k.shape}")


def rgb_uint8(rgb: Any) -> np.ndarray:
    """(H, W, 3|4) or (H, W) uint8; floats are taken to be in [0, 1]."""
    image = to_numpy(rgb)
    if image.ndim == 3 and image.shape[0] in (1, 3, 4) and image.shape[-1] not in (1, 3, 4):
        image = np.moveaxis(image, 0, -1)  # CHW -> HWC
    if image.ndim == 3 and image.shape[-1] == 1:
        image = image[..., 0]
    if image.dtype != np.uint8:
        image = np.clip(np.nan_to_num(image.astype(np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


def depth_f32(depth: Any) -> np.ndarray:
    """(H, W) float32 metres, non-finite and negative values set to 0 (invalid)."""
    d = to_numpy(depth).astype(np.float32)
    if d.ndim == 3 and d.shape[0] == 1:
        d = d[0]
    elif d.ndim == 3 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    return np.ascontiguousarray(d)


def logged_size(height: int, width: int, max_width: int | None) -> tuple[int, int]:
    if max_width is None or width <= max_width:
        return height, width
    return max(1, round(height * max_width / width)), max_width


def resize_rgb(image: np.ndarray, height: int, width: int) -> np.ndarray:
    if image.shape[:2] == (height, width):
        return image
    from PIL import Image as PILImage  # pillow is a rerun-sdk dependency

    return np.asarray(PILImage.fromarray(image).resize((width, height), PILImage.Resampling.BOX))


def resize_nearest(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize (never mixes valid depth with 0 = invalid)."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return np.ascontiguousarray(depth[rows[:, None], cols[None, :]])


def camera_of(intrinsics: Any, source: tuple[int, int] | None) -> tuple[Any, tuple[int, int]] | None:
    """(intrinsics, (H, W) of the image they are in pixels of) from (fx, fy, cx, cy, width,
    height), or from 4 values or a 3x3 matrix in pixels of ``source``; None when either is
    unknown."""
    if intrinsics is None:
        return None
    k = to_numpy(intrinsics).astype(np.float64)
    if k.shape == (6,):
        return k[:4], (int(k[5]), int(k[4]))
    return None if source is None else (k, tuple(source))


def pose_matrix(pose: Any) -> np.ndarray:
    t = to_numpy(pose).astype(np.float64)
    if t.shape != (4, 4):
        raise ValueError(f"pose must be a 4x4 camera-to-world matrix, got shape {t.shape}")
    return t
