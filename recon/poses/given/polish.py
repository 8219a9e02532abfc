"""Polishing given camera poses against the images (flow bundle adjustment with a pose tie).

Poses that come with a video are right overall but rarely right to the pixel for the colour
camera, and multi-view stereo needs sub-pixel agreement, so they can be polished
(``--polish``; off by default, why: docs/decisions.md#given-poses-are-used-as-given): the
front end's dense flow bundle adjustment (``recon.poses.ba.bundle``, DROID-SLAM style) over each
frame's temporal neighbours and best stereo partners, with every pose weakly tied to its
given value (``ba.PosePrior``): the tie holds what flow cannot see (the gauge, the metric
scale, slow drift) and lets the flow decide relative motion. The lens' radial term can be
estimated on the way. ``benchmarks/refine_study.py`` has the study.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from tqdm.auto import tqdm

from mvs_core.views import select_sources
from recon.geometry import lie
from recon.poses.ba import bundle as ba
from recon.poses.config import disp_from_depth, make_geometry
from recon.poses.matching import flow as fl
from recon.poses.result import invert_poses, pool_depth


@dataclass
class PolishConfig:
    """Settings of :func:`polish_poses`.

    why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen
    """

    ba_stride: int = 8
    """The BA grid is the frame size / ba_stride (the flow runs at twice that resolution)."""
    temporal: int = 3
    """Each frame is linked to this many following frames."""
    partners: int = 3
    """... and to this many stereo partners chosen by triangulation angle and overlap on the prior depth.

    ``mvs_core.select_sources``: the pairs the refinement will match.
    """
    pose_weight: float = 1e-4
    """The strength of the tie to the given poses (weak, so that the flow decides relative motion).

    Moving a pose so that its pixels shift by one BA pixel costs pose_weight times as much as
    all its flow being off by one pixel (so the tie does not depend on how many edges a
    frame has).
    """
    prior_weight: float = 0.002
    """The tie of the BA depth to the depth prior (``ba.BAOptions``)."""
    iters: int = 6
    """Levenberg-Marquardt iterations of the joint BA."""
    depth_iters: int = 3
    """Iterations of the first fit, the BA's depth alone under the given poses."""
    min_gain: float = 1.5
    """The polished poses are kept only when the joint BA lowers the depth-only cost at least this many times.

    So poses that already agree with the frames (a rendered sequence, a good SfM model) are
    left exactly as given: polishing is limited by the flow's own noise.
    """
    calibrate_lens: bool = False
    """Estimate the lens' radial term k1 as well (off: the poses come with intrinsics).

    A fitted lens would override their calibration; why: docs/poses.md#given-poses
    """
    min_fit: float = 0.75
    """The share of the flow (BA inlier fraction) the poses that come out of the polish should explain.

    Below it ``info["disagreement"]`` says so (``pose_disagreement``; report.json only:
    MEDeA's gate judges the poses in use with ``recon.poses.given.pose_check``, which needs no
    polish). why: docs/validation.md
    """
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)
    """The DIS flow settings."""

    def to_dict(self) -> dict:
        return {k: v for k, v in asdict(self).items() if k != "flow"}


@dataclass
class PolishResult:
    """poses: (N, 4, 4) polished camera-to-world; lens_k1: the radial term they belong to
    (0 when not estimated); info: what the BA did and how far the poses moved, and
    info["disagreement"]: why multi-view depth should not trust the poses (None: it may)."""

    poses: np.ndarray
    lens_k1: float
    info: dict


def polish_pairs(depth: torch.Tensor, poses: torch.Tensor, intrinsics: torch.Tensor, cfg: PolishConfig) -> list:
    """Undirected frame pairs (a < b): temporal neighbours and stereo partners."""
    num = depth.shape[0]
    pairs = {(i, i + t) for i in range(num) for t in range(1, cfg.temporal + 1) if i + t < num}
    if cfg.partners > 0 and num > 2:
        partners, _ = select_sources(depth, poses, intrinsics, min(cfg.partners, num - 1))
        pairs |= {(min(i, j), max(i, j)) for i in range(num) for j in partners[i].tolist() if i != j}
    return sorted(pairs)


def pose_tie(T_cw: torch.Tensor, edges: ba.Edges, depth: np.ndarray, focal: float, weight: float) -> ba.PosePrior:
    """The tie of every pose to its given value, scaled as PolishConfig.pose_weight says."""
    num = T_cw.shape[0]
    conf = torch.zeros(num, dtype=torch.float64)
    per_edge = edges.weight.flatten(1).sum(1)
    conf.index_add_(0, edges.ii, per_edge).index_add_(0, edges.jj, per_edge)
    z = torch.tensor([float(np.median(d[d > 0])) if (d > 0).any() else 1.0 for d in depth], dtype=torch.float64)
    # A translation t moves pixels by ~ f t / z, a rotation w by ~ f w.
    per_axis = torch.stack([(focal / z) ** 2] * 3 + [torch.full_like(z, focal**2)] * 3, -1)
    return ba.PosePrior(T_cw.clone(), per_axis * conf[:, None] * weight)


def polish_poses(frames: np.ndarray, prior_depth: np.ndarray, poses: np.ndarray, intrinsics,
                 config: PolishConfig | None = None, progress: bool = True, device: str = "cpu") -> PolishResult:
    """Polish given poses (N, 4, 4) camera-to-world against the frames (N, H, W, 3) uint8.

    prior_depth: (N, h, w) metres (0 invalid), for pairing and for the BA's depth; intrinsics:
    (fx, fy, cx, cy) in pixels of the frames (pinhole, or the lens of ``lens_k1`` when
    calibrating). Frames with non-finite poses are left as they are.
    """
    cfg = config or PolishConfig()
    t0 = time.perf_counter()
    poses = np.asarray(poses, np.float64)
    good = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if len(good) < 2:
        return PolishResult(poses.copy(), 0.0, {"polished": False, "reason": "fewer than 2 valid poses",
                                                   "disagreement": None})
    geo = make_geometry(frames.shape[1:3], cfg.ba_stride)
    intr = geo.ba_intrinsics(intrinsics)
    pooled = np.stack([pool_depth(np.asarray(prior_depth[i], np.float32), geo.ba_shape) for i in good])
    c2w = torch.from_numpy(poses[good])
    pairs = polish_pairs(torch.from_numpy(pooled), c2w, intr.float(), cfg)
    grays = [fl.prepare_gray(frames[i], geo.flow_shape) for i in good]
    ii, jj, targets, weights = [], [], [], []
    for a, b in tqdm(pairs, desc="pose polish: flow", unit="pair", disable=not progress, leave=False):
        fwd, bwd, cf, cb = fl.flow_pair(grays[a], grays[b], cfg.flow)
        for src, dst, flow, conf in ((a, b, fwd, cf), (b, a, bwd, cb)):
            target, weight = fl.pool_edge(flow, conf, geo.flow_factor, cfg.flow)
            ii.append(src), jj.append(dst), targets.append(target), weights.append(weight)
    edges = ba.Edges(torch.tensor(ii), torch.tensor(jj), torch.stack(targets), torch.stack(weights))
    priors = [disp_from_depth(d, cfg.prior_weight) for d in pooled]
    disp0 = torch.stack([p[0] for p in priors])
    prior_w = torch.stack([p[1] for p in priors])
    T_cw = lie.inv(c2w)
    tie = pose_tie(T_cw, edges, pooled, float(intr[0]), cfg.pose_weight)
    opts = replace(ba.BAOptions(), iters=cfg.iters, prior_weight=cfg.prior_weight, calibrate_k1=cfg.calibrate_lens,
                   device=device)
    # What the given poses explain of the flow: the depth alone fitted under them.
    held = torch.ones(len(good), dtype=torch.bool)
    depth_only = replace(opts, iters=cfg.depth_iters, calibrate_k1=False)
    _, _, held_report = ba.bundle_adjust(T_cw, disp0.clone(), intr, edges, disp0, prior_w, held, depth_only)
    free = torch.zeros(len(good), dtype=torch.bool)  # the tie holds the gauge
    T_new, _, report = ba.bundle_adjust(T_cw, disp0.clone(), intr, edges, disp0, prior_w, free, opts, pose_prior=tie)
    gain = held_report.costs[-1] / max(report.costs[-1], 1e-12)
    accepted = gain >= cfg.min_gain
    out = poses.copy()
    if accepted:
        out[good] = invert_poses(T_new.numpy())
    moved = np.linalg.norm(out[good, :3, 3] - poses[good, :3, 3], axis=1)
    turned = lie.so3_log(torch.from_numpy(out[good, :3, :3] @ np.transpose(poses[good, :3, :3], (0, 2, 1))))
    info = {
        "polished": bool(accepted), "cost_gain": float(gain), "pairs": len(pairs), "edges": len(edges),
        "ba_rmse_px": report.rmse, "ba_inlier_fraction": report.inlier_fraction,
        "given_rmse_px": held_report.rmse, "given_inlier_fraction": held_report.inlier_fraction,
        "ba_cost": [report.costs[0], report.costs[-1]], "lens_k1": report.k1 if accepted else 0.0,
        "median_move_m": float(np.median(moved)), "max_move_m": float(moved.max()),
        "median_turn_deg": float(np.degrees(np.median(turned.norm(dim=-1).numpy()))),
        "seconds": time.perf_counter() - t0, "config": cfg.to_dict(),
    }
    info["disagreement"] = pose_disagreement(info, cfg.min_fit)
    if not accepted:
        fits = info["disagreement"] is None
        info["reason"] = (f"{'the given poses already explain the flow: ' if fits else ''}polishing them lowers the "
                          f"BA cost only {gain:.2f}x (< {cfg.min_gain}x); kept as given")
    return PolishResult(out, float(report.k1) if cfg.calibrate_lens and accepted else 0.0, info)


def fit_in_use(info: dict) -> float | None:
    """The share of the flow (BA inlier fraction) that fits the poses a polish returned
    (``PolishResult.info``): the polished ones, or the given ones when it kept them."""
    return info.get("ba_inlier_fraction" if info.get("polished") else "given_inlier_fraction")


def pose_disagreement(info: dict, min_fit: float) -> str | None:
    """Why multi-view depth should not trust the poses a polish returned, or None.

    info: PolishResult.info. The poses are those polished, or the given ones when the
    polish kept them; if under them less than ``min_fit`` of the flow fits (BA inlier
    fraction), the frames contradict the poses (a camera whose rows are read while it
    turns, poses timed or calibrated for another camera), and MEDeA's consistency terms
    would bend the depth to fit them.
    """
    polished = bool(info.get("polished"))
    fit = fit_in_use(info)
    if fit is None or not np.isfinite(fit) or fit >= min_fit:
        return None
    poses = "the polished poses" if polished else "the given poses, which polishing did not improve"
    return f"only {100 * fit:.0f}% of the flow between the frames fits {poses} (at least {100 * min_fit:.0f}% needed)"


__all__ = ["PolishConfig", "PolishResult", "fit_in_use", "polish_pairs", "polish_poses", "pose_disagreement",
           "pose_tie"]
