"""The one state object of a front-end run (DROID-SLAM's ``depth_video``): the keyframe
graph and the per-frame records that the roles around it read and write.

The roles: ``motion_filter`` (is this frame a keyframe?), ``tracker`` (the local window:
align each new frame, insert keyframes, window BA, relocalise), ``backend`` (edges, BA,
lens calibration, metric scale), ``filler`` (poses of the non-keyframes at the end). Each
takes a :class:`TrackState`; none keeps state of its own.

Poses here are world-to-camera (``T_cw``), as in the BA; the estimator's result is
camera-to-world.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.ba import bundle as ba
from recon.poses.ba import graph as gr
from recon.poses.config import FrontendConfig, Geometry, disp_from_depth
from recon.poses.frontend.park import FramePark
from recon.poses.matching import flow as fl
from recon.poses.result import PriorSource, pool_depth


class TrackState:
    """Everything one tracking run knows.

    graph: keyframes (frame index, grey image, pose, BA depth, prior) and flow edges.
    frame_T: {frame: T_cw (4, 4)} every frame tracked so far (keyframes: their graph pose).
    refs: {non-keyframe: (keyframe id, seeded)}: the keyframe whose flow aligned it and
        whether DIS was seeded. The filler uses that flow again, pooled to the BA grid, from
        ``park`` (``park_edge``, ``tracked_edge``) where it was parked; else it makes it again
        from the frame (keeping it here, 115 KB a frame at 640x480, would make the state grow
        with the video).
    park: a ``park.FramePark`` for those flows, or None (the filler makes them again).
    rel: {non-keyframe: T_frame <- T_keyframe (4, 4)} its pose relative to that keyframe, so
        that it follows the keyframe through later BA.
    status: {frame: one of result.FRAME_STATES, or "lost" while tracking}.
    frame_ratios: {frame: geometric / prior inverse depth}, for the metric scale.
    ref_kf: the keyframe new frames are aligned to first.
    lost_run: the current run of consecutive lost frames.
    previous: the last tracked non-keyframe (index, frame, grey, pose, keyframe, flows),
        promoted to a keyframe when the next frame cannot be aligned to ref_kf.
    last_failure: why the last alignment was refused (for the error message).
    inlier: {frame: share of its flow confidence its tracked pose explains} (evidence for
        the quality gate; last_inlier: that of the last accepted alignment).
    k1, lens_calibrated: the lens' radial term and whether the BA has estimated it.
    kf_detail, kf_keypoints: half-size grey images and ORB keypoints (the feature start)
        of the keyframes it can still use (the tracker drops older ones); feature_starts
        counts the frames it started.
    reloc_events, revisits, ba_reports: what happened, for the diagnostics (revisits: how
        many frames went on from an older keyframe instead of becoming one).
    """

    def __init__(self, intrinsics, geo: Geometry, prior: PriorSource, cfg: FrontendConfig,
                 park: FramePark | None = None):
        self.cfg = cfg
        self.park = park
        self.geo = geo
        self.prior = prior
        self.intrinsics = intrinsics
        self.intr = geo.ba_intrinsics(intrinsics)
        self.graph = gr.FrameGraph(geo.ba_shape)
        self.refs: dict[int, tuple[int, bool]] = {}
        self.frame_T: dict[int, torch.Tensor] = {}
        self.rel: dict[int, torch.Tensor] = {}
        self.frame_ratios: dict[int, float] = {}
        self.status: dict[int, str] = {}
        self.ref_kf = 0
        self.lost_run: list[int] = []
        self.reloc_events: list[dict] = []
        self.revisits = 0
        self.ba_reports: list[ba.BAReport] = []
        self.previous: tuple | None = None
        self.last_failure = ""
        self.last_inlier = float("nan")
        self.inlier: dict[int, float] = {}
        self.k1 = cfg.lens_k1
        self.lens_calibrated = False
        # Keyframes' grey images at half the working size and their ORB keypoints, for the
        # feature start (``features``) of frames the flow cannot start on.
        height, width = geo.shape
        self.detail_shape = (max(height // 2, 16), max(width // 2, 16))
        self.detail_intrinsics = pj.scale_intrinsics(intrinsics, self.detail_shape[1] / width,
                                                     self.detail_shape[0] / height)
        self.kf_detail: dict[int, np.ndarray] = {}
        self.kf_keypoints: dict = {}
        self.feature_starts = 0

    def forget_from(self, stop: int) -> None:
        """Forget frames stop and later (where tracking starts again as a new piece,
        ``recon.poses.frontend.pieces``): their records, and the keyframes among them with their
        edges. The window BAs those keyframes took part in stay in the older keyframes'
        state; the global BA at the end solves them again without them."""
        for records in (self.status, self.frame_T, self.refs, self.rel, self.frame_ratios, self.inlier):
            for frame in [f for f in records if f >= stop]:
                del records[frame]
        kept = sum(frame < stop for frame in self.graph.frames)
        self.graph.drop_from(kept)
        for cache in (self.kf_detail, self.kf_keypoints):
            for k in [k for k in cache if k >= kept]:
                del cache[k]
        self.ref_kf = min(self.ref_kf, kept - 1)
        self.lost_run = [f for f in self.lost_run if f < stop]
        self.reloc_events = [e for e in self.reloc_events if e["frame"] < stop]
        if self.previous is not None and self.previous[0] >= stop:
            self.previous = None

    def ba_options(self, iters: int) -> ba.BAOptions:
        return replace(self.cfg.ba, iters=iters, prior_weight=self.cfg.prior_weight)

    def prior_disp(self, index: int, frame: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Prior inverse depth (h, w) of a frame on the BA grid and its tie weight."""
        depth = pool_depth(self.prior.get(index, frame), self.geo.ba_shape)
        return disp_from_depth(depth, self.cfg.prior_weight)

    def edge_targets(self, flow: np.ndarray, conf: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """A flow-resolution flow and confidence pooled to a BA target and weight."""
        return fl.pool_edge(flow, conf, self.geo.flow_factor, self.cfg.flow)

    def park_edge(self, index: int, kf: int, target: torch.Tensor, weight: torch.Tensor) -> None:
        """Park frame index's unseeded flow from keyframe kf, pooled to the BA grid (target
        (h, w, 2), weight (h, w); ``edge_targets``), for the filler (``tracked_edge``)."""
        if self.park is not None:
            self.park.put(index, edge_target=target.numpy(), edge_weight=weight.numpy(),
                          edge_keyframe=np.array([self.graph.frames[kf]], np.int64))

    def tracked_edge(self, index: int, kf: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The BA target and weight parked for frame index against keyframe kf (``park_edge``),
        or None where none was parked against that keyframe."""
        if self.park is None or not self.park.has(index, "edge_keyframe"):
            return None
        if int(self.park.get(index, "edge_keyframe")[0]) != self.graph.frames[kf]:
            return None
        return (torch.from_numpy(self.park.get(index, "edge_target")),
                torch.from_numpy(self.park.get(index, "edge_weight")))

    def whitening(self, gray: np.ndarray) -> torch.Tensor | None:
        """The residual factors (h, w, 2, 2) of edges from a keyframe with flow-resolution
        grey image gray (``flow.flow_whitening``; None when the flow is weighed isotropically)."""
        return fl.flow_whitening(gray, self.geo.flow_factor, self.cfg.flow)
