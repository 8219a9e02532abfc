"""A simulated monocular depth prior: ground truth distorted the way a per-frame network
errs, so that MEDeA has something realistic to correct.

This module owns the distortion model, per frame i
``D0_i = blur(D_i * s_i * exp(B(g_i))) * exp(noise_sigma * n_i)``: a log-normal global
scale, a smooth scale field from an upsampled coarse log-grid, a mask-aware blur and
per-pixel multiplicative noise, so frames are mutually inconsistent in scale and shape.
More: docs/running.md#the-synthetic-scenes
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ReconInputError


@dataclass
class SimulatedPrior:
    """A simulated prior with the distortions that produced it.

    Attributes:
        depth: (N, H, W) float32 prior depth in metres, 0 where the input was 0.
        global_scale: (N,) float64 per-frame global scale factors s_i (prior / truth).
        log_grids: (N, rows, cols) float64 coarse log-scale grids g_i of the smooth field.
    """

    depth: np.ndarray
    global_scale: np.ndarray
    log_grids: np.ndarray

    def scale_field(self, index: int) -> np.ndarray:
        """(H, W) float32 noise-free scale s_i * exp(B(g_i)) of frame `index` (prior / truth before blur and noise)."""
        height, width = self.depth.shape[1:]
        return (self.global_scale[index] * np.exp(_upsample(self.log_grids[index], height, width))).astype(np.float32)


def _upsample(grid: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bicubic upsampling of a coarse (rows, cols) grid to (H, W); grid nodes sit at cell centres."""
    return cv2.resize(grid.astype(np.float32), (width, height), interpolation=cv2.INTER_CUBIC)


def _masked_blur(depth: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (H, W) of depth over valid pixels only (normalised convolution), so
    invalid zeros never leak into their neighbours."""
    if sigma <= 0:
        return depth
    num = cv2.GaussianBlur(depth * valid, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    den = cv2.GaussianBlur(valid.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def _check_depth(depth) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 3 or min(depth.shape) < 1:
        raise ReconInputError(f"simulate_prior: depth must be (N, H, W), got shape {depth.shape}")
    depth = depth.astype(np.float32, copy=False)
    if not np.isfinite(depth).all():
        raise ReconInputError("simulate_prior: depth contains NaN or inf (use 0 for invalid pixels)")
    if (depth < 0).any():
        raise ReconInputError("simulate_prior: depth contains negative values (use 0 for invalid pixels)")
    return depth


def simulate_prior_with_truth(
    depth,
    seed: int = 0,
    *,
    global_sigma: float = 0.2,
    field_sigma: float = 0.15,
    field_grid: tuple[int, int] = (3, 4),
    noise_sigma: float = 0.025,
    blur_sigma: float = 1.0,
) -> SimulatedPrior:
    """Distort ground-truth depth (N, H, W) into a prior and report the distortions.

    Args:
        depth: (N, H, W) z-depth in metres, 0 = invalid (kept 0).
        seed: the same seed gives bit-identical output.
        global_sigma: std of the per-frame log global scale (default 0.2). The N log
            scales are drawn from N(0, 1) and rescaled to RMS exactly 1 before
            multiplying by global_sigma, so short sequences get the nominal error too.
        field_sigma: std of the coarse log-scale grid nodes (default 0.15).
        field_grid: (rows, cols) of the coarse grid (default (3, 4)); transposed for
            portrait frames.
        noise_sigma: std of the per-pixel log noise (default 0.025, i.e. ~2.5%).
        blur_sigma: Gaussian blur in pixels at 640 px width, scaled with the width
            (default 1.0; 0 disables).

    Returns:
        SimulatedPrior with depth (N, H, W) float32, global_scale (N,), log_grids (N, rows, cols).
        With the defaults the abs rel against the input is about 0.2.
    """
    depth = _check_depth(depth)
    n, height, width = depth.shape
    rows, cols = (int(x) for x in field_grid)
    if rows < 1 or cols < 1:
        raise ReconInputError(f"simulate_prior: field_grid must be positive, got {field_grid}")
    if height > width and rows < cols:
        rows, cols = cols, rows
    rng = np.random.default_rng([seed, 7])
    z = rng.standard_normal(n)
    if n > 1:
        z /= np.sqrt(np.mean(z**2))
    global_scale = np.exp(global_sigma * z)
    log_grids = field_sigma * rng.standard_normal((n, rows, cols))
    sigma_px = blur_sigma * width / 640.0
    prior = np.empty_like(depth)
    for i in range(n):
        valid = depth[i] > 0
        field = np.exp(_upsample(log_grids[i], height, width)) * np.float32(global_scale[i])
        blurred = _masked_blur(depth[i] * field, valid, sigma_px)
        noise = np.exp(np.float32(noise_sigma) * rng.standard_normal((height, width), dtype=np.float32))
        prior[i] = np.where(valid, blurred * noise, 0.0)
    return SimulatedPrior(depth=prior, global_scale=global_scale, log_grids=log_grids)


def simulate_prior(depth, seed: int = 0, **kwargs) -> np.ndarray:
    """(N, H, W) float32 simulated monocular prior of ground-truth depth (N, H, W).

    Same keyword arguments as :func:`simulate_prior_with_truth` (global_sigma=0.2,
    field_sigma=0.15, field_grid=(3, 4), noise_sigma=0.025, blur_sigma=1.0); use that
    function to also get the true per-frame scale factors.
    """
    return simulate_prior_with_truth(depth, seed, **kwargs).depth


def add_shape_errors(
    prior,
    seed: int = 0,
    *,
    bumps: int = 12,
    bump_amplitude: float = 0.12,
    bump_radius: float = 0.03,
    ramp_amplitude: float = 0.06,
    ramp_period: float = 0.08,
    edge_blur: float = 6.0,
) -> np.ndarray:
    """Per-pixel shape errors (N, H, W) float32 that no coarse scale grid can represent.

    A network's depth is wrong in shape as well as in scale: small blobs that bulge or sink,
    surfaces tilted in stripes, depth edges smeared between foreground and background.
    MEDeA's 8x10 grid per frame (one node per 64 x 60 pixels at 640 x 480) corrects
    neither; the multi-view refinement must.

    prior: (N, H, W) metres (0 invalid, kept 0); per frame and independently:
    bumps: Gaussian blobs in log depth, amplitude uniform in +-bump_amplitude, radius
    bump_radius x width; a sawtooth ramp in log depth of +-ramp_amplitude along a random
    direction with period ramp_period x width; a mask-aware Gaussian blur of edge_blur
    pixels (at 640 px width) over the whole map, which smears depth edges.
    """
    prior = _check_depth(prior)
    n, height, width = prior.shape
    rng = np.random.default_rng([seed, 11])
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    out = np.empty_like(prior)
    sigma_px = edge_blur * width / 640.0
    for i in range(n):
        field = np.zeros((height, width), np.float32)
        for _ in range(bumps):
            cx, cy = rng.uniform(0, width), rng.uniform(0, height)
            r = bump_radius * width * rng.uniform(0.6, 1.4)
            field += np.float32(rng.uniform(-bump_amplitude, bump_amplitude)) * np.exp(
                -((u - cx) ** 2 + (v - cy) ** 2) / (2 * r * r))
        angle = rng.uniform(0, np.pi)
        phase = (u * np.cos(angle) + v * np.sin(angle)) / (ramp_period * width) + rng.uniform(0, 1)
        field += np.float32(ramp_amplitude) * (2.0 * (phase - np.floor(phase)) - 1.0)
        valid = prior[i] > 0
        shaped = _masked_blur(prior[i] * np.exp(field), valid, sigma_px)
        out[i] = np.where(valid, shaped, 0.0)
    return out
