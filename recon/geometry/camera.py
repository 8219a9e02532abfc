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
    """Intrinsics of an image scaled by `sx` horizontally and `sy` vertically.

    Pixel centres sit at integer coordinates, so the scaling is about the image corner
    (-0.5, -0.5): cx' = (cx + 0.5) * sx - 0.5, and likewise for cy (exact for area
    resizing and pooling).

    Args:
        intrinsics: (fx, fy, cx, cy) in pixels of the original image, any sequence of 4 numbers.
        sx: new width / old width.
        sy: new height / old height; None: sx.

    Returns:
        (fx, fy, cx, cy) floats in pixels of the scaled image.
    """
    sy = sx if sy is None else sy
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)


def resize_intrinsics(intrinsics, native: tuple[int, int], shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """Intrinsics of an image of `native` (H, W) after resizing to `shape` (H, W).

    Args:
        intrinsics: (fx, fy, cx, cy) in pixels of the native image.
        native: (H, W) of the image the intrinsics belong to.
        shape: (H, W) of the resized image.

    Returns:
        (fx, fy, cx, cy) floats in pixels of the resized image.
    """
    return scale_intrinsics(intrinsics, shape[1] / native[1], shape[0] / native[0])


def intrinsics_from_fov(fov_deg: float, height: int, width: int) -> tuple[float, float, float, float]:
    """Intrinsics of a centred square-pixel camera with horizontal field of view `fov_deg`.

    Args:
        fov_deg: horizontal field of view in degrees.
        height: image height in pixels.
        width: image width in pixels.

    Returns:
        (f, f, cx, cy) floats in pixels, f = (W / 2) / tan(fov / 2) and the principal point
        at the image centre ((W - 1) / 2, (H - 1) / 2).

    Raises:
        ReconInputError: (a ValueError) unless 0 < fov_deg < 180.
    """
    if not 0.0 < float(fov_deg) < 180.0:
        raise ReconInputError(f"field of view must be between 0 and 180 degrees, got {fov_deg}")
    f = 0.5 * width / math.tan(math.radians(float(fov_deg)) / 2.0)
    return (f, f, (width - 1) / 2.0, (height - 1) / 2.0)


# OpenCV's distortion model, in its order: radial k1, k2, tangential p1, p2, radial k3.
DISTORTION_TERMS = ("k1", "k2", "p1", "p2", "k3")


def check_distortion(values, where: str = "--distortion") -> tuple[float, ...]:
    """Validate OpenCV distortion coefficients k1, k2, p1, p2[, k3].

    Args:
        values: the coefficients, any sequence of numbers.
        where: names the setting in the error message.

    Returns:
        The coefficients as a tuple of 4 or 5 floats.

    Raises:
        ReconInputError: (one line) unless there are 4 or 5 finite numbers.
    """
    coefficients = tuple(float(v) for v in values)
    if len(coefficients) not in (4, 5) or not all(math.isfinite(v) for v in coefficients):
        raise ReconInputError(f"{where}: expected 4 or 5 finite numbers k1,k2,p1,p2[,k3] (OpenCV's model), got "
                              f"{','.join(str(v) for v in values)}")
    return coefficients


def is_pinhole(distortion) -> bool:
    """Whether there is no distortion to undo.

    Args:
        distortion: OpenCV coefficients k1, k2, p1, p2[, k3], or None.

    Returns:
        True for None or when every coefficient is 0.
    """
    return distortion is None or not any(float(v) for v in distortion)


def undistortion_maps(intrinsics, distortion, shape: tuple[int, int]):
    """Maps for ``cv2.remap`` from the pinhole image to where the lens recorded each pixel.

    For every pixel of the pinhole image with the same intrinsics, the position the lens
    recorded it at (OpenCV's model; the coefficients act on normalised coordinates, so they
    hold at any image size).

    Args:
        intrinsics: (fx, fy, cx, cy) in pixels of an image of `shape`.
        distortion: OpenCV coefficients k1, k2, p1, p2[, k3].
        shape: (H, W) of the image.

    Returns:
        (map_x, map_y), each (H, W) float32, recorded pixel coordinates.
    """
    import cv2
    import numpy as np

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return cv2.initUndistortRectifyMap(K, np.asarray(distortion, np.float64), None, K, (shape[1], shape[0]),
                                       cv2.CV_32FC1)


def largest_lens_shift(maps) -> float:
    """The largest distance between a pinhole pixel and where the lens recorded it.

    Args:
        maps: (map_x, map_y) (H, W) from :func:`undistortion_maps`.

    Returns:
        The largest shift in pixels.
    """
    import numpy as np

    map_x, map_y = maps
    v, u = np.mgrid[0:map_x.shape[0], 0:map_x.shape[1]]
    return float(np.sqrt((map_x - u) ** 2 + (map_y - v) ** 2).max())
