"""Focal-length self-calibration for videos without intrinsics (phone clips).

The principal point at the image centre and fx = fy = f; each candidate f is scored by the
final robust reprojection cost of a dense BA of the first keyframes (on flows that do not
depend on f), with the plumb-line lens (``recon.poses.intrinsics.plumb_line``) held at its k1
for that f. :func:`search_focal` sweeps a log grid of fields of view, then golden-section
search on log f; :func:`estimate_focal` picks the keyframes and scores f. Rotation is what
makes f observable: a turning camera's flow bends with x^2 / f, which no depths imitate.
More: docs/poses.md#the-focal-search
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from recon.poses.ba import bundle as ba
from recon.poses.ba import motion_only
from recon.poses.config import FrontendConfig, disp_from_depth, make_geometry
from recon.poses.intrinsics.plumb_line import LensEstimate
from recon.poses.matching import flow as fl
from recon.poses.result import PriorSource, TrackingLostError, pool_depth

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass
class FocalSearch:
    """Result of :func:`search_focal`: the focal (pixels of the input frames), every
    (focal, score) evaluated, in order, and whether the minimum was bracketed."""

    focal: float
    evaluations: list[tuple[float, float]] = field(default_factory=list)
    bracketed: bool = True


def candidate_focals(width: int, height: int, fovs_deg=(100.0, 85.0, 72.0, 62.0, 53.0, 45.0, 38.0)) -> list[float]:
    """Focal lengths (pixels) giving the horizontal fields of view `fovs_deg` for a width-`width` image.

    The default spans ultra-wide (100 deg) to mild tele (38 deg), roughly geometric in f,
    which covers phone main and wide cameras and most action cameras after undistortion.
    """
    return [0.5 * width / math.tan(math.radians(fov) / 2.0) for fov in fovs_deg]


def search_focal(
    score: Callable[[float], float], candidates: list[float], tol: float = 0.003, max_evals: int = 12
) -> FocalSearch:
    """Minimise score(f) over f: sweep the candidates, then golden-section on log f between
    the neighbours of the best one until the bracket is within `tol` (relative) or
    `max_evals` further evaluations. A minimum at the end of the sweep is reported as not
    bracketed (the true focal may lie outside the candidates)."""
    cands = sorted(candidates)
    evals: list[tuple[float, float]] = []

    def f_eval(f: float) -> float:
        s = float(score(f))
        if not np.isfinite(s):
            s = float("inf")
        evals.append((f, s))
        return s

    scores = [f_eval(f) for f in cands]
    best = int(np.argmin(scores))
    bracketed = 0 < best < len(cands) - 1
    lo = math.log(cands[max(best - 1, 0)])
    hi = math.log(cands[min(best + 1, len(cands) - 1)])
    # Golden-section on log f inside [lo, hi].
    a, b = lo, hi
    c = b - GOLDEN * (b - a)
    d = a + GOLDEN * (b - a)
    fc, fd = f_eval(math.exp(c)), f_eval(math.exp(d))
    n = 2
    while (b - a) > tol and n < max_evals:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - GOLDEN * (b - a)
            fc = f_eval(math.exp(c))
        else:
            a, c, fc = c, d, fd
            d = a + GOLDEN * (b - a)
            fd = f_eval(math.exp(d))
        n += 1
    f_best, s_best = min(evals, key=lambda e: e[1])
    return FocalSearch(focal=float(f_best), evaluations=evals, bracketed=bracketed)


def estimate_focal(frames: list[np.ndarray], prior: PriorSource, cfg: FrontendConfig,
                   lens: LensEstimate | None = None) -> FocalSearch:
    """Focal length (pixels, fx = fy, principal point at the centre) minimising the BA cost
    of the first keyframes. frames: the first frames of the video (H, W, 3) uint8; lens: the
    lens measured from straight edges (None: a pinhole camera)."""
    height, width = frames[0].shape[:2]
    ba_geo = make_geometry((height, width), cfg.calib_stride)

    factor = cfg.calib_stride // cfg.calib_flow_stride
    flow_shape = (ba_geo.ba_shape[0] * factor, ba_geo.ba_shape[1] * factor)
    # Keyframes by the motion filter (independent of the focal length).
    grays = [fl.prepare_gray(f, flow_shape) for f in frames]
    kfs = [0]
    for i in range(1, len(frames)):
        fwd, _, cf, _ = fl.flow_pair(grays[kfs[-1]], grays[i], cfg.flow)
        if fl.mean_magnitude(fwd, cf) * (width / flow_shape[1]) * (640.0 / width) > cfg.keyframe_flow:
            kfs.append(i)
        if len(kfs) >= cfg.calib_keyframes:
            break
    if len(kfs) < 3:
        raise TrackingLostError(
            f"cannot estimate the focal length: the first {len(frames)} frames move too little "
            f"({len(kfs)} keyframes); pass intrinsics or a field of view", frame=0)
    pairs = [(a, b) for a in range(len(kfs)) for b in range(a + 1, min(a + 3, len(kfs)))]
    edge_data = []
    for a, b in pairs:
        fwd, bwd, cf, cb = fl.flow_pair(grays[kfs[a]], grays[kfs[b]], cfg.flow)
        edge_data.append((a, b, *fl.pool_edge(fwd, cf, factor, cfg.flow)))
        edge_data.append((b, a, *fl.pool_edge(bwd, cb, factor, cfg.flow)))
    ii = torch.tensor([e[0] for e in edge_data])
    jj = torch.tensor([e[1] for e in edge_data])
    whiten = [fl.flow_whitening(grays[k], factor, cfg.flow) for k in kfs]
    edges = ba.Edges(ii, jj, torch.stack([e[2] for e in edge_data]), torch.stack([e[3] for e in edge_data]),
                     whiten=None if whiten[0] is None else torch.stack(whiten))
    priors = [disp_from_depth(pool_depth(prior.get(k, frames[k]), ba_geo.ba_shape), cfg.prior_weight) for k in kfs]
    disp0 = torch.stack([p[0] for p in priors])
    pw = torch.stack([p[1] for p in priors])
    opts = replace(cfg.ba, iters=cfg.calib_iters, prior_weight=cfg.prior_weight)
    score_opts = replace(opts, huber_auto=0.0, huber=1.0)

    def score(f: float) -> float:
        k1 = lens.k1(f) if lens is not None else 0.0
        intr = ba_geo.ba_intrinsics((f, f, (width - 1) / 2.0, (height - 1) / 2.0))
        T = torch.eye(4, dtype=torch.float64).repeat(len(kfs), 1, 1)
        for k in range(1, len(kfs)):
            sel = (edges.ii == k - 1) & (edges.jj == k)
            e = edges.select(sel)
            Tk, _, _ = motion_only.align_frames(T[k - 1 : k], T[k - 1 : k], disp0[k - 1 : k], intr,
                                       torch.zeros(1, dtype=torch.int64), e.target, e.weight, k1=k1,
                                       whiten=None if e.whiten is None else e.whiten[k - 1 : k])
            T[k] = Tk[0]
        T, D, _ = ba.bundle_adjust(T, disp0.clone(), intr, edges, disp0, pw, None, opts, k1=k1)
        return ba.total_cost(T, D, intr, edges, disp0, pw, score_opts, k1=k1)

    return search_focal(score, candidate_focals(width, height), tol=cfg.calib_tol)
