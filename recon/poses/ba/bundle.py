"""Dense bundle adjustment over keyframe poses and per-pixel inverse depth (DROID-SLAM style).

:func:`bundle_adjust` minimises, over every flow edge (i, j) and BA pixel p of keyframe i,
``target_ij(p) - proj(T_j T_i^-1 X_i(p, d_i(p)))`` (pixels, confidence- and Huber-weighted),
each inverse depth tied to the prior by ``sqrt(prior_weight) * log(d / d0)`` (what makes the
result metric). Levenberg-Marquardt over world-to-camera poses (left updates), the inverse
depths (eliminated by :mod:`recon.poses.ba.schur`) and optionally k1 (``calibrate_k1``).
Shapes: K keyframes (poses (K, 4, 4), inverse depths (K, H, W)), E directed edges (ii, jj
(E,), targets (E, H, W, 2) = where pixel p of ii lands in jj, weights (E, H, W)).
More: docs/poses.md#the-dense-bundle-adjustment
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from recon.geometry import lie
from recon.geometry import projective as pj
from recon.poses.ba import schur
from recon.poses.ba.normal_equations import Edges, chunks, huber_cost, normal_equations

# Inverse depth is kept inside [MIN_DISP, MAX_DISP] (1/m): beyond 1 km nothing is
# measurable from a hand-held video, and nearer than 5 cm nothing is in focus.
MIN_DISP = 1e-3
MAX_DISP = 20.0
# |k1| beyond this is a fisheye, which one radial term cannot describe.
MAX_K1 = 0.5
# Residuals the robust threshold's median is taken of, at most (a subsample beyond).
MEDIAN_SAMPLES = 16_000_000


@dataclass
class BAOptions:
    """Solver settings.

    iters: Levenberg-Marquardt iterations.
    huber: robust threshold (BA-grid pixels): residuals beyond it count linearly. Flow
        outliers (occlusions, repeated texture, DIS failures) are what limits accuracy, so
        the default is adaptive (``huber_auto``): ``huber_auto`` times the median residual
        of confident pixels at the start of each call, clipped to [huber_min, huber].
    prior_weight: weight of the relative inverse-depth tie to the prior, per pixel, in
        units of squared BA pixels per squared relative error: 0.01 means a 10 % depth
        change costs like a 0.01 px reprojection error. Weak on purpose: the prior is only
        trusted where the images say nothing (scale, rotation-only motion, low parallax).
    lm: initial damping (relative to the diagonal); multiplied by 10 on a rejected step and
        divided by 3 on an accepted one.
    eps: absolute damping added to every pose and depth diagonal entry.
    pixel_dtype: dtype of the per-pixel Jacobians (float32 halves the time; the reduced
        camera system and the poses stay float64).
    calibrate_k1: also estimate the lens' radial term k1 (``projective.undistort``), one
        unknown shared by all keyframes; the edges must then be measured on the recorded
        images (``Edges.source`` None).
    k1_prior_weight: tie of k1 to its starting value, 0.5 w C (k1 - k1_0)^2 with C the total
        flow confidence of the edges (so that its strength does not depend on the size of
        the problem): 1e-3 makes k1 = 0.1 cost as much as every pixel being off by 0.003 px,
        nothing against what a lens does to the flow, but it holds k1 where the motion says
        nothing about the lens.
    device: where the solver runs ("cpu", "cuda", "cuda:N"); inputs and results stay where
        the caller keeps them. Most of a BA is per-pixel Jacobian products, which a GPU
        runs in far fewer steps than two CPU cores.
    """

    iters: int = 6
    huber: float = 1.0
    huber_auto: float = 1.5
    huber_min: float = 0.05
    prior_weight: float = 0.01
    lm: float = 1e-4
    eps: float = 1e-6
    pixel_dtype: torch.dtype = torch.float32
    calibrate_k1: bool = False
    k1_prior_weight: float = 1e-3
    device: str = "cpu"


@dataclass
class BAReport:
    """What one BA call did: cost per accepted iteration, rejected steps, final stats and
    the lens' radial term (estimated when calibrating, else as given)."""

    costs: list[float] = field(default_factory=list)
    rejected: int = 0
    rmse: float = float("nan")
    inlier_fraction: float = float("nan")
    huber: float = float("nan")
    k1: float = 0.0


def edge_residuals(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, edges: Edges, dtype: torch.dtype | None = None,
    k1: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual vectors (E, P, 2) = target - projection (whitened by ``edges.whiten``) and
    validity (E, P), computed in dtype (default: the poses' dtype), the edges undistorted
    with k1 first."""
    dtype = dtype or T_cw.dtype
    edges = Edges(edges.ii, edges.jj, edges.target.to(dtype), edges.weight, edges.source,
                  edges.whiten).undistorted(intr, k1)
    uv, valid = pj.reproject(T_cw.to(dtype), disps.to(dtype), intr.to(dtype), edges.ii, edges.jj,
                             edges.source_pixels(dtype))
    num = len(edges)
    r = (edges.target.to(dtype) - uv).reshape(num, -1, 2)
    L = edges.whitening(slice(None), dtype)
    if L is not None:
        r = (L @ r[..., None])[..., 0]
    return r, valid.reshape(num, -1)


@dataclass
class _Residuals:
    """Residual norms (E, P) and validity (E, P) of one BA state: evaluated once per state
    and shared by the robust threshold, the cost and the final statistics."""

    norm: torch.Tensor
    valid: torch.Tensor

    @classmethod
    def of(cls, T_cw, disps, intr, edges: Edges, dtype: torch.dtype, k1: float = 0.0) -> "_Residuals":
        if not len(edges):
            empty = torch.zeros(0, disps[0].numel(), dtype=dtype, device=disps.device)
            return cls(empty, empty.bool())
        # In chunks of edges: a whole graph's residuals at once would hold several (E, P, 3)
        # intermediates (gigabytes for a long video's global BA).
        E, P = len(edges), disps[0].numel()
        norm = torch.empty(E, P, dtype=dtype, device=disps.device)
        valid = torch.empty(E, P, dtype=torch.bool, device=disps.device)
        for sl in chunks(E, P):
            r, valid[sl] = edge_residuals(T_cw, disps, intr, edges.select(sl), dtype, k1)
            norm[sl] = torch.hypot(r[..., 0], r[..., 1])
        return cls(norm, valid)

    def _sums(self, edges: Edges, terms) -> list[float]:
        """Sums over every pixel-edge of terms(weight (n, P), valid (n, P), norm (n, P)
        float64) -> [tensor], a chunk of edges at a time (a whole graph's float64 planes
        would be gigabytes)."""
        totals = None
        P = self.norm.shape[1]
        for sl in chunks(len(edges), P):
            w = edges.weight[sl].reshape(-1, P).double()
            sums = [float(t.sum()) for t in terms(w, self.valid[sl], self.norm[sl].double())]
            totals = sums if totals is None else [a + b for a, b in zip(totals, sums)]
        return totals

    def cost(self, edges: Edges, huber: float) -> float:
        if not len(edges):
            return 0.0
        return self._sums(edges, lambda w, valid, rn: [w * valid * huber_cost(rn, huber)])[0]

    def adaptive_huber(self, edges: Edges, opts: "BAOptions") -> float:
        """huber_auto x the median over confident pixels, clipped to [huber_min, huber] (the
        residual norm of 2-D Gaussian noise has median 1.18 sigma)."""
        P = self.norm.shape[1]
        pieces = chunks(len(edges), P)
        confident = [(edges.weight[sl].reshape(-1, P) > 0.5) & self.valid[sl] for sl in pieces]
        total = sum(int(c.sum()) for c in confident)
        if not total:
            return opts.huber
        # Beyond MEDIAN_SAMPLES residuals (a long video's global BA: tens of millions) the
        # median is taken of every step-th one, which it cannot tell from the whole.
        step = -(-total // MEDIAN_SAMPLES)
        samples, seen = [], 0
        for sl, conf in zip(pieces, confident):
            values = self.norm[sl][conf]
            samples.append(values[(-seen) % step :: step])
            seen += values.numel()
        med = float(torch.cat(samples).median())
        return float(min(max(opts.huber_auto * med, opts.huber_min), opts.huber))

    def stats(self, edges: Edges, inlier: float) -> tuple[float, float]:
        """Confidence-weighted RMS residual (BA pixels) and the weight fraction within `inlier` px."""
        if not len(edges):
            return float("nan"), float("nan")
        total, weight, squares, inside = self._sums(edges, lambda w, valid, rn: [
            w, w * valid, w * valid * rn.clamp(max=10 * inlier) ** 2, w * valid * (rn < inlier)])
        if total <= 0:
            return float("nan"), 0.0
        return float(np.sqrt(squares / max(weight, 1e-9))), inside / total


@dataclass
class PosePrior:
    """A tie of the poses to given ones: 0.5 sum_k weight_k . log(T_k T0_k^-1)^2.

    T0: (K, 4, 4) world-to-camera poses to stay near; weight: (K, 6) per tangent component
    (translation, then rotation, in camera k's axes, as the left updates of the BA). For
    poses that come from elsewhere (a dataset, ARKit, a pose file) and are right overall but
    not to the pixel: the flow polishes their relative motion while the tie holds what flow
    cannot see (scale, slow drift, the gauge).
    """

    T0: torch.Tensor
    weight: torch.Tensor

    def to(self, device: torch.device | str) -> "PosePrior":
        return PosePrior(self.T0.to(device), self.weight.to(device))

    def residual(self, T_cw: torch.Tensor) -> torch.Tensor:
        """(K, 6) log(T_k T0_k^-1)."""
        return lie.se3_log(T_cw @ lie.inv(self.T0))

    def cost(self, T_cw: torch.Tensor) -> float:
        r = self.residual(T_cw)
        return float(0.5 * (self.weight * r * r).sum())


def prior_cost(disps: torch.Tensor, prior: torch.Tensor | None, prior_w: torch.Tensor | None) -> float:
    """The tie of inverse depth (K, H, W) to the prior: 0.5 sum prior_w log(d / d0)^2."""
    if prior is None:
        return 0.0
    rel = torch.log(disps.clamp(min=MIN_DISP) / prior.clamp(min=MIN_DISP))
    return float(0.5 * (prior_w * rel * rel).sum())


def total_cost(
    T_cw: torch.Tensor,
    disps: torch.Tensor,
    intr: torch.Tensor,
    edges: Edges,
    prior: torch.Tensor | None,
    prior_w: torch.Tensor | None,
    opts: BAOptions,
    k1: float = 0.0,
) -> float:
    """The BA objective: robust reprojection cost plus the prior tie (the edges undistorted
    with k1)."""
    res = _Residuals.of(T_cw, disps, intr, edges, opts.pixel_dtype, k1)
    return res.cost(edges, opts.huber) + prior_cost(disps, prior, prior_w)


def ba_step(
    T_cw: torch.Tensor,
    disps: torch.Tensor,
    intr: torch.Tensor,
    edges: Edges,
    prior: torch.Tensor | None,
    prior_w: torch.Tensor | None,
    fixed: torch.Tensor,
    opts: BAOptions,
    lm: float,
    sys: dict | None = None,
    fixed_disp: torch.Tensor | None = None,
    k1: float | None = None,
    k1_tie: tuple[float, float] = (0.0, 0.0),
    pose_prior: PosePrior | None = None,
) -> tuple[torch.Tensor, torch.Tensor, float | None, dict]:
    """One damped Gauss-Newton step. Returns the proposed poses (K, 4, 4), inverse depths
    (K, H, W), k1 (when estimated: k1 given, edges raw, tied to k1_tie = (start, weight)
    by 0.5 weight (k1 - start)^2; else None) and the normal equations used (reusable for a
    re-damped retry)."""
    K = disps.shape[0]
    height, width = disps.shape[-2:]
    P = height * width
    if sys is None:
        sys = normal_equations(T_cw, disps, intr, edges, opts.pixel_dtype, opts.huber, k1)
    C = sys["C"].clone()
    wz = sys["w"].clone()
    if prior is not None:
        d = disps.reshape(K, P).clamp(min=MIN_DISP)
        d0 = prior.reshape(K, P).clamp(min=MIN_DISP)
        pw = prior_w.reshape(K, P)
        # r = log(d / d0), dr/dd = 1 / d.
        C += pw / (d * d)
        wz += pw * torch.log(d0 / d) / d
    C = C * (1.0 + lm) + opts.eps
    Q = 1.0 / C
    # A held depth has infinite stiffness: it drops out of the Schur complement.
    free_disp = torch.ones(K, dtype=torch.bool, device=disps.device) if fixed_disp is None else ~fixed_disp
    S, g = schur.reduced_system(sys, edges.ii, edges.jj, Q, wz, K, free_disp)
    if pose_prior is not None:
        # r(dx) = log(exp(dx) T T0^-1) ~ r + dx for the left update.
        k = torch.arange(K, device=S.device)
        S[k, k] += torch.diag_embed(pose_prior.weight.to(S.dtype))
        g[:K] -= pose_prior.weight * pose_prior.residual(T_cw)
    if k1 is not None:
        start, weight = k1_tie
        S[K, K, 0, 0] += weight
        g[K, 0] += weight * (start - k1)
        fixed = torch.cat([fixed, fixed.new_zeros(1)])

    free = (~fixed).nonzero(as_tuple=True)[0]
    dx = torch.zeros(S.shape[0], 6, dtype=T_cw.dtype, device=S.device)
    if free.numel():
        Sf = S[free][:, free].permute(0, 2, 1, 3).reshape(6 * free.numel(), 6 * free.numel())
        Sf = 0.5 * (Sf + Sf.T)
        diag = Sf.diagonal()
        Sf = Sf + torch.diag(lm * diag + opts.eps)
        dx[free] = schur.solve_spd(Sf, g[free].reshape(-1)).reshape(-1, 6)
    dz = schur.back_substitute(sys, edges.ii, edges.jj, free_disp, dx, Q, wz).reshape(K, height, width)
    T_new = lie.se3_exp(dx[:K]) @ T_cw
    d_new = (disps + dz).clamp(MIN_DISP, MAX_DISP)
    k1_new = None if k1 is None else float(min(max(k1 + float(dx[K, 0]), -MAX_K1), MAX_K1))
    return T_new, d_new, k1_new, sys


def bundle_adjust(
    T_cw: torch.Tensor,
    disps: torch.Tensor,
    intr: torch.Tensor,
    edges: Edges,
    prior: torch.Tensor | None = None,
    prior_w: torch.Tensor | None = None,
    fixed: torch.Tensor | None = None,
    opts: BAOptions | None = None,
    fixed_disp: torch.Tensor | None = None,
    k1: float = 0.0,
    pose_prior: PosePrior | None = None,
) -> tuple[torch.Tensor, torch.Tensor, BAReport]:
    """Levenberg-Marquardt dense BA.

    T_cw: (K, 4, 4) float64 world-to-camera poses; disps: (K, H, W) inverse depth;
    intr: (4,) BA-grid intrinsics; edges: the frame graph, measured on the recorded images;
    prior: (K, H, W) prior inverse depth (or None); prior_w: (K, H, W) per-pixel tie
    weight (0 where the prior is invalid); fixed: (K,) bool poses held constant (at least
    one, or the gauge is free); fixed_disp: (K,) bool keyframes whose depth is held (old
    keyframes around a window); k1: the lens' radial term (0: pinhole), the start of its
    estimate when ``opts.calibrate_k1``.
    Returns the refined poses, inverse depths and a report (with k1).
    """
    opts = opts or BAOptions()
    K = disps.shape[0]
    if fixed is None:
        fixed = torch.zeros(K, dtype=torch.bool)
        fixed[0] = True
    home, device = T_cw.device, torch.device(opts.device)
    if device != home:
        T_cw, disps, intr, edges, fixed = T_cw.to(device), disps.to(device), intr.to(device), edges.to(device), \
            fixed.to(device)
        prior, prior_w, fixed_disp = (None if t is None else t.to(device) for t in (prior, prior_w, fixed_disp))
        pose_prior = None if pose_prior is None else pose_prior.to(device)
    calibrate = opts.calibrate_k1
    k1_tie = (k1, opts.k1_prior_weight * float(edges.weight.sum(dtype=torch.float64)) if calibrate else 0.0)
    if not calibrate:
        edges = edges.undistorted(intr, k1)

    def tie(T: torch.Tensor) -> float:
        return 0.0 if pose_prior is None else pose_prior.cost(T)

    def objective(res: _Residuals, T: torch.Tensor, d: torch.Tensor, k: float, huber: float) -> float:
        lens = 0.5 * k1_tie[1] * (k - k1_tie[0]) ** 2
        return res.cost(edges, huber) + prior_cost(d, prior, prior_w) + lens + tie(T)

    def residuals(T: torch.Tensor, d: torch.Tensor, k: float) -> _Residuals:
        return _Residuals.of(T, d, intr, edges, opts.pixel_dtype, k if calibrate else 0.0)

    report = BAReport()
    lm = opts.lm
    sys = None
    huber = opts.huber
    cost = float("nan")
    res = residuals(T_cw, disps, k1)
    for _ in range(opts.iters):
        if sys is None:
            # The robust threshold follows the residuals as they shrink; both sides of the
            # accept test below use the same threshold.
            if opts.huber_auto > 0 and len(edges):
                huber = res.adaptive_huber(edges, opts)
            cost = objective(res, T_cw, disps, k1, huber)
            if not report.costs:
                report.costs.append(cost)
        T_new, d_new, k1_new, sys = ba_step(T_cw, disps, intr, edges, prior, prior_w, fixed,
                                            replace(opts, huber=huber), lm, sys, fixed_disp,
                                            k1 if calibrate else None, k1_tie, pose_prior)
        k1_new = k1 if k1_new is None else k1_new
        res_new = residuals(T_new, d_new, k1_new)
        new_cost = objective(res_new, T_new, d_new, k1_new, huber)
        if new_cost <= cost:
            T_cw, disps, k1, res = T_new, d_new, k1_new, res_new
            report.costs.append(new_cost)
            lm = max(lm / 3.0, 1e-7)
            sys = None
        else:
            report.rejected += 1
            lm *= 10.0
            if lm > 1e4:
                break
    report.rmse, report.inlier_fraction = res.stats(edges, max(huber, 0.5))
    report.huber = huber
    report.k1 = k1
    return T_cw.to(home), disps.to(home), report
