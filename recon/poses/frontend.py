"""The DROID-SLAM-style front end with classical parts: the entry point that drives its
roles over one state, and the focal-length search for videos without intrinsics.

The roles, after DROID-SLAM's files: ``track_state`` (the state, its ``depth_video``),
``motion_filter`` (keyframe policy), ``tracker`` (the local window: alignment, keyframes,
window BA, relocalisation; its ``droid_frontend``), ``backend`` (edges, global BA, lens
calibration, metric scale; its ``droid_backend``) and ``filler`` (the non-keyframes; its
``trajectory_filler``). Their pieces: ``flow`` (DIS + confidence), ``graph`` (keyframes,
edges, proximity), ``ba`` (Schur-complement LM, motion-only alignment), ``calib`` (focal
search), ``lie``, ``projective``; the settings are ``frontend_config``'s.

Resolutions: frames come at working resolution (H, W); flow runs at 1/4 and BA at 1/8
(the flow is pooled 2x2 with confidence weights). Internally poses are world-to-camera
(``T_cw``) as in the BA; the result is camera-to-world. The metric scale comes from the
depth prior: BA ties inverse depth to it (weakly, in logs), and a final robust rescale
makes the median keyframe depth agree with the prior across keyframes.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np
import torch
from tqdm import tqdm

from recon.errors import ReconInputError
from recon.poses import ba, backend, calib, filler
from recon.poses import flow as fl
from recon.poses.frontend_config import FrontendConfig, disp_from_depth, make_geometry
from recon.poses.result import (
    PoseResult,
    PriorSource,
    TrackingLostError,
    invert_poses,
    iterate_frames,
    parse_intrinsics,
    pool_depth,
)
from recon.poses.track_state import TrackState
from recon.poses.tracker import Tracker

log = logging.getLogger(__name__)

__all__ = ["FrontendConfig", "estimate_focal", "estimate_poses_frontend"]


# --------------------------------------------------------------------------- focal search


def estimate_focal(frames: list[np.ndarray], prior: PriorSource, cfg: FrontendConfig, progress: bool = False
                   ) -> calib.FocalSearch:
    """Focal length (pixels, fx = fy, principal point at the centre) minimising the BA cost
    of the first keyframes. frames: the first frames of the video (H, W, 3) uint8."""
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
    edges = ba.Edges(ii, jj, torch.stack([e[2] for e in edge_data]), torch.stack([e[3] for e in edge_data]))
    priors = [disp_from_depth(pool_depth(prior.get(k, frames[k]), ba_geo.ba_shape), cfg.prior_weight) for k in kfs]
    disp0 = torch.stack([p[0] for p in priors])
    pw = torch.stack([p[1] for p in priors])
    opts = replace(cfg.ba, iters=cfg.calib_iters, prior_weight=cfg.prior_weight)
    score_opts = replace(opts, huber_auto=0.0, huber=1.0)

    def score(f: float) -> float:
        intr = ba_geo.ba_intrinsics((f, f, (width - 1) / 2.0, (height - 1) / 2.0))
        T = torch.eye(4, dtype=torch.float64).repeat(len(kfs), 1, 1)
        for k in range(1, len(kfs)):
            sel = (edges.ii == k - 1) & (edges.jj == k)
            e = edges.select(sel)
            Tk, _, _ = ba.align_frames(T[k - 1 : k], T[k - 1 : k], disp0[k - 1 : k], intr,
                                       torch.zeros(1, dtype=torch.int64), e.target, e.weight)
            T[k] = Tk[0]
        T, D, _ = ba.bundle_adjust(T, disp0.clone(), intr, edges, disp0, pw, None, opts)
        return ba.total_cost(T, D, intr, edges, disp0, pw, score_opts)

    return calib.search_focal(score, calib.candidate_focals(width, height), tol=cfg.calib_tol)


# --------------------------------------------------------------------------- entry point


def estimate_poses_frontend(frames, prior_depth, intrinsics=None, progress: bool = True,
                            config: FrontendConfig | None = None) -> PoseResult:
    """Track a video with the dense front end.

    frames: (N, H, W, 3) uint8 RGB (or a sequence of such frames); prior_depth: (N, h, w)
    metric depth (0 invalid) or a callable ``prior(index, frame)``; intrinsics: (fx, fy,
    cx, cy) in pixels of the frames, or None to search the focal length (principal point
    at the centre). Returns camera-to-world poses of every frame, metric.

    diagnostics: method, num_keyframes, edges per kind, focal search (evaluations,
    bracketed), metric scale factor applied, per-frame status ("keyframe", "tracked",
    "recovered" (lost while tracking, aligned at the end), "interpolated" (no reliable
    flow: geodesic between keyframes)), relocalisation events, BA rmse / inlier fraction.
    Raises TrackingLostError when more than ``max_lost`` consecutive frames cannot be aligned.
    """
    cfg = config or FrontendConfig()
    threads = torch.get_num_threads()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    try:
        return _estimate(frames, prior_depth, intrinsics, progress, cfg)
    finally:
        torch.set_num_threads(threads)


def _estimate(frames, prior_depth, intrinsics, progress: bool, cfg: FrontendConfig) -> PoseResult:
    t0 = time.perf_counter()
    frames_list = [f for _, f in iterate_frames(frames)]
    if not frames_list:
        raise TrackingLostError("no frames to track", frame=0)
    prior = PriorSource(prior_depth)
    if not prior.is_callable and len(prior) != len(frames_list):
        raise ReconInputError(f"prior depth has {len(prior)} frames but the video has {len(frames_list)}")
    height, width = frames_list[0].shape[:2]
    diagnostics: dict = {"method": "frontend"}
    intr = parse_intrinsics(intrinsics)
    if intr is None:
        search = estimate_focal(frames_list[: 8 * cfg.calib_keyframes], prior, cfg, progress)
        intr = (search.focal, search.focal, (width - 1) / 2.0, (height - 1) / 2.0)
        diagnostics["focal_search"] = {"focal": search.focal, "bracketed": search.bracketed,
                                       "evaluations": search.evaluations}
        log.info("estimated focal length %.1f px (horizontal FOV %.1f deg)", search.focal,
                 math.degrees(2 * math.atan(width / (2 * search.focal))))
    state = TrackState(intr, make_geometry((height, width), cfg.ba_stride), prior, cfg)
    tracker = Tracker(state)
    tracker.start(0, frames_list[0])
    for i in tqdm(range(1, len(frames_list)), desc="tracking", unit="frame", disable=not progress, leave=False):
        tracker.track(i, frames_list[i])
    if state.lost_run:
        first = state.lost_run[0]
        if len(state.lost_run) > cfg.max_lost // 2 and state.lost_run[-1] == len(frames_list) - 1:
            raise TrackingLostError(f"tracking lost at frame {first} and not recovered before the end of the video",
                                    frame=first)
    backend.global_ba(state)
    filler.align_non_keyframes(state, lambda i: frames_list[i], len(frames_list), progress)
    g = state.graph
    for k, i in enumerate(g.frames):
        state.frame_T[i] = g.poses([k])[0]
    scale = backend.metric_rescale(state)
    T_cw = torch.stack([state.frame_T[i] for i in range(len(frames_list))]).numpy()
    poses = invert_poses(T_cw)
    last = state.ba_reports[-1] if state.ba_reports else ba.BAReport()
    status = [state.status.get(i, "tracked") for i in range(len(frames_list))]
    diagnostics.update(
        num_keyframes=len(g),
        edges=g.kinds(),
        metric_scale_factor=scale,
        frame_status=status,
        frame_inlier=[state.inlier.get(i, float("nan")) for i in range(len(frames_list))],
        feature_starts=state.feature_starts,
        lost_frames=[i for i, s in enumerate(status) if s in ("recovered", "interpolated")],
        relocalisations=state.reloc_events,
        ba_rmse_px=last.rmse,
        ba_inlier_fraction=last.inlier_fraction,
        ba_grid=state.geo.ba_shape[::-1],  # reported (w, h), as the run reports always had it
        lens_k1=state.k1,
    )
    depth = (1.0 / g.disps()).float().numpy()
    return PoseResult(
        poses=poses,
        intrinsics=tuple(float(v) for v in intr),
        keyframes=np.array(g.frames, dtype=np.int64),
        seconds=time.perf_counter() - t0,
        diagnostics=diagnostics,
        keyframe_depth=depth,
    )
