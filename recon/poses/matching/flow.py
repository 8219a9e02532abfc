"""Dense correspondence for the pose front end: classical optical flow (OpenCV DIS) with a
per-pixel confidence from forward-backward consistency, pooled to the BA grid.

This module owns everything between images and BA targets: grey images at the flow
resolution, DIS flow both ways (optionally seeded by a predicted flow), its confidences,
the pooling to BA targets and weights, and the whitening of the aperture problem.

Coordinates: flows are (H, W, 2) = (du, dv) in pixels of the grid they were computed on;
BA targets are absolute (u, v) pixel coordinates on the BA grid of the target image.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F


@dataclass
class FlowConfig:
    """DIS settings and the confidence model."""

    finest_scale: int = 0
    """DIS's finest pyramid level (0: full resolution).

    OpenCV's presets stop at 1/4 (fast) or 1/2 (medium) of the input and upsample; the flow
    images here are already small (about 160 px wide), so the default runs DIS down to full
    resolution, which on the synthetic room cuts the median error 2-3x for ~3x the time
    (still ~10 ms per flow at 160x120).
    """
    patch_size: int = 8
    """DIS's patch size in pixels."""
    patch_stride: int = 4
    """DIS's patch stride in pixels."""
    gd_iters: int = 16
    """DIS's gradient descent iterations."""
    var_iters: int = 5
    """DIS's variational refinement iterations."""
    fb_sigma: float = 0.75
    """The forward-backward error (pixels at the flow resolution) at which the confidence drops to 1/2.

    A Cauchy-like falloff 1 / (1 + (e / sigma)^2).
    """
    fb_rel: float = 0.05
    """The tolerated error grows by this fraction of the flow magnitude (large motions are less precise)."""
    spread_sigma: float = 1.0
    """Within a pooled block, a flow spread (std, pixels at the flow resolution) of this much halves the weight.

    Blocks straddling a depth edge mix two motions.
    """
    photo_sigma: float = 24.0
    """The mean absolute grey-level difference (0-255, over 3x3 pixels) at which the confidence halves.

    Between a pixel and where its flow lands. Forward-backward agreement alone trusts a flow
    that is zero both ways, which is what DIS returns between unrelated images (a cut, a
    blurred or corrupt frame); the images then disagree. Wide enough for exposure changes
    and blur between neighbouring frames.
    """
    anisotropic: bool = False
    """Weigh each flow vector by the direction its image's texture measures it in (``flow_whitening``).

    Along a straight edge or over plain shading only the flow across the edge is measured;
    what DIS returns along it is the aperture problem's guess, and it is biased short (on
    the synthetic walk-through's plain corridor it shrank the trajectory to half its
    length). why: docs/poses.md#plain-surfaces-the-flows-aperture-problem
    """
    texture_floor: float = 1.0
    """Texture weaker than this (grey levels per pixel, squared) counts as plain; its flow is weighted down."""


_DIS_CACHE = threading.local()  # one set of DIS instances per thread: an instance is not thread-safe
_SECOND_THREAD: dict[int, ThreadPoolExecutor] = {}  # by process id: a forked child starts its own


def _second_thread() -> ThreadPoolExecutor:
    """The thread that computes the second direction of a flow pair, one per process."""
    pid = os.getpid()
    if pid not in _SECOND_THREAD:
        _SECOND_THREAD.clear()
        _SECOND_THREAD[pid] = ThreadPoolExecutor(max_workers=1, thread_name_prefix="recon-flow")
    return _SECOND_THREAD[pid]


def _dis(cfg: FlowConfig, shape: tuple[int, int], seeded: bool) -> cv2.DISOpticalFlow:
    """One DIS instance per parameter set, image shape and use (creating one allocates
    buffers; reusing one on a larger image than it was first used on crashes OpenCV 4.x).

    seeded: calls with an initial flow get their own instance: a call with an initial flow
    leaves state behind in OpenCV 5.0's DIS that changes the next unseeded call on the same
    instance. why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen"""
    key = (cfg.finest_scale, cfg.patch_size, cfg.patch_stride, cfg.gd_iters, cfg.var_iters, tuple(shape), seeded)
    cache = _DIS_CACHE.__dict__
    if key not in cache:
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
        dis.setFinestScale(cfg.finest_scale)
        dis.setPatchSize(cfg.patch_size)
        dis.setPatchStride(cfg.patch_stride)
        dis.setGradientDescentIterations(cfg.gd_iters)
        dis.setVariationalRefinementIterations(cfg.var_iters)
        cache[key] = dis
    return cache[key]


def prepare_gray(frame: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Grey uint8 image of `shape` (h, w) of an RGB frame (H, W, 3) uint8, area-resized."""
    gray = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY) if frame.ndim == 3 else frame
    if gray.shape[:2] != tuple(shape):
        gray = cv2.resize(gray, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(gray)


def dis_flow(a: np.ndarray, b: np.ndarray, cfg: FlowConfig, init: np.ndarray | None = None) -> np.ndarray:
    """DIS optical flow (h, w, 2) float32 from grey image a (h, w) to b (h, w).

    init: optional initial flow (h, w, 2); DIS refines it coarse to fine, so a good
    prediction lets it find motions far beyond its search range. It is left as it was:
    OpenCV writes the flow into the array it is given, which would be the caller's own
    when that is already contiguous float32.
    """
    flow = None if init is None else np.array(init, dtype=np.float32, order="C", copy=True)
    return _dis(cfg, a.shape[:2], flow is not None).calc(a, b, flow)


def sample_along(image: np.ndarray, flow: np.ndarray, **border) -> np.ndarray:
    """image (h, w[, c]) float32 sampled bilinearly at ``p + flow(p)`` (flow (h, w, 2))."""
    h, w = flow.shape[:2]
    coords = np.mgrid[0:h, 0:w][::-1].transpose(1, 2, 0).astype(np.float32) + flow
    return cv2.remap(image, coords[..., 0], coords[..., 1], cv2.INTER_LINEAR, **border)


def warp_flow(flow: np.ndarray, by: np.ndarray) -> np.ndarray:
    """flow (h, w, 2) sampled bilinearly at ``p + by(p)`` (by (h, w, 2)); outside -> NaN."""
    return sample_along(flow, by, borderMode=cv2.BORDER_CONSTANT, borderValue=(np.nan, np.nan))


def flow_length(flow: np.ndarray) -> np.ndarray:
    """Length (h, w) of each vector of a flow (h, w, 2): the same values as
    ``np.linalg.norm(flow, axis=-1)``, three times faster on these small images."""
    return np.sqrt(flow[..., 0] * flow[..., 0] + flow[..., 1] * flow[..., 1])


def fb_confidence(fwd: np.ndarray, bwd: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    """Confidence (h, w) in [0, 1] of forward flow fwd (h, w, 2) given the backward flow bwd.

    The backward flow at the forward target should undo the forward flow; the residual
    ``|fwd(p) + bwd(p + fwd(p))|`` is large at occlusions, the image border and where DIS
    failed. Targets outside the image get 0.
    """
    back = warp_flow(bwd, fwd)
    err = flow_length(fwd + back)
    tol = cfg.fb_sigma + cfg.fb_rel * flow_length(fwd)
    conf = 1.0 / (1.0 + (err / tol) ** 2)
    conf[~np.isfinite(conf)] = 0.0
    return conf.astype(np.float32)


def photo_confidence(a: np.ndarray, b: np.ndarray, flow: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    """Confidence (h, w) in [0, 1] that flow (h, w, 2) from grey image a to b joins pixels
    that look alike: 1 / (1 + (e / photo_sigma)^2) with e the 3x3 mean of |a(p) - b(p + flow(p))|."""
    err = cv2.blur(np.abs(a.astype(np.float32) - _matched(b, flow)), (3, 3))
    return (1.0 / (1.0 + (err / cfg.photo_sigma) ** 2)).astype(np.float32)


def _matched(b: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Grey image b (h, w) sampled where flow (h, w, 2) sends each pixel, float32."""
    return sample_along(b.astype(np.float32), flow, borderMode=cv2.BORDER_REPLICATE)


def match_correlation(a: np.ndarray, b: np.ndarray, flow: np.ndarray, conf: np.ndarray) -> float:
    """Confidence-weighted correlation coefficient between grey image a (h, w) and b
    sampled along flow (h, w, 2): near 1 when the flow joins matching structure, near 0
    between unrelated images. Pixelwise confidence cannot tell that apart: a smooth flow
    between two unrelated low-contrast images (noise, a cut) is forward-backward
    consistent, and their grey levels are close enough to look photometrically plausible."""
    w = conf.astype(np.float64)
    total = w.sum()
    if total <= 0:
        return 0.0
    x = a.astype(np.float64)
    y = _matched(b, flow).astype(np.float64)
    x = x - (w * x).sum() / total
    y = y - (w * y).sum() / total
    cov = (w * x * y).sum()
    return float(cov / max(np.sqrt((w * x * x).sum() * (w * y * y).sum()), 1e-9))


def local_correlation(a: np.ndarray, b: np.ndarray, flow: np.ndarray, conf: np.ndarray, radius: int = 3,
                      min_std: float = 4.0) -> float:
    """Confidence-weighted mean of the zero-normalised cross-correlation of (2 radius + 1)^2
    windows of grey image a (h, w) and b sampled along flow (h, w, 2), over windows with
    texture (grey-level std >= min_std in both). A dense flow can bend one image onto the
    coarse layout of an unrelated one (a floor below a wall, a bright window), which the
    global correlation of ``match_correlation`` rewards; the fine texture inside each
    window only lines up between views of the same surfaces."""
    x = a.astype(np.float32)
    y = _matched(b, flow)
    k = (2 * radius + 1, 2 * radius + 1)
    mx, my = cv2.blur(x, k), cv2.blur(y, k)
    vx = np.maximum(cv2.blur(x * x, k) - mx * mx, 0.0)
    vy = np.maximum(cv2.blur(y * y, k) - my * my, 0.0)
    cov = cv2.blur(x * y, k) - mx * my
    textured = (vx >= min_std**2) & (vy >= min_std**2)
    w = conf.astype(np.float64) * textured
    if w.sum() <= 0:
        return 0.0
    ncc = cov / np.sqrt(np.maximum(vx * vy, 1e-6))
    return float((w * ncc).sum() / w.sum())


def flow_pair(
    a: np.ndarray,
    b: np.ndarray,
    cfg: FlowConfig,
    init_ab: np.ndarray | None = None,
    init_ba: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Flows a->b, b->a (h, w, 2) and their confidences (h, w): forward-backward agreement
    times photometric agreement.

    The backward direction runs on a second thread (OpenCV and NumPy let go of the GIL), so
    that DIS, whose own parallel loops leave the second core half idle on these small
    images, keeps both busy; the results are those of running the two in turn."""
    backward = _second_thread().submit(dis_flow, b, a, cfg, init_ba)
    fwd = dis_flow(a, b, cfg, init_ab)
    bwd = backward.result()
    backward = _second_thread().submit(_confidence, b, a, bwd, fwd, cfg)
    cf = _confidence(a, b, fwd, bwd, cfg)
    return fwd, bwd, cf, backward.result()


def _confidence(a: np.ndarray, b: np.ndarray, fwd: np.ndarray, bwd: np.ndarray, cfg: FlowConfig) -> np.ndarray:
    """Confidence (h, w) of the flow a->b fwd given the flow b->a bwd (see flow_pair)."""
    return fb_confidence(fwd, bwd, cfg) * photo_confidence(a, b, fwd, cfg)


def pool_edge(flow: np.ndarray, conf: np.ndarray, factor: int, cfg: FlowConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Pool a flow (h*k, w*k, 2) and confidence (h*k, w*k) by k = factor to BA targets.

    Returns target (h, w, 2) float64, the absolute BA-grid coordinates in the other image
    where each BA pixel goes (confidence-weighted mean flow / k), and weight (h, w) float64
    = mean confidence times a penalty on the flow spread inside the block.
    """
    f = torch.from_numpy(np.ascontiguousarray(flow, dtype=np.float32)).permute(2, 0, 1)[None].double()
    c = torch.from_numpy(np.ascontiguousarray(conf, dtype=np.float32))[None, None].double()
    k = int(factor)
    hk, wk = f.shape[-2:]
    h, w = hk // k, wk // k
    f, c = f[..., : h * k, : w * k], c[..., : h * k, : w * k]
    csum = F.avg_pool2d(c, k) + 1e-9
    mean = F.avg_pool2d(f * c, k) / csum
    var = (F.avg_pool2d((f * f) * c, k) / csum - mean * mean).clamp(min=0).sum(1, keepdim=True)
    weight = (F.avg_pool2d(c, k) / (1.0 + var / cfg.spread_sigma**2))[0, 0]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    target = torch.stack([u, v], -1) + mean[0].permute(1, 2, 0) / k
    return target, weight


def gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grey-level gradient (gx, gy), each (h, w) float32 in grey levels per pixel, of
    gray (h, w): Sobel's 3 x 3 kernels normalised."""
    g = gray.astype(np.float32)
    return cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8.0, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8.0


def structure_tensor(gray: np.ndarray, window: int) -> np.ndarray:
    """The image's structure tensor (h, w, 3) float32: the mean over a window x window
    patch of g g^T, g the grey-level gradient (:func:`gradients`) of gray (h, w); the
    components (xx, xy, yy)."""
    gx, gy = gradients(gray)
    return np.stack([cv2.blur(v, (window, window)) for v in (gx * gx, gx * gy, gy * gy)], axis=-1)


def flow_whitening(gray: np.ndarray, factor: int, cfg: FlowConfig) -> torch.Tensor | None:
    """Per BA pixel, the 2 x 2 factor L (h, w, 2, 2) float32 the BA multiplies a flow
    residual (and its Jacobian) from this image by, so that its squared norm weighs each
    direction by how well the texture measures the flow in it (Lucas and Kanade's normal
    matrix: the flow's information is the structure tensor S). With S averaged over DIS's
    patch and over the k x k flow pixels of a BA pixel (k = factor; gray is the
    flow-resolution image (h*k, w*k)), L^T L = S / (trace(S) / 2 + ``texture_floor``):
    about the identity on texture, weight 2 across and 0 along a straight edge, about 0 on
    a plain surface. None when ``cfg.anisotropic`` is off."""
    if not cfg.anisotropic:
        return None
    tensor = torch.from_numpy(structure_tensor(gray, cfg.patch_size)).permute(2, 0, 1)[None].double()
    k = int(factor)
    h, w = tensor.shape[-2] // k, tensor.shape[-1] // k
    xx, xy, yy = F.avg_pool2d(tensor[..., : h * k, : w * k], k)[0]
    scale = 0.5 * (xx + yy) + cfg.texture_floor
    xx, xy, yy = xx / scale, xy / scale, yy / scale
    # The symmetric square root of a 2 x 2 positive semi-definite matrix in closed form:
    # sqrt(N) = (N + sqrt(det N) I) / sqrt(trace N + 2 sqrt(det N)).
    root_det = (xx * yy - xy * xy).clamp(min=0).sqrt()
    t = (xx + yy + 2 * root_det).clamp(min=1e-12).sqrt()
    rows = torch.stack([torch.stack([xx + root_det, xy], -1), torch.stack([xy, yy + root_det], -1)], -2)
    return (rows / t[..., None, None]).float()


def mean_magnitude(flow: np.ndarray, conf: np.ndarray | None = None) -> float:
    """Mean flow length (pixels), confidence-weighted when conf (h, w) is given."""
    mag = flow_length(flow)
    if conf is None:
        return float(mag.mean())
    return float((mag * conf).sum() / max(conf.sum(), 1e-9))
