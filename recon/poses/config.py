"""The front end's settings and image geometry, shared by its roles (``tracker``,
``backend``, ``filler``) and by the estimators that reuse them (SfM's dense registration,
the pose polish).

This module owns :class:`FrontendConfig` (every tunable of the front end; why the defaults:
docs/decisions.md#pose-settings-how-the-defaults-were-chosen), :class:`Geometry` (the three resolutions:
working frames, flow at 1/4, BA at 1/8) and the conversion of a pooled depth prior to the
BA's inverse depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.ba import bundle as ba
from recon.poses.checks import normal_flow as nf
from recon.poses.matching import features as ft
from recon.poses.matching import flow as fl


@dataclass
class FrontendConfig:
    """Front-end settings. keyframe_flow, keyframe_max_flow and proximity_max_flow are in
    working-resolution pixels, scaled as if the frames were 640 px wide.
    why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen

    ba_stride: BA grid = working resolution / ba_stride (DROID: 8); flow runs at twice
        the BA resolution and is pooled.
    keyframe_flow: a frame becomes a keyframe when the mean *parallax* flow from the last
        keyframe (its flow minus what its tracked rotation alone explains) exceeds this:
        rotation adds cost but no depth information.
    keyframe_max_flow: ... or when the mean flow itself exceeds this, so that a rotating
        camera still gets keyframes before the overlap runs out.
    revisit_flow: when a frame is due to become a keyframe, an older keyframe whose pixels
        would move by less than this much parallax into it (by the current poses and
        depths; overlap at least ``revisit_overlap``) is tried first: the frame is aligned to
        it and, when the measured flow confirms it, tracking goes on from that keyframe
        instead of adding one (ORB-SLAM keeps its map from growing on revisits the same
        way, by culling redundant keyframes). A camera that walks the same room again then
        adds no keyframes, so the map, the global BA and their memory stay the size of the
        place rather than of the video. 0 turns it off (DROID-SLAM's behaviour).
    revisit_overlap: ... see above.
    temporal_radius: each new keyframe is linked (both directions) to this many previous
        keyframes; at or above ``window`` it also ties the window to held keyframes, which
        holds the drift.
    proximity_edges, proximity_max_flow, proximity_min_overlap, proximity_nms: up to that
        many extra links to older keyframes that, by the current poses and depths, see the
        same region (mean induced flow below proximity_max_flow pixels, overlap above
        proximity_min_overlap), not within proximity_nms keyframes of each other (DROID's
        proximity edges / loop closures).
    final_proximity_edges: before the global BA, every keyframe gets up to this many such
        links again, found with the final poses and depths (a revisit is often recognisable
        only once the later keyframes are in place).
    min_edge_weight: an edge whose mean flow confidence is below this is dropped.
    window: keyframes optimised by the sliding-window BA while tracking.
    window_iters, global_iters: LM iterations of the window and of the final global BA (the
        window is re-optimised as it slides, so few suffice).
    prior_weight: tie of BA inverse depth to the prior (``ba.BAOptions``); weak, so that the
        flow shapes the depth and the prior mostly holds the scale.
    lens_k1: the lens' radial term k1 when known (``projective.undistort``; 0 = pinhole):
        flow is measured on the frames as recorded and undistorted in the BA.
    calibrate_lens: estimate k1 (starting from lens_k1) in a BA over all keyframes once
        ``calibrate_after`` keyframes exist (``calibrate_iters`` LM iterations; tracking
        goes on with it) and again in the final global BA. An ignored lens makes the BA
        trade rotation for translation. None (default): only when the focal length is
        estimated too (no intrinsics given): a lens estimated from the frames never
        overrides a calibration the user gave (``calibrates_lens``).
    plumb_line: when the focal length is searched and the lens is to be calibrated from k1 =
        0, first measure the lens from the frames' straight edges (``plumb_line``, which
        needs no focal length), search the focal length through that lens and start
        tracking from it: a barrel lens ignored by the search makes the focal length long.
    vanishing_points, vanishing_min_share: when the focal length is searched, also measure
        it from the vanishing points of the frames' straight edges (``vanishing``: a
        Manhattan world's orthogonal directions), and take that value when at least
        ``vanishing_min_share`` of the frames agree on it (``focal_choice``: on the
        recordings' clips such values came within 3.4 %, the search's within -54 % to +61 %).
    rotation_focal: when the focal length is searched, also measure it from the homographies
        of the frame pairs that turned (``rotation_focal``: self-calibration of a rotating
        camera), taken where they fix it and no vanishing points were agreed on
        (``focal_choice``).
    join_scale_breaks: where the map's depth steps against the depth prior's beyond the
        prior's noise (``scale_watch``: the trajectory's scale broke there), bring each
        stretch after such a step to the scale of the one before it
        (``backend.rescale_stretches``) before the metric rescale. Off: it made the
        joins worse. why: docs/decisions.md#joining-across-a-break
    stop_untrusted: stop (TrackingLostError, which the SfM fallback then answers) when the
        front end's checks of its own motion (``motion_checks``: the lens fit on its bound,
        a camera turned on the spot for most of the run, with the focal length estimated),
        or the focal search's
        minimum was not bracketed (``focal_choice.FocalChoice.found``), say the trajectory
        cannot be trusted; off: return it, the verdicts in ``diagnostics["motion_checks"]``
        (``--on-break keep``).
    restart_after_loss: where the camera is lost in the middle of the video (after at least
        2 (max_lost + 1) tracked frames), track again from the first lost frame as a new
        piece, with the first piece's camera (``recon.poses.frontend.pieces``), instead of falling
        back to SfM; the pieces come back as one estimate whose scale watch has a "lost"
        break at each restart. The pipeline turns it on with ``--on-break segments``.
    failing_inlier: with ``restart_after_loss``, a piece that ends where the camera was
        lost also gives up the frames before the loss whose tracking was already failing:
        those after which, within a loss's length (max_lost + 1) of it, no three frames in a
        row explain this share of their flow confidence once the piece's BA is solved
        (``quality.failing_since``); its BA is then solved again without them. A map goes
        wrong before the front end loses it, and the frames in between pass every check one
        by one (the synthetic walk-through's corner: frames 176-185, 0.2-1.6 m off, each
        explaining 0.65-0.98 of its flow). 0: keep them.
    min_match_correlation: a frame whose flow from a keyframe joins grey levels correlated
        less than this (``flow.match_correlation``) is not aligned to it: flow confidence
        alone passes unrelated images.
    min_local_correlation: ... nor when its 7x7 windows along the flow correlate less than
        this on average (``flow.local_correlation``): a flow can bend an unrelated image
        onto the keyframe's coarse layout, less so onto its fine texture.
    lost_inlier: a frame whose alignment keeps less than this fraction of the flow
        confidence within the robust threshold counts as lost.
    max_lost: consecutive lost frames (after relocalisation attempts) that stop tracking.
    reloc_candidates: older keyframes tried when a frame is lost against the last one.
    calib_keyframes: keyframes used by the focal-length search.
    calib_stride, calib_flow_stride: BA grid and flow strides of the focal search; the flow
        is finer than while tracking, since f shows only in the flow field's slight bending.
    calib_tol, calib_iters: golden-section bracket width on log f at which the search stops
        (0.01 = 1 %), and LM iterations per evaluated focal length.
    align_chunk: non-keyframes aligned per batch at the end (bounds memory).
    torch_threads: intra-op threads while tracking (restored after); None leaves torch's
        setting alone. Set 1 when other work shares the cores.
    seed_min_flow: a frame whose unseeded flow from the keyframe fails the checks is tried
        again with DIS seeded by the flow its start pose (the previous frame's) predicts,
        when that moves the keyframe's pixels by at least this many flow pixels on average
        (a keyframe several fast frames back is beyond DIS's unseeded reach).
    feature_init: when flow fails from the prediction, start the frame from the pose that
        ORB matches to the keyframe give by PnP against its depth (``features``), and
        likewise when relocalising against older keyframes.
    check_short_flow: after the global BA, check each pair of consecutive keyframes' steps
        against the images' gradients (``normal_flow``, its settings ``normal_flow``): a
        stretch where the dense flow made them short (plain surfaces: the flow's aperture
        problem) is marked in ``diagnostics["motion_checks"]`` and said by the run.
    flow, features, ba, normal_flow: the nested settings of DIS flow, ORB features, the BA
        and the short-flow check.
    """

    ba_stride: int = 8
    keyframe_flow: float = 16.0
    keyframe_max_flow: float = 48.0
    revisit_flow: float = 8.0
    revisit_overlap: float = 0.7
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
    calibrate_lens: bool | None = None
    calibrate_after: int = 20
    calibrate_iters: int = 4
    plumb_line: bool = True
    vanishing_points: bool = True
    vanishing_min_share: float = 0.5
    rotation_focal: bool = True
    join_scale_breaks: bool = False
    stop_untrusted: bool = True
    restart_after_loss: bool = False
    failing_inlier: float = 0.85
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
    check_short_flow: bool = True
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)
    features: ft.FeatureConfig = field(default_factory=ft.FeatureConfig)
    ba: ba.BAOptions = field(default_factory=ba.BAOptions)
    normal_flow: nf.NormalFlowConfig = field(default_factory=nf.NormalFlowConfig)

    def on_device(self, device: str) -> "FrontendConfig":
        """The same settings with the bundle adjustment on ``device`` (the rest runs on the CPU)."""
        return replace(self, ba=replace(self.ba, device=device))


@dataclass
class Geometry:
    """Image shapes (H, W) and intrinsics at the three resolutions."""

    shape: tuple[int, int]  # working frames
    flow_shape: tuple[int, int]
    ba_shape: tuple[int, int]
    flow_factor: int  # flow pixels per BA pixel

    @property
    def px_scale(self) -> float:
        """Working-resolution pixels per flow pixel, normalised to a 640 px wide frame."""
        width = self.shape[1]
        return (width / self.flow_shape[1]) * (640.0 / width)

    def ba_intrinsics(self, intrinsics) -> torch.Tensor:
        sx = self.ba_shape[1] / self.shape[1]
        sy = self.ba_shape[0] / self.shape[0]
        return torch.tensor(pj.scale_intrinsics(intrinsics, sx, sy), dtype=torch.float64)


def make_geometry(shape: tuple[int, int], ba_stride: int) -> Geometry:
    """The geometry of working frames of `shape` (H, W): BA grid 1/ba_stride (at least 4
    pixels a side), flow at twice that."""
    height, width = shape
    hb, wb = max(height // ba_stride, 4), max(width // ba_stride, 4)
    return Geometry((height, width), (2 * hb, 2 * wb), (hb, wb), 2)


def disp_from_depth(depth: np.ndarray, prior_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse depth (h, w) float64 of a pooled depth (h, w) and its tie weight (0 where invalid)."""
    d = torch.from_numpy(depth.astype(np.float64))
    valid = d > 0
    disp = torch.where(valid, 1.0 / d.clamp(min=1e-6), torch.zeros_like(d))
    fill = float(disp[valid].median()) if valid.any() else 1.0
    disp = torch.where(valid, disp, torch.full_like(disp, fill)).clamp(ba.MIN_DISP, ba.MAX_DISP)
    return disp, valid.double() * prior_weight


def ba_pixels(cfg_value: float, ba_width: int) -> float:
    """A threshold given in 640-px-wide working pixels, in pixels of a BA grid ba_width wide
    (what ``graph.induced_flow`` and ``graph.parallax_into`` measure)."""
    return cfg_value * ba_width / 640.0


def calibrates_lens(setting: bool | None, intrinsics) -> bool:
    """Whether an estimator with ``calibrate_lens`` = `setting` estimates the lens' radial
    term for a camera with `intrinsics` (None: unknown). None estimates it only together
    with an unknown focal length: given intrinsics are a calibration.
    why: docs/decisions.md#the-lens"""
    return (intrinsics is None) if setting is None else bool(setting)
