"""Turning affine-invariant disparity (e.g. relative Depth Anything / MiDaS output) into metric
depth by fitting a per-frame scale and shift in disparity space against a metric reference.

The reference is whatever metric depth the caller has: sparse points (SfM, sensor) or a
metric prior such as FastDepth. This module does not know or record which; the caller
does (``PriorOutput.info["aligned_to"]``).
"""

from __future__ import annotations

import numpy as np

# Metric disparities below this (depth beyond 1 km) or non-positive are "no depth".
_MIN_DISPARITY = 1e-3


def fit_affine_disparity(disparity: np.ndarray, target: np.ndarray, iterations: int = 20) -> tuple[float, float]:
    """Robust (scale, shift) with ``scale * disparity + shift ~ target``.

    disparity, target: (P,) matched samples. Starts from a median/MAD match (immune to
    outliers), then iteratively reweighted least squares with Tukey's biweight at 4.685
    robust sigmas, so wrong reference points or sky/edge pixels do not pull the fit.
    """
    d = np.asarray(disparity, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    d_med, y_med = np.median(d), np.median(y)
    d_mad = np.median(np.abs(d - d_med))
    y_mad = np.median(np.abs(y - y_med))
    scale = y_mad / d_mad if d_mad > 0 else 0.0
    shift = y_med - scale * d_med
    design = np.stack([d, np.ones_like(d)], axis=1)
    for _ in range(iterations):
        residual = y - (scale * d + shift)
        sigma = 1.4826 * np.median(np.abs(residual - np.median(residual)))
        if sigma <= 1e-12 * max(1.0, abs(y_med)):
            break  # exact fit already
        u = residual / (4.685 * sigma)
        weights = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        if weights.sum() < 2:
            break
        sw = np.sqrt(weights)
        (new_scale, new_shift), *_ = np.linalg.lstsq(design * sw[:, None], y * sw, rcond=None)
        converged = abs(new_scale - scale) <= 1e-9 * abs(scale) + 1e-12 and abs(new_shift - shift) <= 1e-9
        scale, shift = float(new_scale), float(new_shift)
        if converged:
            break
    return float(scale), float(shift)


def align_affine_disparity(disparity, reference_depth, mask=None, min_points: int = 16) -> np.ndarray:
    """Metric depth from affine-invariant disparity, one scale and shift per frame.

    Args:
        disparity: (N, H, W) or (H, W) affine-invariant disparity (larger = nearer).
        reference_depth: same shape, metric depth in metres; 0 / NaN where there is none
            (sparse points are fine).
        mask: optional same-shape bool, pixels allowed in the fit.
        min_points: fewer usable reference pixels in a frame is an error.

    Returns:
        depth of the input shape, float32 metres, 0 where the aligned disparity is not
        positive (or the input disparity is not finite).

    Raises:
        ValueError: shapes differ, or a frame has too few reference pixels.
    """
    disparity = np.asarray(disparity, dtype=np.float32)
    reference_depth = np.asarray(reference_depth, dtype=np.float32)
    single = disparity.ndim == 2
    if single:
        disparity, reference_depth = disparity[None], reference_depth[None]
        mask = None if mask is None else np.asarray(mask)[None]
    if disparity.shape != reference_depth.shape or (mask is not None and np.shape(mask) != disparity.shape):
        raise ValueError(
            f"align_affine_disparity: disparity {disparity.shape}, reference {reference_depth.shape}"
            f"{'' if mask is None else f', mask {np.shape(mask)}'} must have the same shape"
        )
    finite = np.isfinite(disparity)
    usable = finite & np.isfinite(reference_depth) & (reference_depth > 0)
    if mask is not None:
        usable &= np.asarray(mask, dtype=bool)
    depth = np.zeros_like(disparity)
    for k in range(len(disparity)):
        m = usable[k]
        if m.sum() < min_points:
            raise ValueError(
                f"align_affine_disparity: frame {k} has {int(m.sum())} reference pixels, need {min_points}"
            )
        scale, shift = fit_affine_disparity(disparity[k][m], 1.0 / reference_depth[k][m])
        metric = scale * disparity[k] + shift
        ok = finite[k] & (metric > _MIN_DISPARITY)
        depth[k][ok] = 1.0 / metric[ok]
    return depth[0] if single else depth
