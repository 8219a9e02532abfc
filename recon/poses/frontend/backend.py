"""The front end's map upkeep (DROID-SLAM's ``droid_backend`` and its factor graph's edge
building): flow edges between keyframes, bundle adjustment of a window or of the whole
graph (estimating the lens' radial term when asked), and the final metric rescale.

Functions over a :class:`~recon.poses.frontend.track_state.TrackState`; they change its graph,
its poses and its lens term.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import torch

from recon.geometry import lie
from recon.poses.ba import bundle as ba
from recon.poses.ba import graph as gr
from recon.poses.config import ba_pixels
from recon.poses.frontend.track_state import TrackState
from recon.poses.matching import flow as fl
from recon.poses.result import robust_log_mean

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- edges


def add_pair(state: TrackState, i: int, j: int, fwd, bwd, cf, cb, kind: str) -> bool:
    """Edges i -> j and j -> i from flows both ways (flow resolution), unless either is too
    unconfident to constrain anything (``min_edge_weight``)."""
    ti, wi = state.edge_targets(fwd, cf)
    tj, wj = state.edge_targets(bwd, cb)
    if float(wi.mean()) < state.cfg.min_edge_weight or float(wj.mean()) < state.cfg.min_edge_weight:
        return False
    state.graph.add_edge(i, j, ti, wi, kind)
    state.graph.add_edge(j, i, tj, wj, kind)
    return True


def link(state: TrackState, i: int, j: int, kind: str) -> bool:
    """Flow edges i <-> j, DIS seeded with the flow the current geometry predicts."""
    g = state.graph
    T, D = g.poses(), g.disps()
    init_ij = gr.predicted_flow(T, D, state.intr, i, j, state.geo.flow_shape, state.k1)
    init_ji = gr.predicted_flow(T, D, state.intr, j, i, state.geo.flow_shape, state.k1)
    flows = fl.flow_pair(g.gray[i], g.gray[j], state.cfg.flow, init_ij, init_ji)
    return add_pair(state, i, j, *flows, kind)


def link_proximity(state: TrackState, k: int, max_edges: int | None = None) -> None:
    """Up to max_edges links from keyframe k to older keyframes that, by the current poses
    and depths, see the same region (DROID's proximity edges)."""
    cfg = state.cfg
    max_edges = cfg.proximity_edges if max_edges is None else max_edges
    if max_edges <= 0:
        return
    candidates = [c for c in range(0, k - cfg.temporal_radius - 1) if not state.graph.connected(c, k)]
    if not candidates:
        return
    dist, frac = gr.induced_flow(state.graph.poses(), state.graph.disps(), state.intr, k, torch.tensor(candidates))
    max_dist = ba_pixels(cfg.proximity_max_flow, state.geo.ba_shape[1])
    chosen = gr.select_proximity(candidates, dist.numpy(), frac.numpy(), max_edges, max_dist,
                                 cfg.proximity_min_overlap, cfg.proximity_nms)
    for c in chosen:
        link(state, c, k, "proximity")


# ---------------------------------------------------------------------- bundle adjustment


def run_ba(state: TrackState, free_ids: list[int], iters: int, calibrate: bool = False) -> None:
    """BA of the keyframes free_ids (poses and depths) against every edge touching them; the
    other ends are held. calibrate: also estimate the lens' radial term k1."""
    g = state.graph
    _, edges = g.edge_list(free_ids)
    if not len(edges):
        return
    ids = sorted(set(edges.ii.tolist()) | set(edges.jj.tolist()) | set(free_ids))
    index = torch.full((len(g),), -1, dtype=torch.int64)
    index[ids] = torch.arange(len(ids))
    local = replace(edges.remap(index), whiten=g.whitening(ids))
    free = set(free_ids)
    fixed = torch.tensor([i not in free for i in ids])
    if not bool(fixed.any()):
        fixed[0] = True  # gauge: the first keyframe of the window
    fixed_disp = torch.tensor([i not in free for i in ids])
    prior, prior_w = g.priors(ids)
    opts = state.ba_options(iters)
    opts.calibrate_k1 = calibrate
    T, D, report = ba.bundle_adjust(g.poses(ids), g.disps(ids), state.intr, local, prior, prior_w, fixed,
                                    opts, fixed_disp, state.k1)
    g.set_state(ids, T, D)
    if calibrate:
        log.info("lens radial term k1 %.4f (was %.4f)", report.k1, state.k1)
        state.k1 = report.k1
    state.ba_reports.append(report)


def window_ba(state: TrackState, k: int) -> None:
    """BA of the last ``window`` keyframes up to k; the first time the graph is large
    enough, a BA of every keyframe that estimates the lens instead."""
    cfg = state.cfg
    if cfg.calibrate_lens and not state.lens_calibrated and len(state.graph) >= cfg.calibrate_after:
        run_ba(state, list(range(len(state.graph))), cfg.calibrate_iters, calibrate=True)
        state.lens_calibrated = True
        return
    run_ba(state, list(range(max(0, k + 1 - cfg.window), k + 1)), cfg.window_iters)


def global_ba(state: TrackState) -> None:
    """Proximity edges searched again with the final poses (a revisit is often recognisable
    only once the later keyframes are in place), then BA of the whole graph."""
    if len(state.graph) > 1:
        for k in range(len(state.graph)):
            link_proximity(state, k, state.cfg.final_proximity_edges)
        run_ba(state, list(range(len(state.graph))), state.cfg.global_iters, calibrate=state.cfg.calibrate_lens)


def metric_rescale(state: TrackState) -> float:
    """Rescale the world so that depths agree with the prior, robustly over all frames.

    Each keyframe contributes median(BA depth / prior depth); each aligned non-keyframe
    the median ratio of the keyframe points it sees (their z in its camera) to its own
    prior there (``frame_ratios``). Pooling over every frame, not only the keyframes,
    averages out more of the prior's per-frame scale error. Returns the factor applied.
    """
    g = state.graph
    prior, prior_w = g.priors()
    ratios = list(state.frame_ratios.values())
    for k in range(len(g)):
        ok = prior_w[k] > 0
        if ok.any():
            ratios.append(float(torch.median(g.disps([k])[0][ok] / prior[k][ok])))
    s = robust_log_mean(np.array(ratios)) if ratios else 1.0
    if not (np.isfinite(s) and s > 0):
        return 1.0
    g.scale_world(s)
    for i, T in state.frame_T.items():
        T = T.clone()
        T[:3, 3] *= s
        state.frame_T[i] = T
    return float(s)


def rescale_stretches(state: TrackState, breaks: list[tuple[int, float]]) -> None:
    """Bring each stretch of the trajectory after a scale break to the scale of the stretch
    before it (``scale_watch``): breaks: [(frame of the last keyframe before the break,
    factor)] in frame order. Every camera after that keyframe moves away from it by
    ``factor`` (camera centres C -> A + factor (C - A), A its centre; rotations kept) and
    the keyframes after it have their depth scaled alike, as do the non-keyframes' depth
    ratios the metric rescale pools. A Sim(3) per stretch, anchored at the break, the way a
    loop closure's Sim(3) joins two submaps of different scale (ORB-SLAM's monocular
    loop correction), with the depth prior standing in for the loop."""
    g = state.graph
    for anchor_frame, factor in breaks:
        if not (np.isfinite(factor) and factor > 0):
            continue
        anchor = lie.inv(state.frame_T[anchor_frame])[:3, 3]
        later = [i for i in state.frame_T if i > anchor_frame]
        for i, T in zip(later, _moved(torch.stack([state.frame_T[i] for i in later]), anchor, factor)):
            state.frame_T[i] = T
        ids = [k for k, frame in enumerate(g.frames) if frame > anchor_frame]
        if ids:
            g.set_state(ids, _moved(g.poses(ids), anchor, factor), g.disps(ids) / factor)
        for i in [i for i in state.frame_ratios if i > anchor_frame]:
            state.frame_ratios[i] /= factor


def _moved(T_cw: torch.Tensor, anchor: torch.Tensor, factor: float) -> torch.Tensor:
    """World-to-camera poses T_cw (N, 4, 4) with their camera centres C moved to
    anchor + factor (C - anchor) (anchor (3,)); rotations kept."""
    T_wc = lie.inv(T_cw)
    T_wc[:, :3, 3] = anchor + factor * (T_wc[:, :3, 3] - anchor)
    return lie.inv(T_wc)
