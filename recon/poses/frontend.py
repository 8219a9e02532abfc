"""The DROID-SLAM-style front end with classical parts: motion filter, keyframe graph, DIS flow
edges, sliding-window dense BA while tracking, one global BA at the end, and motion-only
alignment of every non-keyframe against its neighbouring keyframes.

This module owns the *driver*: which frames become keyframes, which edges are built, when
BA runs, how tracking loss is detected and recovered, and the focal-length search for
videos without intrinsics. The pieces it drives live next to it: ``flow`` (DIS +
forward-backward confidence), ``graph`` (keyframes, edges, proximity), ``ba`` (Schur
complement LM, motion-only alignment), ``calib`` (focal search), ``lie``, ``projective``.

Resolutions: frames come at working resolution (W x H); flow runs at 1/4 and BA at 1/8
(the flow is pooled 2x2 with confidence weights). Internally poses are world-to-camera
(``T_cw``) as in the BA; the result is camera-to-world. The metric scale comes from the
depth prior: BA ties inverse depth to it (weakly, in logs), and a final robust rescale
makes the median keyframe depth agree with the prior across keyframes.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from tqdm import tqdm

from recon.errors import ReconInputError
from recon.poses import ba
from recon.poses import calib
from recon.poses import flow as fl
from recon.poses import graph as gr
from recon.poses import lie
from recon.poses import projective as pj
from recon.poses.result import (
    PoseResult,
    PriorSource,
    TrackingLostError,
    invert_poses,
    iterate_frames,
    parse_intrinsics,
    pool_depth,
    robust_log_mean,
)

log = logging.getLogger(__name__)


@dataclass
class FrontendConfig:
    """Front-end settings (defaults tuned on the synthetic room, 7-Scenes and TUM fr1).

    ba_stride: BA grid = working resolution / ba_stride (DROID: 8); flow runs at twice
        the BA resolution and is pooled.
    keyframe_flow: a frame becomes a keyframe when the mean *parallax* flow from the last
        keyframe (its flow minus the flow its tracked rotation alone explains) exceeds this
        many pixels at working resolution (scaled for other widths as if the frames were
        640 px wide). Rotation adds no depth information, only cost: under near-pure
        rotation (TUM fr1/rpy) plain mean flow made 88 of 100 frames keyframes.
    keyframe_max_flow: ... or when the mean flow itself exceeds this many pixels, so that a
        rotating camera still gets keyframes before the overlap runs out.
    temporal_radius: each new keyframe is linked (both directions) to this many previous
        keyframes. Linking across the whole window (radius >= window) ties it to held
        keyframes as well, which holds the drift: on 7-Scenes (Sim(3) ATE at keyframe_flow
        15 / 16 / 17) radius 4 with window 6 gave 3.24 / 3.06 / 3.50 cm, radius 5 with
        window 5 3.30 / 2.90 / 3.38 and radius 6 with window 5 2.85 / 2.86 / 3.17; on TUM
        fr1/rpy radius 5 costs what radius 4 did, radius 6 ~10 % more (1.60 cm).
    proximity_edges, proximity_max_flow, proximity_min_overlap, proximity_nms: up to that
        many extra links to older keyframes that, by the current poses and depths, see the
        same region (mean induced flow below proximity_max_flow working-resolution pixels
        at 640 px width, overlap above proximity_min_overlap), not within proximity_nms
        keyframes of each other (DROID's proximity edges / loop closures).
    final_proximity_edges: before the global BA, every keyframe gets up to this many such
        links again, found with the final poses and depths (a revisit is often recognisable
        only once the later keyframes are in place). On 7-Scenes this and temporal radius 4
        took the Sim(3) ATE from 5.5 to 4.6 cm.
    min_edge_weight: an edge whose mean flow confidence is below this is dropped.
    window: keyframes optimised by the sliding-window BA while tracking (see
        temporal_radius).
    window_iters, global_iters: LM iterations of the window and final global BA. Two per
        window are as accurate as four on 7-Scenes and TUM (the window is re-optimised as it
        slides, and the global BA finishes the job) at 60 % of the tracking time.
    prior_weight: tie of BA inverse depth to the prior (see ``ba.BAOptions``). Weak, so
        that the flow shapes the depth and the prior mostly holds the scale: on 7-Scenes
        0.01 -> 0.002 took the Sim(3) ATE from 3.43 to 3.04 cm (0.005: 3.37, 0.001: 3.05),
        with TUM fr1/rpy and the synthetic room unchanged.
    lens_k1: the lens' radial term k1 when known (``projective.undistort``; 0 = pinhole):
        flow is measured on the frames as recorded and undistorted in the BA.
    calibrate_lens: estimate k1 (starting from lens_k1) in a BA over all keyframes once
        ``calibrate_after`` keyframes exist (``calibrate_iters`` LM iterations; tracking
        goes on with it) and again in the final global BA. A lens the model ignores makes
        the BA trade rotation for translation: on 7-Scenes (whose colour images are not
        undistorted) rotations came out ~11 % short and the path ~20 % long.
    min_match_correlation: a frame whose flow from a keyframe joins grey levels correlated
        less than this (``flow.match_correlation``) is not aligned to it. Pixelwise flow
        confidence passes unrelated images (random-noise frames matched a keyframe with
        mean confidence 0.16 and 99 % inliers); their correlation was 0.09-0.17, that of
        every tracked frame of TUM fr1/rpy and 7-Scenes 0.988 or more.
    lost_inlier: a frame whose alignment keeps less than this fraction of the flow
        confidence within the robust threshold counts as lost.
    max_lost: consecutive lost frames (after relocalisation attempts) that stop tracking.
    reloc_candidates: older keyframes tried when a frame is lost against the last one.
    calib_keyframes: keyframes used by the focal-length search.
    calib_stride, calib_flow_stride: BA grid and flow strides of the focal search. The
        flow is finer than while tracking: f shows only in the slight bending of the flow
        field (x^2 / f), and DIS at 1/4 resolution smooths it enough to bias f by ~5 %
        (with exact flow the search lands within 0.1 % on the synthetic room).
    calib_tol, calib_iters: golden-section bracket width on log f at which the search stops
        (0.01 = 1 %), and LM iterations per evaluated focal length.
    align_chunk: non-keyframes aligned per batch at the end (memory bound).
    torch_threads: intra-op threads while tracking (restored after); None leaves torch's
        setting alone. The BA's pixel-plane products are large enough for threads to pay:
        on the 2-core machine two threads took TUM fr1/rpy from 0.23-0.28 to 0.20-0.21 s
        per frame and 7-Scenes from 0.126 to 0.103. Set 1 when other work shares the cores.
    """

    ba_stride: int = 8
    keyframe_flow: float = 16.0
    keyframe_max_flow: float = 48.0
    temporal_radius: int = 6
    proximity_edges: int = 2
    proximity_max_flow: float = 96.0
    proximity_min_overlap: float = 0.5
    proximity_nms: int = 2
    final_proximity_edges: int = 4
    min_edge_weight: float = 0.15
    window: int = 5
    window_iters: int = 2
    global_iters: int = 8
    prior_weight: float = 0.002
    lens_k1: float = 0.0
    calibrate_lens: bool = True
    calibrate_after: int = 20
    calibrate_iters: int = 4
    min_match_correlation: float = 0.5
    lost_inlier: float = 0.25
    max_lost: int = 10
    reloc_candidates: int = 4
    calib_keyframes: int = 10
    calib_stride: int = 8
    calib_flow_stride: int = 2
    calib_tol: float = 0.01
    calib_iters: int = 6
    align_chunk: int = 64
    torch_threads: int | None = None
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)
    ba: ba.BAOptions = field(default_factory=ba.BAOptions)


@dataclass
class _Geometry:
    """Image sizes and intrinsics at the three resolutions."""

    width: int
    height: int
    flow_size: tuple[int, int]  # (w, h)
    ba_size: tuple[int, int]  # (w, h)
    flow_factor: int  # flow pixels per BA pixel

    @property
    def px_scale(self) -> float:
        """Working-resolution pixels per flow pixel, normalised to a 640 px wide frame."""
        return (self.width / self.flow_size[0]) * (640.0 / self.width)

    def ba_intrinsics(self, intrinsics) -> torch.Tensor:
        sx = self.ba_size[0] / self.width
        sy = self.ba_size[1] / self.height
        return torch.tensor(pj.scale_intrinsics(intrinsics, sx, sy), dtype=torch.float64)


def make_geometry(width: int, height: int, ba_stride: int) -> _Geometry:
    wb, hb = max(width // ba_stride, 4), max(height // ba_stride, 4)
    return _Geometry(width, height, (2 * wb, 2 * hb), (wb, hb), 2)


def _disp_from_depth(depth: np.ndarray, prior_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse depth (h, w) float64 of a pooled depth (h, w) and its tie weight (0 where invalid)."""
    d = torch.from_numpy(depth.astype(np.float64))
    valid = d > 0
    disp = torch.where(valid, 1.0 / d.clamp(min=1e-6), torch.zeros_like(d))
    fill = float(disp[valid].median()) if valid.any() else 1.0
    disp = torch.where(valid, disp, torch.full_like(disp, fill)).clamp(ba.MIN_DISP, ba.MAX_DISP)
    return disp, valid.double() * prior_weight


def _scaled_pixels(cfg_value: float, geo: _Geometry) -> float:
    """A threshold given in 640-px-wide working pixels, in flow pixels."""
    return cfg_value / geo.px_scale


class _Tracker:
    """State of one tracking run: the graph, per-frame references, lost-frame bookkeeping."""

    def __init__(self, intrinsics, geo: _Geometry, prior: PriorSource, cfg: FrontendConfig):
        self.cfg = cfg
        self.geo = geo
        self.prior = prior
        self.intrinsics = intrinsics
        self.intr = geo.ba_intrinsics(intrinsics)
        self.graph = gr.FrameGraph((geo.ba_size[1], geo.ba_size[0]))
        # Per non-keyframe: (keyframe id, BA target, weight) of the flow from that keyframe.
        self.refs: dict[int, tuple[int, torch.Tensor, torch.Tensor]] = {}
        self.frame_T: dict[int, torch.Tensor] = {}
        # Tracked pose relative to its reference keyframe (re-anchored after the global BA).
        self.rel: dict[int, torch.Tensor] = {}
        self.frame_ratios: dict[int, float] = {}
        self.status: dict[int, str] = {}
        self.ref_kf = 0
        self.lost_run: list[int] = []
        self.reloc_events: list[dict] = []
        self.ba_reports: list[ba.BAReport] = []
        # The last tracked non-keyframe (index, frame, grey, pose, keyframe, flows): promoted
        # to a keyframe when the next frame cannot be aligned to the reference keyframe.
        self.previous: tuple | None = None
        self.last_failure = ""
        self.k1 = cfg.lens_k1
        self.lens_calibrated = False

    # ------------------------------------------------------------------ helpers

    def _ba_opts(self, iters: int) -> ba.BAOptions:
        return replace(self.cfg.ba, iters=iters, prior_weight=self.cfg.prior_weight)

    def _prior_disp(self, index: int, frame: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        depth = pool_depth(self.prior.get(index, frame), self.geo.ba_size)
        return _disp_from_depth(depth, self.cfg.prior_weight)

    def _edge_targets(self, flow: np.ndarray, conf: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        return fl.pool_edge(flow, conf, self.geo.flow_factor, self.cfg.flow)

    def _align(self, T_init: torch.Tensor, kf: int, target: torch.Tensor, weight: torch.Tensor):
        """Pose (4, 4) of one frame against keyframe kf, and its inlier fraction."""
        T, _, inl = ba.align_frames(
            T_init[None], self.graph.poses([kf]), self.graph.disps([kf]), self.intr, torch.zeros(1, dtype=torch.int64),
            target[None].double(), weight[None].double(), huber=1.0, k1=self.k1,
        )
        return T[0], float(inl[0])

    # ------------------------------------------------------------------ tracking

    def start(self, index: int, frame: np.ndarray) -> None:
        disp, pw = self._prior_disp(index, frame)
        gray = fl.prepare_gray(frame, self.geo.flow_size)
        self.graph.add_keyframe(index, gray, torch.eye(4, dtype=torch.float64), disp, disp.clone(), pw)
        self.frame_T[index] = torch.eye(4, dtype=torch.float64)
        self.status[index] = "keyframe"

    def track(self, index: int, frame: np.ndarray) -> None:
        """Motion filter, alignment and (when the flow is large) a new keyframe for one frame."""
        gray = fl.prepare_gray(frame, self.geo.flow_size)
        T0 = self.frame_T.get(index - 1, self.graph.poses([self.ref_kf])[0])
        found = self._against(self.ref_kf, gray, T0)
        if found is None and self._promote_previous(index):
            # The reference keyframe is too far (fast rotation, blur): the previous frame,
            # which still tracked, becomes a keyframe and this frame is aligned to it.
            found = self._against(self.ref_kf, gray, T0)
        if found is None:
            found = self._relocalise(index, gray, T0)
            if found is None:
                self._lost(index)
                return
            self.ref_kf = found[0]
        kf, T, fwd, bwd, cf, cb, target, weight = found
        self.lost_run = []
        self.frame_T[index] = T
        self.refs[index] = (kf, target, weight)
        self.rel[index] = T @ lie.inv(self.graph.poses([kf])[0])
        self.status[index] = "tracked"
        motion = fl.mean_magnitude(fwd, cf) * self.geo.px_scale
        parallax = fl.mean_magnitude(fwd - self._rotation_flow(self.rel[index], fwd.shape[:2]), cf) * self.geo.px_scale
        if parallax > self.cfg.keyframe_flow or motion > self.cfg.keyframe_max_flow:
            self._add_keyframe(index, frame, gray, T, kf, (fwd, bwd, cf, cb))
            self.previous = None
        else:
            self.previous = (index, frame, gray, T, kf, (fwd, bwd, cf, cb))

    def _against(self, kf: int, gray: np.ndarray, T0: torch.Tensor):
        """Flow from keyframe kf to a frame and the frame's pose aligned to it, or None when
        the flow or the alignment is not to be trusted (``last_failure`` says why)."""
        cfg = self.cfg
        fwd, bwd, cf, cb = fl.flow_pair(self.graph.gray[kf], gray, cfg.flow)
        correlation = fl.match_correlation(self.graph.gray[kf], gray, fwd, cf)
        if correlation < cfg.min_match_correlation:
            self.last_failure = f"image correlation along the flow {correlation:.2f} < {cfg.min_match_correlation}"
            return None
        target, weight = self._edge_targets(fwd, cf)
        if float(weight.mean()) < cfg.min_edge_weight:
            self.last_failure = f"mean flow confidence {float(weight.mean()):.2f} < {cfg.min_edge_weight}"
            return None
        T, inl = self._align(T0, kf, target, weight)
        if inl < cfg.lost_inlier:
            self.last_failure = f"inlier fraction {inl:.2f} < {cfg.lost_inlier}"
            return None
        return kf, T, fwd, bwd, cf, cb, target, weight

    def _promote_previous(self, index: int) -> bool:
        """Make the previous frame a keyframe when it tracked (and is not one already)."""
        if self.previous is None or self.previous[0] != index - 1:
            return False
        prev, frame, gray, T, kf, flows = self.previous
        self.previous = None
        log.info("frame %d: keyframe at frame %d too far, the previous frame becomes a keyframe", index,
                 self.graph.frames[kf])
        self._add_keyframe(prev, frame, gray, T, kf, flows)
        return True

    def _rotation_flow(self, rel: torch.Tensor, shape: tuple[int, int]) -> np.ndarray:
        """(h, w, 2) flow from a keyframe to a frame at relative pose `rel` (keyframe camera ->
        frame camera, (4, 4)) that the rotation alone would cause: the reprojection of points
        at infinity (inverse depth 0), i.e. the infinite homography K R K^-1."""
        h, w = shape
        intr = torch.tensor(pj.scale_intrinsics(self.intrinsics, w / self.geo.width, h / self.geo.height),
                            dtype=torch.float64)
        uv = pj.pixel_grid(h, w)
        at_infinity = pj.backproject(uv, torch.zeros(h, w, dtype=torch.float64), intr)
        moved, _ = pj.project(pj.transform(rel[None], at_infinity[None])[0], intr)
        return (moved - uv).numpy().astype(np.float32)

    def _relocalise(self, index: int, gray: np.ndarray, T0: torch.Tensor):
        """Try older keyframes (most recent first) when the reference keyframe fails."""
        K = len(self.graph)
        tried = [k for k in range(K - 1, -1, -1) if k != self.ref_kf][: self.cfg.reloc_candidates]
        for k in tried:
            found = self._against(k, gray, self.graph.poses([k])[0])
            if found is not None:
                self.reloc_events.append({"frame": index, "keyframe": int(self.graph.frames[k])})
                log.info("frame %d: relocalised against keyframe at frame %d", index, self.graph.frames[k])
                return found
        return None

    def _lost(self, index: int) -> None:
        self.lost_run.append(index)
        self.status[index] = "lost"
        if len(self.lost_run) > self.cfg.max_lost:
            first = self.lost_run[0]
            raise TrackingLostError(
                f"tracking lost at frame {first}: {len(self.lost_run)} consecutive frames could not be aligned to any "
                f"of the last keyframes ({self.last_failure}); the video may cut, "
                "blur or move too fast",
                frame=first,
            )

    def _add_keyframe(self, index, frame, gray, T, ref, flows) -> None:
        g = self.graph
        disp, pw = self._prior_disp(index, frame)
        # Start the new depth at the reference keyframe's scale: the prior's per-frame scale
        # error would otherwise pull the new keyframe's pose along the baseline.
        k = g.add_keyframe(index, gray, T, disp, disp.clone(), pw)
        self.refs.pop(index, None)
        self.status[index] = "keyframe"
        fwd, bwd, cf, cb = flows
        self._add_pair(ref, k, fwd, bwd, cf, cb, "temporal")
        for j in range(k - 1, max(k - 1 - self.cfg.temporal_radius, -1), -1):
            if j != ref:
                self._link(j, k, "temporal")
        self._proximity(k)
        if self.cfg.calibrate_lens and not self.lens_calibrated and len(g) >= self.cfg.calibrate_after:
            self._run_ba(list(range(len(g))), self.cfg.calibrate_iters, calibrate=True)
            self.lens_calibrated = True
        else:
            self._window_ba(k)
        self.ref_kf = k
        self.frame_T[index] = g.poses([k])[0]

    def _add_pair(self, i, j, fwd, bwd, cf, cb, kind) -> bool:
        ti, wi = self._edge_targets(fwd, cf)
        tj, wj = self._edge_targets(bwd, cb)
        if float(wi.mean()) < self.cfg.min_edge_weight or float(wj.mean()) < self.cfg.min_edge_weight:
            return False
        self.graph.add_edge(i, j, ti, wi, kind)
        self.graph.add_edge(j, i, tj, wj, kind)
        return True

    def _link(self, i: int, j: int, kind: str) -> bool:
        """Flow edges i <-> j, DIS seeded with the flow the current geometry predicts."""
        g = self.graph
        T, D = g.poses(), g.disps()
        init_ij = gr.predicted_flow(T, D, self.intr, i, j, self.geo.flow_size, self.k1)
        init_ji = gr.predicted_flow(T, D, self.intr, j, i, self.geo.flow_size, self.k1)
        flows = fl.flow_pair(g.gray[i], g.gray[j], self.cfg.flow, init_ij, init_ji)
        return self._add_pair(i, j, *flows, kind)

    def _proximity(self, k: int, max_edges: int | None = None) -> None:
        cfg = self.cfg
        max_edges = cfg.proximity_edges if max_edges is None else max_edges
        if max_edges <= 0:
            return
        candidates = [c for c in range(0, k - cfg.temporal_radius - 1) if not self.graph.connected(c, k)]
        if not candidates:
            return
        dist, frac = gr.induced_flow(self.graph.poses(), self.graph.disps(), self.intr, k, torch.tensor(candidates))
        # induced_flow is in BA pixels; thresholds are in 640-wide working pixels.
        max_dist = _scaled_pixels(cfg.proximity_max_flow, self.geo) / self.geo.flow_factor
        chosen = gr.select_proximity(candidates, dist.numpy(), frac.numpy(), max_edges, max_dist,
                                     cfg.proximity_min_overlap, cfg.proximity_nms)
        for c in chosen:
            self._link(c, k, "proximity")

    def _window_ba(self, k: int) -> None:
        g = self.graph
        lo = max(0, k + 1 - self.cfg.window)
        window = list(range(lo, k + 1))
        self._run_ba(window, self.cfg.window_iters)

    def _run_ba(self, free_ids: list[int], iters: int, calibrate: bool = False) -> None:
        g = self.graph
        _, edges = g.edge_list(free_ids)
        if not len(edges):
            return
        ids = sorted(set(edges.ii.tolist()) | set(edges.jj.tolist()) | set(free_ids))
        index = torch.full((len(g),), -1, dtype=torch.int64)
        index[ids] = torch.arange(len(ids))
        local = edges.remap(index)
        free = set(free_ids)
        fixed = torch.tensor([i not in free for i in ids])
        if not bool(fixed.any()):
            fixed[0] = True  # gauge: the first keyframe of the window
        fixed_disp = torch.tensor([i not in free for i in ids])
        prior, prior_w = g.priors(ids)
        opts = replace(self._ba_opts(iters), calibrate_k1=calibrate)
        T, D, report = ba.bundle_adjust(g.poses(ids), g.disps(ids), self.intr, local, prior, prior_w, fixed,
                                        opts, fixed_disp, self.k1)
        g.set_state(ids, T, D)
        if calibrate:
            log.info("lens radial term k1 %.4f (was %.4f)", report.k1, self.k1)
            self.k1 = report.k1
        self.ba_reports.append(report)

    # ------------------------------------------------------------------ finishing

    def global_ba(self) -> None:
        if len(self.graph) > 1:
            for k in range(len(self.graph)):
                self._proximity(k, self.cfg.final_proximity_edges)
            self._run_ba(list(range(len(self.graph))), self.cfg.global_iters, calibrate=self.cfg.calibrate_lens)

    def metric_rescale(self) -> float:
        """Rescale the world so that depths agree with the prior, robustly over all frames.

        Each keyframe contributes median(BA depth / prior depth); each aligned non-keyframe
        the median ratio of the keyframe points it sees (their z in its camera) to its own
        prior there (``frame_ratios``). Pooling over every frame, not only the keyframes,
        averages out more of the prior's per-frame scale error.
        """
        g = self.graph
        prior, prior_w = g.priors()
        ratios = list(self.frame_ratios.values())
        for k in range(len(g)):
            ok = prior_w[k] > 0
            if ok.any():
                ratios.append(float(torch.median(g.disps([k])[0][ok] / prior[k][ok])))
        s = robust_log_mean(np.array(ratios)) if ratios else 1.0
        if not (np.isfinite(s) and s > 0):
            return 1.0
        g.scale_world(s)
        for i, T in self.frame_T.items():
            T = T.clone()
            T[:3, 3] *= s
            self.frame_T[i] = T
        return float(s)

    def align_non_keyframes(self, frames_lookup, num_frames: int, progress: bool) -> None:
        """Motion-only alignment of every non-keyframe against the keyframes before and after it."""
        g = self.graph
        T_kf = g.poses()
        kf_frames = np.array(g.frames)
        jobs = [i for i in range(num_frames) if self.status.get(i) != "keyframe"]
        known = {i: ref for i, ref in self.refs.items()}

        def init_of(i: int, prev: int, nxt: int) -> torch.Tensor:
            if i in self.rel:
                return self.rel[i] @ T_kf[self.refs[i][0]]
            return interpolated_pose(i, prev, nxt, kf_frames, T_kf)

        prior_of = None if self.prior.is_callable else (lambda i: self._prior_disp(i, None))
        out = align_to_keyframes(jobs, lambda i: fl.prepare_gray(frames_lookup(i), self.geo.flow_size),
                                 kf_frames, g.gray, T_kf, g.disps(), self.intr, self.cfg, init_of, known,
                                 prior_of, progress, self.k1)
        for i, (T, ok, ratio) in out.items():
            self.frame_T[i] = T
            if ok:
                if np.isfinite(ratio):
                    self.frame_ratios[i] = ratio
                if self.status.get(i) == "lost":
                    self.status[i] = "recovered"
            else:
                self.status[i] = "interpolated"


def interpolated_pose(i: int, prev: int, nxt: int, kf_frames: np.ndarray, T_kf: torch.Tensor) -> torch.Tensor:
    """Pose (4, 4) of frame i on the geodesic between keyframes prev and nxt (ids; -1 or K
    when there is none on that side: then the nearest keyframe's pose)."""
    if prev >= 0 and nxt < len(kf_frames):
        a = (i - kf_frames[prev]) / max(kf_frames[nxt] - kf_frames[prev], 1)
        return torch.from_numpy(lie.interpolate(T_kf[prev][None].numpy(), T_kf[nxt][None].numpy(), np.array([a]))[0])
    return T_kf[prev] if prev >= 0 else T_kf[nxt]


def align_to_keyframes(jobs, gray_of, kf_frames, kf_gray, T_kf, disp_kf, intr, cfg: FrontendConfig, init_of=None,
                       known=None, prior_of=None, progress: bool = False, k1: float = 0.0) -> dict:
    """Motion-only alignment of frames `jobs` against their neighbouring keyframes.

    kf_frames (K,) sorted frame indices of the keyframes, kf_gray their flow-resolution grey
    images, T_kf (K, 4, 4) world-to-camera poses, disp_kf (K, H, W) BA-grid inverse depth.
    gray_of(i): frame i's flow-resolution grey image. init_of(i, prev, nxt): initial pose
    (default: geodesic between the keyframes before and after). known: {i: (k, target,
    weight)} flow measurements already made (from tracking). prior_of(i): (prior inverse
    depth, tie weight) on the BA grid, for the per-frame metric ratio (``frame_depth_ratios``);
    k1: the lens' radial term.
    Returns {i: (T_cw (4, 4), ok, ratio)}; ok is False when the alignment kept less than
    ``cfg.lost_inlier`` of its flow confidence (a keyframe whose flow fails
    ``cfg.min_match_correlation`` is left out), and T_cw is then the initial pose.
    """
    known = known or {}
    init_of = init_of or (lambda i, p, n: interpolated_pose(i, p, n, kf_frames, T_kf))
    results = {}
    K = len(kf_frames)
    for start in tqdm(range(0, len(jobs), cfg.align_chunk), desc="aligning frames", unit="batch",
                      disable=not progress, leave=False):
        chunk = jobs[start : start + cfg.align_chunk]
        frame_idx, kfs, targets, weights, T_init = [], [], [], [], []
        for m, i in enumerate(chunk):
            nxt = int(np.searchsorted(kf_frames, i))
            prev = nxt - 1
            T_init.append(init_of(i, prev, nxt))
            if i in known:
                k, t, w = known[i]
                frame_idx.append(m), kfs.append(k), targets.append(t), weights.append(w)
            gray = None
            for k in (prev, nxt):
                if k < 0 or k >= K or (i in known and known[i][0] == k):
                    continue
                gray = gray_of(i) if gray is None else gray
                fwd, _, cf, _ = fl.flow_pair(kf_gray[k], gray, cfg.flow)
                if fl.match_correlation(kf_gray[k], gray, fwd, cf) < cfg.min_match_correlation:
                    continue
                t, w = fl.pool_edge(fwd, cf, 2, cfg.flow)
                frame_idx.append(m), kfs.append(k), targets.append(t), weights.append(w)
        if not kfs:
            results.update({i: (T_init[m], False, float("nan")) for m, i in enumerate(chunk)})
            continue
        kt, ft = torch.tensor(kfs), torch.tensor(frame_idx)
        wt = torch.stack(weights).double()
        T, _, inl = ba.align_frames(torch.stack(T_init), T_kf[kt], disp_kf[kt], intr, ft,
                                    torch.stack(targets).double(), wt, huber=1.0, k1=k1)
        ratio = np.full(len(chunk), np.nan)
        if prior_of is not None:
            disp_w = [prior_of(i) for i in chunk]
            prior = torch.stack([d for d, _ in disp_w])
            prior_ok = torch.stack([w for _, w in disp_w]) > 0
            ratio = frame_depth_ratios(T, T_kf[kt], disp_kf[kt], intr, ft, wt, prior, prior_ok, k1)
        for m, i in enumerate(chunk):
            ok = float(inl[m]) >= cfg.lost_inlier
            results[i] = (T[m] if ok else T_init[m], ok, float(ratio[m]))
    return results


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


# --------------------------------------------------------------------------- focal search


def estimate_focal(frames: list[np.ndarray], prior: PriorSource, cfg: FrontendConfig, progress: bool = False
                   ) -> calib.FocalSearch:
    """Focal length (pixels, fx = fy, principal point at the centre) minimising the BA cost
    of the first keyframes. frames: the first frames of the video (H, W, 3) uint8."""
    height, width = frames[0].shape[:2]
    ba_geo = make_geometry(width, height, cfg.calib_stride)

    factor = cfg.calib_stride // cfg.calib_flow_stride
    flow_size = (ba_geo.ba_size[0] * factor, ba_geo.ba_size[1] * factor)
    # Keyframes by the motion filter (independent of the focal length).
    grays = [fl.prepare_gray(f, flow_size) for f in frames]
    kfs = [0]
    for i in range(1, len(frames)):
        fwd, _, cf, _ = fl.flow_pair(grays[kfs[-1]], grays[i], cfg.flow)
        if fl.mean_magnitude(fwd, cf) * (width / flow_size[0]) * (640.0 / width) > cfg.keyframe_flow:
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
    priors = [_disp_from_depth(pool_depth(prior.get(k, frames[k]), ba_geo.ba_size), cfg.prior_weight) for k in kfs]
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
            Tk, _, _ = ba.align_frames(T[k - 1 : k], T[k - 1 : k], disp0[k - 1 : k], intr, torch.zeros(1, dtype=torch.int64),
                                       e.target, e.weight)
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
    geo = make_geometry(width, height, cfg.ba_stride)
    tracker = _Tracker(intr, geo, prior, cfg)
    tracker.start(0, frames_list[0])
    for i in tqdm(range(1, len(frames_list)), desc="tracking", unit="frame", disable=not progress, leave=False):
        tracker.track(i, frames_list[i])
    if tracker.lost_run:
        first = tracker.lost_run[0]
        if len(tracker.lost_run) > cfg.max_lost // 2 and tracker.lost_run[-1] == len(frames_list) - 1:
            raise TrackingLostError(f"tracking lost at frame {first} and not recovered before the end of the video",
                                    frame=first)
    tracker.global_ba()
    tracker.align_non_keyframes(lambda i: frames_list[i], len(frames_list), progress)
    g = tracker.graph
    for k, i in enumerate(g.frames):
        tracker.frame_T[i] = g.poses([k])[0]
    scale = tracker.metric_rescale()
    T_cw = torch.stack([tracker.frame_T[i] for i in range(len(frames_list))]).numpy()
    poses = invert_poses(T_cw)
    last = tracker.ba_reports[-1] if tracker.ba_reports else ba.BAReport()
    status = [tracker.status.get(i, "tracked") for i in range(len(frames_list))]
    diagnostics.update(
        num_keyframes=len(g),
        edges=g.kinds(),
        metric_scale_factor=scale,
        frame_status=status,
        lost_frames=[i for i, s in enumerate(status) if s in ("recovered", "interpolated")],
        relocalisations=tracker.reloc_events,
        ba_rmse_px=last.rmse,
        ba_inlier_fraction=last.inlier_fraction,
        ba_grid=geo.ba_size,
        lens_k1=tracker.k1,
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
