"""The front end's settings and image geometry, shared by its roles (``tracker``,
``backend``, ``filler``) and by the estimators that reuse them (SfM's dense registration,
the pose polish).

This module owns :class:`FrontendConfig` (every tunable of the front end, with the
measurements behind the defaults), :class:`Geometry` (the three resolutions: working
frames, flow at 1/4, BA at 1/8) and the conversion of a pooled depth prior to the BA's
inverse depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from recon.poses import ba
from recon.poses import features as ft
from recon.poses import flow as fl
from recon.poses import projective as pj


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
    min_local_correlation: ... and whose 7x7 windows along the flow correlate less than
        this on average (``flow.local_correlation``): a flow can bend an unrelated image
        onto the coarse layout of the keyframe (two synthetic rooms filmed alike: global
        correlation 0.64-0.73, local 0.33-0.43), less so its fine texture. Lowest local
        correlation of an accepted frame: 0.55 (the synthetic room at 6x speed with blur),
        0.92 (TUM fr1/rpy every 2nd and 3rd frame, 7-Scenes every 8th and 12th).
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
    seed_min_flow: a frame whose unseeded flow from the keyframe fails the checks is tried
        again with DIS seeded by the flow its start pose (the previous frame's) predicts,
        when that moves the keyframe's pixels by at least this many flow pixels on average:
        a keyframe several fast frames back is beyond DIS's unseeded reach.
    feature_init: when flow fails from the prediction, start the frame from the pose that
        ORB matches to the keyframe give by PnP against its depth (``features``), and
        likewise when relocalising against older keyframes.
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
    min_local_correlation: float = 0.5
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
    seed_min_flow: float = 2.0
    feature_init: bool = True
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)
    features: ft.FeatureConfig = field(default_factory=ft.FeatureConfig)
    ba: ba.BAOptions = field(default_factory=ba.BAOptions)


@dataclass
class Geometry:
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


def make_geometry(width: int, height: int, ba_stride: int) -> Geometry:
    wb, hb = max(width // ba_stride, 4), max(height // ba_stride, 4)
    return Geometry(width, height, (2 * wb, 2 * hb), (wb, hb), 2)


def disp_from_depth(depth: np.ndarray, prior_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse depth (h, w) float64 of a pooled depth (h, w) and its tie weight (0 where invalid)."""
    d = torch.from_numpy(depth.astype(np.float64))
    valid = d > 0
    disp = torch.where(valid, 1.0 / d.clamp(min=1e-6), torch.zeros_like(d))
    fill = float(disp[valid].median()) if valid.any() else 1.0
    disp = torch.where(valid, disp, torch.full_like(disp, fill)).clamp(ba.MIN_DISP, ba.MAX_DISP)
    return disp, valid.double() * prior_weight


def scaled_pixels(cfg_value: float, geo: Geometry) -> float:
    """A threshold given in 640-px-wide working pixels, in flow pixels."""
    return cfg_value / geo.px_scale
