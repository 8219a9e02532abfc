"""Whether the dense flow shortened the camera's steps: its translation checked against the
images' own gradients, keyframe pair by keyframe pair.

On plain surfaces DIS returns only part of the flow (the aperture problem, Horn and
Schunck's *normal flow*) and the BA's steps come out short, unseen by the scale watch.
Lucas-Kanade steps on high-passed images (:func:`gradient_flow`) measure where the gradients
say each pixel went; that translation flow regressed on the induced one, weighted by the
structure tensor (:func:`translation_slope`), has slope 1 on texture and more where the
steps were shortened; :func:`short_stretches` flags windows over ``max_slope``.
More: docs/poses.md#the-short-flow-check  why: docs/decisions.md#the-short-flow-check
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from recon.poses.ba import graph as gr
from recon.poses.checks.quality import runs
from recon.poses.matching import flow as fl


@dataclass(frozen=True)
class NormalFlowConfig:
    """sigma: Gaussian blur (flow pixels) of both images before the gradients (widens the
        reach of the linearised steps);
    highpass: side (flow pixels) of the box mean subtracted from each image, so that a
        brightness change between the frames moves no pixel (DIS compares mean-free
        patches for the same reason); 0 turns it off;
    window: side of the Lucas-Kanade window (flow pixels);
    texture_floor: the smallest structure tensor (grey levels^2 per pixel^2, per pixel of
        the window) a step is taken on: steps on sensor noise are damped towards none;
    iters, max_step: Lucas-Kanade steps, and the most (flow pixels) they may move a pixel
        in all;
    min_flow: a pair is judged only when its induced translation flow is at least this
        (pixels of a 640-px-wide frame; mean over the valid pixels): a turn without
        parallax says nothing of the steps' length;
    pairs, min_pairs: consecutive keyframe pairs pooled per window, and how many of them
        must be judged;
    max_slope: a window whose pooled slope exceeds this is flagged (the dense flow's steps
        are shorter than the gradients say)."""

    sigma: float = 1.5
    highpass: int = 7
    window: int = 5
    texture_floor: float = 1.0
    iters: int = 3
    max_step: float = 2.0
    min_flow: float = 6.0
    pairs: int = 3
    min_pairs: int = 2
    max_slope: float = 1.2


def _prepared(gray: np.ndarray, cfg: NormalFlowConfig) -> np.ndarray:
    image = gray.astype(np.float32)
    if cfg.sigma > 0:
        image = cv2.GaussianBlur(image, (0, 0), cfg.sigma)
    if cfg.highpass > 1:
        image = image - cv2.blur(image, (cfg.highpass, cfg.highpass))
    return image


def gradient_flow(a: np.ndarray, b: np.ndarray, flow: np.ndarray, cfg: NormalFlowConfig) -> np.ndarray:
    """Flow (h, w, 2) float32 from grey image a (h, w) to b after ``cfg.iters`` Lucas-Kanade
    steps from `flow` (h, w, 2): each pixel moved where the image gradients in its window say
    it went (the symmetric, ESM-like gradient of both images), damped by the texture floor
    and limited to ``cfg.max_step`` in all. Along an edge the gradients say nothing and the
    pixel keeps `flow`'s component."""
    return _steps(_prepared(a, cfg), _prepared(b, cfg), flow, cfg)


def _steps(A: np.ndarray, B: np.ndarray, flow: np.ndarray, cfg: NormalFlowConfig) -> np.ndarray:
    """:func:`gradient_flow` between images already ``_prepared``."""
    gax, gay = fl.gradients(A)
    gbx, gby = fl.gradients(B)
    start = np.ascontiguousarray(flow, dtype=np.float32)
    current = start.copy()
    size = (cfg.window, cfg.window)
    floor = cfg.texture_floor * cfg.window * cfg.window

    def box(x):
        return cv2.boxFilter(x, -1, size, normalize=False)

    for _ in range(cfg.iters):
        border = {"borderMode": cv2.BORDER_REPLICATE}
        gx = 0.5 * (gax + fl.sample_along(gbx, current, **border))
        gy = 0.5 * (gay + fl.sample_along(gby, current, **border))
        dt = fl.sample_along(B, current, **border) - A
        sxx, sxy, syy = box(gx * gx) + floor, box(gx * gy), box(gy * gy) + floor
        bx, by = -box(gx * dt), -box(gy * dt)
        det = sxx * syy - sxy * sxy
        current += np.stack([(syy * bx - sxy * by) / det, (sxx * by - sxy * bx) / det], axis=-1)
        moved = current - start
        length = np.linalg.norm(moved, axis=-1, keepdims=True)
        current = start + moved * np.minimum(1.0, cfg.max_step / np.maximum(length, 1e-9))
    return current


def translation_slope(a: np.ndarray, b: np.ndarray, rotation_flow: np.ndarray, translation_flow: np.ndarray,
                      valid: np.ndarray, cfg: NormalFlowConfig) -> tuple[float, float]:
    """(numerator, denominator) of the structure-tensor-weighted slope of the translation
    flow the gradients measure on the one the poses induce, from grey image a (h, w) to b:
    sum t^T S m / sum t^T S t, with t the induced translation flow (h, w, 2), m the measured
    one (:func:`gradient_flow` from the induced flow, less its rotation part rotation_flow)
    and S a's structure tensor (``flow.structure_tensor`` over the window); valid (h, w):
    the pixels that land in b in front of it. Returned apart so that pairs can be pooled."""
    return _slope(_prepared(a, cfg), _prepared(b, cfg), rotation_flow, translation_flow, valid, cfg)


def _slope(A: np.ndarray, B: np.ndarray, rotation_flow: np.ndarray, translation_flow: np.ndarray,
           valid: np.ndarray, cfg: NormalFlowConfig) -> tuple[float, float]:
    """:func:`translation_slope` between images already ``_prepared``."""
    measured = _steps(A, B, rotation_flow + translation_flow, cfg) - rotation_flow
    xx, xy, yy = np.moveaxis(fl.structure_tensor(A, cfg.window), -1, 0)
    tx, ty = translation_flow[..., 0], translation_flow[..., 1]
    stx, sty = xx * tx + xy * ty, xy * tx + yy * ty  # S t
    w = valid.astype(np.float64)
    num = float((w * (stx * measured[..., 0] + sty * measured[..., 1])).sum())
    den = float((w * (stx * tx + sty * ty)).sum())
    return num, den


def short_stretches(num: np.ndarray, den: np.ndarray, judged: np.ndarray, cfg: NormalFlowConfig
                    ) -> tuple[list[tuple[int, int]], float]:
    """([(first pair, last pair)] of the runs of consecutive keyframe pairs in flagged
    windows, the largest pooled slope of any judged window (NaN when none is)).

    num, den: (P,) per pair as from :func:`translation_slope`; judged: (P,) bool, the pairs
    with enough translation flow. A window of ``cfg.pairs`` pairs with at least
    ``cfg.min_pairs`` judged is flagged when sum num / sum den over its judged pairs
    exceeds ``cfg.max_slope``; a run of such windows is one stretch, from its first to its
    last judged pair whose own slope exceeds 1."""
    P = len(num)
    if P < cfg.pairs:
        return [], float("nan")
    n = np.where(judged, num, 0.0)
    d = np.where(judged, den, 0.0)
    count = np.lib.stride_tricks.sliding_window_view(judged.astype(np.int64), cfg.pairs).sum(axis=1)
    pooled_num = np.lib.stride_tricks.sliding_window_view(n, cfg.pairs).sum(axis=1)
    pooled_den = np.lib.stride_tricks.sliding_window_view(d, cfg.pairs).sum(axis=1)
    ok = (count >= cfg.min_pairs) & (pooled_den > 0)
    slope = np.where(ok, pooled_num / np.where(pooled_den > 0, pooled_den, 1.0), np.nan)
    in_flagged_window = np.zeros(P, dtype=bool)
    for start in np.flatnonzero(ok & (slope > cfg.max_slope)):
        in_flagged_window[start:start + cfg.pairs] = True
    # A run of flagged windows is one stretch, trimmed to its first and last shortened pair:
    # the verdict covers the pairs inside it, not the right ones at its edges.
    own = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    shortened = judged & (own > 1.0)
    stretches = []
    for a, b in runs(np.flatnonzero(in_flagged_window).tolist()):
        inside = a + np.flatnonzero(shortened[a:b + 1])
        if inside.size:
            stretches.append((int(inside[0]), int(inside[-1])))
    largest = float(np.nanmax(slope)) if ok.any() else float("nan")
    return stretches, largest


def keyframe_slopes(T_cw: torch.Tensor, disps: torch.Tensor, grays: list[np.ndarray], intr: torch.Tensor,
                    k1: float, cfg: NormalFlowConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(num, den, judged), each (K-1,), of :func:`translation_slope` for every pair of
    consecutive keyframes: T_cw (K, 4, 4) world-to-camera, disps (K, H, W) BA inverse depth,
    intr the BA grid's intrinsics, k1 the lens' radial term, grays (K,) the keyframes' grey
    images at the flow resolution. A pair is judged when its induced translation flow is at
    least ``cfg.min_flow`` (640-px-wide frame pixels)."""
    K = len(grays)
    num, den, judged = np.zeros(max(K - 1, 0)), np.zeros(max(K - 1, 0)), np.zeros(max(K - 1, 0), dtype=bool)
    if K < 2:
        return num, den, judged
    shape = grays[0].shape[:2]
    h, w = shape
    at_infinity = torch.zeros_like(disps)
    grid = np.mgrid[0:h, 0:w][::-1].transpose(1, 2, 0)
    after = _prepared(grays[0], cfg)
    for p in range(K - 1):
        # Each keyframe prepared once: the second image of one pair is the first of the next.
        before, after = after, _prepared(grays[p + 1], cfg)
        induced = gr.predicted_flow(T_cw, disps, intr, p, p + 1, shape, k1)
        rotation = gr.predicted_flow(T_cw, at_infinity, intr, p, p + 1, shape, k1)
        translation = induced - rotation
        land = grid + induced
        valid = ((land[..., 0] >= 0) & (land[..., 0] <= w - 1) & (land[..., 1] >= 0) & (land[..., 1] <= h - 1)
                 & np.any(induced != 0, axis=-1))
        if not valid.any():
            continue
        length = float(np.linalg.norm(translation, axis=-1)[valid].mean()) * 640.0 / w
        num[p], den[p] = _slope(before, after, rotation, translation, valid, cfg)
        judged[p] = length >= cfg.min_flow and den[p] > 0
    return num, den, judged


__all__ = ["NormalFlowConfig", "gradient_flow", "keyframe_slopes", "short_stretches", "translation_slope"]
