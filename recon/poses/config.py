"""The front end's settings and image geometry, shared by its roles (``tracker``,
``backend``, ``filler``) and by the estimators that reuse them (SfM's dense registration,
the pose polish).

This module owns :class:`FrontendConfig` (every tunable of the front end; why the defaults:
docs/decisions.md#pose-settings-how-the-defaults-were-chosen), the ranges its fields and SfM's
declare (:func:`bounded`), :class:`Geometry` (the three resolutions: working frames, flow at
1/4, BA at 1/8) and the conversion of a pooled depth prior to the BA's inverse depth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.ba import bundle as ba
from recon.poses.checks import normal_flow as nf
from recon.poses.matching import features as ft
from recon.poses.matching import flow as fl


@dataclass(frozen=True)
class Bounds:
    """The values a setting may take: ``words`` name them in the error ("pose option X must be
    <words>"), ``test`` says whether a value is one of them."""

    words: str
    test: Callable[[Any], bool]


def at_least(low: int) -> Bounds:
    """The bounds of a setting that must be `low` or more.

    Args:
        low: the least value allowed.

    Returns:
        Bounds worded ">= low".
    """
    return Bounds(f">= {low}", lambda v: v >= low)


def one_of(values: tuple[str, ...]) -> Bounds:
    """The bounds of a setting that must be one of `values`.

    Args:
        values: the choices, at least two.

    Returns:
        Bounds naming them in order, quoted, the last after "or".
    """
    quoted = [repr(v) for v in values]
    return Bounds(", ".join(quoted[:-1]) + " or " + quoted[-1], lambda v: v in values)


POSITIVE = Bounds("> 0", lambda v: v > 0)
FRACTION = Bounds("in [0, 1]", lambda v: 0 <= v <= 1)
CORRELATION = Bounds("in [-1, 1]", lambda v: -1 <= v <= 1)


def bounded(default: Any, bounds: Bounds) -> Any:
    """A dataclass field whose values must lie in `bounds`, kept in its metadata ("bounds").

    Args:
        default: the field's default (immutable; None passes unchecked).
        bounds: what its values must be (``recon.poses.options.check_pose_config`` checks it).

    Returns:
        The ``dataclasses.field`` to assign in the class body.
    """
    return field(default=default, metadata={"bounds": bounds})


@dataclass
class FrontendConfig:
    """Front-end settings. keyframe_flow, keyframe_max_flow and proximity_max_flow are in
    working-resolution pixels, scaled as if the frames were 640 px wide; a field's range, where
    it has one, is its ``bounded`` metadata.
    why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen
    """

    ba_stride: int = bounded(8, at_least(1))
    """BA grid = working resolution / ba_stride (DROID: 8).

    Flow runs at twice the BA resolution and is pooled.
    """
    keyframe_flow: float = bounded(16.0, POSITIVE)
    """A frame becomes a keyframe when the mean *parallax* flow from the last keyframe exceeds this.

    Parallax: its flow minus what its tracked rotation alone explains; rotation adds cost but
    no depth information.
    """
    keyframe_max_flow: float = bounded(48.0, POSITIVE)
    """A frame also becomes a keyframe when the mean flow itself exceeds this.

    So that a rotating camera still gets keyframes before the overlap runs out.
    """
    revisit_flow: float = 8.0
    """An older keyframe with less parallax than this into a frame due to become a keyframe is tried first (0: off).

    When a frame is due to become a keyframe, an older keyframe whose pixels would move by less
    than this much parallax into it (by the current poses and depths; overlap at least
    ``revisit_overlap``) is tried first: the frame is aligned to it and, when the measured flow
    confirms it, tracking goes on from that keyframe instead of adding one (ORB-SLAM keeps its
    map from growing on revisits the same way, by culling redundant keyframes). A camera that
    walks the same room again then adds no keyframes, so the map, the global BA and their
    memory stay the size of the place rather than of the video. 0 turns it off (DROID-SLAM's
    behaviour).
    """
    revisit_overlap: float = 0.7
    """See revisit_flow: the overlap the older keyframe must have at least."""
    temporal_radius: int = bounded(6, at_least(1))
    """Each new keyframe is linked (both directions) to this many previous keyframes.

    At or above ``window`` it also ties the window to held keyframes, which holds the drift.
    """
    proximity_edges: int = bounded(2, at_least(0))
    """Up to this many extra links to older keyframes that see the same region (DROID's proximity edges).

    Which ones, by the current poses and depths: mean induced flow below proximity_max_flow
    pixels, overlap above proximity_min_overlap, not within proximity_nms keyframes of each
    other (DROID's proximity edges / loop closures).
    """
    proximity_max_flow: float = bounded(96.0, POSITIVE)
    """See proximity_edges: the mean induced flow (pixels) of a proximity link must be below this."""
    proximity_min_overlap: float = bounded(0.5, FRACTION)
    """See proximity_edges: the overlap of a proximity link must be above this."""
    proximity_nms: int = bounded(2, at_least(0))
    """See proximity_edges: the older keyframes linked are not within this many keyframes of each other."""
    final_proximity_edges: int = bounded(4, at_least(0))
    """Before the global BA, every keyframe gets up to this many proximity links again, by the final poses and depths.

    A revisit is often recognisable only once the later keyframes are in place.
    """
    min_edge_weight: float = bounded(0.15, FRACTION)
    """An edge whose mean flow confidence is below this is dropped."""
    window: int = bounded(5, at_least(1))
    """Keyframes optimised by the sliding-window BA while tracking."""
    window_iters: int = bounded(2, at_least(0))
    """LM iterations of the window BA.

    The window is re-optimised as it slides, so few suffice.
    """
    global_iters: int = bounded(8, at_least(0))
    """See window_iters: LM iterations of the final global BA."""
    prior_weight: float = bounded(0.002, at_least(0))
    """Tie of BA inverse depth to the prior (``ba.BAOptions``).

    Weak, so that the flow shapes the depth and the prior mostly holds the scale.
    """
    lens_k1: float = 0.0
    """The lens' radial term k1 when known (``projective.undistort``; 0 = pinhole).

    Flow is measured on the frames as recorded and undistorted in the BA.
    """
    calibrate_lens: bool | None = None
    """Estimate k1 (from lens_k1) in a BA over all keyframes (None: only when the focal length is estimated too).

    That BA runs once ``calibrate_after`` keyframes exist (``calibrate_iters`` LM iterations;
    tracking goes on with it) and again in the final global BA. An ignored lens makes the BA
    trade rotation for translation. None (default): only when the focal length is estimated
    too (no intrinsics given): a lens estimated from the frames never overrides a calibration
    the user gave (``calibrates_lens``).
    """
    calibrate_after: int = bounded(20, at_least(0))
    """See calibrate_lens: the lens is first estimated once this many keyframes exist."""
    calibrate_iters: int = bounded(4, at_least(0))
    """See calibrate_lens: LM iterations of that BA."""
    plumb_line: bool = True
    """Measure the lens from the frames' straight edges first, when the focal length is searched and k1 starts at 0.

    When the focal length is searched and the lens is to be calibrated from k1 = 0, first
    measure the lens from the frames' straight edges (``plumb_line``, which needs no focal
    length), search the focal length through that lens and start tracking from it: a barrel
    lens ignored by the search makes the focal length long.
    """
    vanishing_points: bool = True
    """When the focal length is searched, also measure it from the vanishing points of the frames' straight edges.

    ``vanishing``: a Manhattan world's orthogonal directions. That value is taken when at
    least ``vanishing_min_share`` of the frames agree on it (``focal_choice``: on the
    recordings' clips such values came within 3.4 %, the search's within -54 % to +61 %).
    """
    vanishing_min_share: float = 0.5
    """See vanishing_points: the share of the frames that must agree on its value for it to be taken."""
    rotation_focal: bool = True
    """When the focal length is searched, also measure it from the homographies of the frame pairs that turned.

    ``rotation_focal``: self-calibration of a rotating camera; taken where they fix it and no
    vanishing points were agreed on (``focal_choice``).
    """
    join_scale_breaks: bool = False
    """Bring each stretch after a scale step to the scale of the one before it (off: it made the joins worse).

    Where the map's depth steps against the depth prior's beyond the prior's noise
    (``scale_watch``: the trajectory's scale broke there), bring each stretch after such a step
    to the scale of the one before it (``backend.rescale_stretches``) before the metric
    rescale. Off: it made the joins worse. why: docs/decisions.md#joining-across-a-break
    """
    stop_untrusted: bool = True
    """Stop when the checks say the trajectory cannot be trusted (TrackingLostError; the SfM fallback answers it).

    The checks: the front end's checks of its own motion (``motion_checks``: the lens fit on
    its bound, a camera turned on the spot for most of the run, with the focal length
    estimated), or the focal search's minimum was not bracketed
    (``focal_choice.FocalChoice.found``). Off: return it, the verdicts in
    ``diagnostics["motion_checks"]`` (``--on-break keep``).
    """
    restart_after_loss: bool = False
    """Where the camera is lost in the middle of the video, track again from the first lost frame as a new piece.

    After at least 2 (max_lost + 1) tracked frames; with the first piece's camera
    (``recon.poses.frontend.pieces``), instead of falling back to SfM; the pieces come back as
    one estimate whose scale watch has a "lost" break at each restart. The pipeline turns it on
    with ``--on-break segments``.
    """
    failing_inlier: float = 0.85
    """With restart_after_loss, also give up the frames before a loss whose tracking was already failing (0: keep them).

    A piece that ends where the camera was lost also gives up the frames before the loss whose
    tracking was already failing: those after which, within a loss's length (max_lost + 1) of
    it, no three frames in a row explain this share of their flow confidence once the piece's
    BA is solved (``quality.failing_since``); its BA is then solved again without them. A map
    goes wrong before the front end loses it, and the frames in between pass every check one by
    one (the synthetic walk-through's corner: frames 176-185, 0.2-1.6 m off, each explaining
    0.65-0.98 of its flow).
    """
    min_match_correlation: float = bounded(0.5, CORRELATION)
    """A frame whose flow from a keyframe joins grey levels correlated less than this is not aligned to it.

    ``flow.match_correlation``: flow confidence alone passes unrelated images.
    """
    min_local_correlation: float = bounded(0.5, CORRELATION)
    """See min_match_correlation: nor when its 7x7 windows along the flow correlate less than this on average.

    ``flow.local_correlation``: a flow can bend an unrelated image onto the keyframe's coarse
    layout, less so onto its fine texture.
    """
    lost_inlier: float = bounded(0.25, FRACTION)
    """A frame whose alignment keeps less than this fraction of the flow confidence counts as lost.

    The confidence kept is that within the robust threshold.
    """
    max_lost: int = bounded(10, at_least(0))
    """Consecutive lost frames (after relocalisation attempts) that stop tracking."""
    reloc_candidates: int = bounded(4, at_least(0))
    """Older keyframes tried when a frame is lost against the last one."""
    calib_keyframes: int = bounded(10, at_least(2))
    """Keyframes used by the focal-length search."""
    calib_stride: int = bounded(8, at_least(1))
    """BA grid stride of the focal search."""
    calib_flow_stride: int = bounded(2, at_least(1))
    """See calib_stride: flow stride of the focal search.

    The flow is finer than while tracking, since f shows only in the flow field's slight
    bending.
    """
    calib_tol: float = bounded(0.01, POSITIVE)
    """Golden-section bracket width on log f at which the focal search stops (0.01 = 1 %)."""
    calib_iters: int = bounded(6, at_least(1))
    """See calib_tol: LM iterations per evaluated focal length."""
    align_chunk: int = bounded(64, at_least(1))
    """Non-keyframes aligned per batch at the end (bounds memory)."""
    torch_threads: int | None = bounded(None, at_least(1))
    """Intra-op threads while tracking (restored after); None leaves torch's setting alone.

    Set 1 when other work shares the cores.
    """
    seed_min_flow: float = bounded(2.0, at_least(0))
    """Retry a failed unseeded flow seeded by the start pose when that moves the keyframe's pixels at least this much.

    A frame whose unseeded flow from the keyframe fails the checks is tried again with DIS
    seeded by the flow its start pose (the previous frame's) predicts, when that moves the
    keyframe's pixels by at least this many flow pixels on average (a keyframe several fast
    frames back is beyond DIS's unseeded reach).
    """
    feature_init: bool = True
    """When flow fails from the prediction, start the frame from the PnP pose of its ORB matches to the keyframe.

    The pose that ORB matches to the keyframe give by PnP against its depth (``features``), and
    likewise when relocalising against older keyframes.
    """
    check_short_flow: bool = True
    """After the global BA, mark the stretches where the dense flow made consecutive keyframes' steps short.

    Each pair of consecutive keyframes' steps is checked against the images' gradients
    (``normal_flow``, its settings ``normal_flow``): a stretch where the dense flow made them
    short (plain surfaces: the flow's aperture problem) is marked in
    ``diagnostics["motion_checks"]`` and said by the run.
    """
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)
    """The nested settings of DIS flow (set in Python, not by ``--pose-option``)."""
    features: ft.FeatureConfig = field(default_factory=ft.FeatureConfig)
    """The nested settings of ORB features."""
    ba: ba.BAOptions = field(default_factory=ba.BAOptions)
    """The nested settings of the BA."""
    normal_flow: nf.NormalFlowConfig = field(default_factory=nf.NormalFlowConfig)
    """The nested settings of the short-flow check (``check_short_flow``)."""

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
