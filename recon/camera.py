"""Pinhole intrinsics of one camera as plain numbers: scaling them with the image, and a
camera from a field of view.

Intrinsics are ``(fx, fy, cx, cy)`` in pixels of the stored image, pixel centres at integer
coordinates (pixel (0, 0) covers [-0.5, 0.5]^2), returned as a tuple of Python floats.
Batched torch intrinsics are :func:`medea_core.geometry.scale_intrinsics`'s business
(``medea_core`` never imports ``recon``).
"""

from __future__ import annotations

import math

from recon.errors import ReconInputError


def scale_intrinsics(intrinsics, sx: float, sy: float | None = None) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) for an image scaled by `sx` horizontally and `sy` (default sx) vertically.

    Pixel centres sit at integer coordinates, so the scaling is about the image corner
    (-0.5, -0.5): cx' = (cx + 0.5) * sx - 0.5, and likewise for cy (exact for area
    resizing and pooling).
    """
    sy = sx if sy is None else sy
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)


def resize_intrinsics(intrinsics, native: tuple[int, int], shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """Intrinsics of an image of `native` (H, W) after resizing to `shape` (H, W)."""
    return scale_intrinsics(intrinsics, shape[1] / native[1], shape[0] / native[0])


def intrinsics_from_fov(fov_deg: float, height: int, width: int) -> tuple[float, float, float, float]:
    """(f, f, cx, cy) of a centred square-pixel camera with horizontal field of view `fov_deg`.

    Raises ReconInputError (a ValueError) unless 0 < fov_deg < 180.
    """
    if not 0.0 < float(fov_deg) < 180.0:
        raise ReconInputError(f"field of view must be between 0 and 180 degrees, got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(float(fov_deg)) / 2.0)
    return (f, f, (width - 1) / 2.0, (height - 1) / 2.0)
