"""The front end's trajectory filler (DROID-SLAM's ``trajectory_filler``): once the
keyframes are final, every other frame is aligned, motion only, against the keyframes
before and after it (and the one tracking aligned it to, whose flow tracking parked, or
else is made again: the state keeps no flow per frame); a frame without reliable flow to
either gets the geodesic between them and is marked "interpolated".

``align_to_keyframes`` is shared with the SfM fallback, which registers the frames COLMAP
did not take the same way.
"""

from __future__ import annotations

import numpy as np
import torch
from tqdm import tqdm

from recon.geometry import lie
from recon.geometry import projective as pj
from recon.poses.ba import graph as gr
from recon.poses.ba import motion_only
from recon.poses.config import FrontendConfig, ba_pixels
from recon.poses.frontend.track_state import TrackState
from recon.poses.matching import flow as fl


def align_non_keyframes(state: TrackState, frames_lookup, num_frames: int, progress: bool) -> None:
    """Motion-only alignment of every non-keyframe against the keyframes before and after it."""
    for i, (T, ok, ratio, inlier) in realigned(state, frames_lookup, num_frames, progress).items():
        state.frame_T[i] = T
        if np.isfinite(inlier):
            state.inlier[i] = inlier
        if ok:
            if np.isfinite(ratio):
                state.frame_ratios[i] = ratio
            if state.status.get(i) == "lost":
                state.status[i] = "recovered"
        else:
            state.status[i] = "interpolated"


def realigned(state: TrackState, frames_lookup, num_frames: int, progress: bool = False, first: int = 0) -> dict:
    """``align_to_keyframes``'s results for the non-keyframes of frames [first, num_frames)
    against the graph as it is, the state left as it was."""
    g = state.graph
    T_kf = g.poses()
    kf_frames = np.array(g.frames)
    jobs = [i for i in range(first, num_frames) if state.status.get(i) != "keyframe"]

    def init_of(i: int, prev: int, nxt: int) -> torch.Tensor:
        if i in state.rel:
            return state.rel[i] @ T_kf[state.refs[i][0]]
        return _between(i, kf_frames, T_kf)

    prior_of = None if state.prior.is_callable else (lambda i: state.prior_disp(i, None))
    return align_to_keyframes(jobs, lambda i: fl.prepare_gray(frames_lookup(i), state.geo.flow_shape),
                              kf_frames, g.gray, T_kf, g.disps(), state.intr, state.cfg, init_of, state.refs,
                              prior_of, progress, state.k1, state.tracked_edge)


def _between(i: int, kf_frames: np.ndarray, T_kf: torch.Tensor) -> torch.Tensor:
    """Frame i's pose (4, 4) on the geodesic between its keyframes (lie.interpolated_pose)."""
    return torch.from_numpy(lie.interpolated_pose(i, kf_frames, np.asarray(T_kf, dtype=np.float64)))


def align_to_keyframes(jobs, gray_of, kf_frames, kf_gray, T_kf, disp_kf, intr, cfg: FrontendConfig, init_of=None,
                       known=None, prior_of=None, progress: bool = False, k1: float = 0.0,
                       tracked_edge=None) -> dict:
    """Motion-only alignment of frames `jobs` against their neighbouring keyframes.

    kf_frames (K,) sorted frame indices of the keyframes, kf_gray their flow-resolution grey
    images, T_kf (K, 4, 4) world-to-camera poses, disp_kf (K, H, W) BA-grid inverse depth.
    gray_of(i): frame i's flow-resolution grey image. init_of(i, prev, nxt): initial pose
    (default: geodesic between the keyframes before and after). known: {i: (k, seeded)}
    frames tracking aligned to keyframe k, with DIS seeded or not: that flow is made again
    and used without the correlation checks, which it passed while tracking (unseeded, it
    is the same flow; seeded, the seed now comes from the initial pose and the final
    keyframe depth: with every frame seeded, poses moved by at most 1.4 mm); the keyframes
    before and after such a frame are left out when, by its tracked pose, they do not see
    its view (a revisit: they were made elsewhere in the room). prior_of(i):
    (prior inverse depth, tie weight) on the BA grid, for the per-frame metric ratio
    (``frame_depth_ratios``); k1: the lens' radial term. tracked_edge(i, k): the unseeded
    flow tracking made from keyframe k to frame i, pooled to the BA grid (target, weight),
    or None: used instead of making it again.
    Returns {i: (T_cw (4, 4), ok, ratio, inlier)}: inlier is the share of the flow confidence
    the alignment explains (NaN without flow to any keyframe); ok is False when the alignment kept less than
    ``cfg.lost_inlier`` of its flow confidence (a keyframe whose flow fails
    ``cfg.min_match_correlation`` is left out), and T_cw is then the initial pose.
    """
    known = known or {}
    init_of = init_of or (lambda i, p, n: _between(i, kf_frames, T_kf))
    results = {}
    K = len(kf_frames)
    # The keyframes' residual factors (flow.flow_whitening), made once each as needed.
    factors: dict[int, torch.Tensor | None] = {}

    def whitening(k: int) -> torch.Tensor | None:
        if k not in factors:
            factors[k] = fl.flow_whitening(kf_gray[k], 2, cfg.flow)
        return factors[k]

    for start in tqdm(range(0, len(jobs), cfg.align_chunk), desc="aligning frames", unit="batch",
                      disable=not progress, leave=False):
        chunk = jobs[start : start + cfg.align_chunk]
        frame_idx, kfs, targets, weights, T_init = [], [], [], [], []
        for m, i in enumerate(chunk):
            nxt = int(np.searchsorted(kf_frames, i))
            prev = nxt - 1
            T_init.append(init_of(i, prev, nxt))
            gray = None
            if i in known:
                k, seeded = known[i]
                edge = None if seeded or tracked_edge is None else tracked_edge(i, k)
                if edge is None:
                    gray = gray_of(i)
                    seed = gr.seed_flows(T_kf[k], T_init[-1], disp_kf[k], intr, gray.shape, k1) if seeded else ()
                    fwd, _, cf, _ = fl.flow_pair(kf_gray[k], gray, cfg.flow, *seed)
                    edge = fl.pool_edge(fwd, cf, 2, cfg.flow)
                t, w = edge
                frame_idx.append(m), kfs.append(k), targets.append(t), weights.append(w)
            for k in (prev, nxt):
                if k < 0 or k >= K or (i in known and known[i][0] == k):
                    continue
                if i in known and not _sees(T_kf[k], disp_kf[k], intr, T_init[-1], cfg):
                    # Tracked against an older keyframe on a revisit: the keyframes next to it
                    # in time were made elsewhere in the room.
                    continue
                gray = gray_of(i) if gray is None else gray
                fwd, _, cf, _ = fl.flow_pair(kf_gray[k], gray, cfg.flow)
                if (fl.match_correlation(kf_gray[k], gray, fwd, cf) < cfg.min_match_correlation
                        or fl.local_correlation(kf_gray[k], gray, fwd, cf) < cfg.min_local_correlation):
                    continue
                t, w = fl.pool_edge(fwd, cf, 2, cfg.flow)
                frame_idx.append(m), kfs.append(k), targets.append(t), weights.append(w)
        if not kfs:
            results.update({i: (T_init[m], False, float("nan"), float("nan")) for m, i in enumerate(chunk)})
            continue
        kt, ft = torch.tensor(kfs), torch.tensor(frame_idx)
        wt = torch.stack(weights).double()
        whiten = [whitening(k) for k in kfs]
        T, _, inl = motion_only.align_frames(torch.stack(T_init), T_kf[kt], disp_kf[kt], intr, ft,
                                    torch.stack(targets).double(), wt, huber=1.0, k1=k1,
                                    whiten=None if whiten[0] is None else torch.stack(whiten))
        ratio = np.full(len(chunk), np.nan)
        if prior_of is not None:
            disp_w = [prior_of(i) for i in chunk]
            prior = torch.stack([d for d, _ in disp_w])
            prior_ok = torch.stack([w for _, w in disp_w]) > 0
            ratio = frame_depth_ratios(T, T_kf[kt], disp_kf[kt], intr, ft, wt, prior, prior_ok, k1)
        for m, i in enumerate(chunk):
            ok = float(inl[m]) >= cfg.lost_inlier
            results[i] = (T[m] if ok else T_init[m], ok, float(ratio[m]), float(inl[m]))
    return results


def _sees(T_kf: torch.Tensor, disp_kf: torch.Tensor, intr: torch.Tensor, T: torch.Tensor,
          cfg: FrontendConfig) -> bool:
    """Whether a keyframe (pose (4, 4), BA depth (H, W)) sees a camera at pose T (4, 4) as a
    proximity edge would: overlap at least ``proximity_min_overlap``, induced flow within
    ``proximity_max_flow``."""
    _, motion, frac = gr.parallax_into(T_kf[None], disp_kf[None], intr, T)
    max_flow = ba_pixels(cfg.proximity_max_flow, disp_kf.shape[-1])
    return bool(frac[0] >= cfg.proximity_min_overlap and motion[0] <= max_flow)


def frame_depth_ratios(T: torch.Tensor, T_kf: torch.Tensor, disp_kf: torch.Tensor, intr: torch.Tensor,
                       frame: torch.Tensor, weight: torch.Tensor, prior: torch.Tensor, prior_ok: torch.Tensor,
                       k1: float = 0.0) -> np.ndarray:
    """Median ratio (M,) of geometric to prior inverse depth per frame.

    T: (M, 4, 4) world-to-camera frame poses; T_kf (L, 4, 4), disp_kf (L, H, W): keyframes
    observed by frame[l] (L,) with flow confidence weight (L, H, W); prior, prior_ok:
    (M, H, W) the frames' prior inverse depth and its validity on the BA grid. Keyframe
    pixels with confidence > 0.5 are moved into the frame, and its prior is read (nearest
    pixel) where they land (through the lens k1). NaN for frames without such pixels.
    """
    L = T_kf.shape[0]
    height, width = disp_kf.shape[-2:]
    uv, _ = pj.undistort(pj.pixel_grid(height, width, dtype=T.dtype), intr, k1)
    X = pj.backproject(uv[None], disp_kf, intr).reshape(L, -1, 4)
    Xf = pj.transform(T[frame] @ lie.inv(T_kf), X)
    proj, valid = pj.project(Xf, intr)
    proj = pj.distort(proj, intr, k1)
    ui, vi = proj[..., 0].round().long(), proj[..., 1].round().long()
    valid &= (ui >= 0) & (ui < width) & (vi >= 0) & (vi < height) & (weight.reshape(L, -1) > 0.5)
    ui, vi = ui.clamp(0, width - 1), vi.clamp(0, height - 1)
    f = frame[:, None].expand_as(ui)
    valid &= prior_ok[f, vi, ui]
    geo_disp = Xf[..., 3] / Xf[..., 2].clamp(min=1e-9)
    ratio = geo_disp / prior[f, vi, ui]
    out = np.full(T.shape[0], np.nan)
    for m in range(T.shape[0]):
        sel = valid & (f == m)
        if int(sel.sum()) >= 16:
            out[m] = float(ratio[sel].median())
    return out
