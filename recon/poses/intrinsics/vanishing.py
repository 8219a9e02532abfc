"""The focal length from vanishing points: a Manhattan world's three orthogonal directions.

Two vanishing points of orthogonal directions fix the focal length when the principal point
is known: (v1 - c) . (v2 - c) = -f^2 (Caprile and Torre, IJCV 1990); rooms and buildings are
built along three such directions (Coughlan and Yuille, "Manhattan world", ICCV 1999;
Kosecka and Zhang, "Video compass", ECCV 2002). :func:`line_segments` fits the plumb-line
regions, :func:`manhattan_support` scores orthogonal triads per candidate focal length and
:func:`estimate_focal_vp` takes the median of the largest group of frames whose peaks agree.
The principal point is the image centre; whether it is taken is ``focal_choice``'s rule.
More: docs/poses.md#vanishing-points
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.intrinsics import plumb_line as pl


@dataclass(frozen=True)
class VanishingConfig:
    """Settings of :func:`estimate_focal_vp`.

    fov_range: candidate horizontal fields of view (degrees), widest first; candidates are
        log-spaced in focal length, ``candidates`` of them.
    min_length: shortest segment used, as a fraction of the frame's width (shorter segments
        point too loosely).
    max_rms: a segment's rms distance from its line (pixels) after undistortion.
    tolerance: a segment's vote for a vanishing point falls from 1, when the direction from
        the segment's centre to the point is the segment's own, to 0 at this angle (degrees).
    triads: random segment triples tried per frame.
    min_drop: a frame's support curve must fall by this much (relative) on both sides of its
        peak for the frame to have a focal length (see :func:`curve_peak`).
    agree: frames whose focal lengths differ by less than this (relative) agree.
    min_share: the largest agreeing group must hold at least this share of the frames.
    min_frames: ... and at least this many frames.
    max_frames: frames used at most (evenly spaced among those given).
    max_width: wider frames are measured downscaled to this width.
    seed: the random triples' seed (the estimate is reproducible).
    """

    fov_range: tuple[float, float] = (120.0, 30.0)
    candidates: int = 100
    min_length: float = 0.06
    max_rms: float = 0.5
    tolerance: float = 1.5
    triads: int = 300
    min_drop: float = 0.02
    agree: float = 0.05
    min_share: float = 0.2
    min_frames: int = 6
    max_frames: int = 40
    max_width: int = 640
    seed: int = 0


@dataclass
class VanishingFocal:
    """Result of :func:`estimate_focal_vp`: focal (pixels of the frames given; 0 when no
    frame's curve peaked), share (of the frames used) and count of the frames in the
    agreeing group, frames whose curve peaked, frames used, and whether it is trusted
    (``min_share`` and ``min_frames`` met)."""

    focal: float
    share: float
    agreeing: int
    peaked: int
    frames: int
    trusted: bool

    def to_dict(self) -> dict:
        return {"focal": self.focal, "share": self.share, "agreeing": self.agreeing, "peaked": self.peaked,
                "frames": self.frames, "trusted": self.trusted}


def candidate_focals(width: int, cfg: VanishingConfig) -> np.ndarray:
    """Log-spaced candidate focal lengths (C,) in pixels for frames `width` pixels wide."""
    wide, narrow = (0.5 * width / math.tan(math.radians(fov) / 2.0) for fov in cfg.fov_range)
    return np.exp(np.linspace(math.log(wide), math.log(narrow), cfg.candidates))


def line_segments(regions: pl.EdgeRegions, corner_shift: float, cfg: VanishingConfig) -> tuple[np.ndarray, ...]:
    """Straight segments of a grey frame (its ``plumb_line.edge_regions``) seen through a lens
    of relative corner shift `corner_shift` (``plumb_line.LensEstimate``): lines (S, 3) (a, b,
    c) with a x + b y + c = 0 and (a, b) a unit normal, centres (S, 2) (the mean of a segment's
    points) and lengths (S,), in undistorted pixels about the image centre."""
    height, width = regions.shape
    points, ids = pl.regions_longer(regions, cfg.min_length)
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    half_diagonal = 0.5 * math.hypot(width - 1, height - 1)
    intr = torch.tensor([half_diagonal, half_diagonal, *centre], dtype=torch.float64)
    u = pj.undistort(torch.from_numpy(points), intr, corner_shift)[0].numpy() - np.asarray(centre)
    regions = int(ids.max()) + 1
    count = np.bincount(ids, minlength=regions).astype(np.float64)
    mean = np.stack([np.bincount(ids, u[:, k], regions) for k in range(2)], 1) / np.maximum(count, 1)[:, None]
    d = u - mean[ids]
    sxx, syy, sxy = (np.bincount(ids, w, regions) / np.maximum(count, 1)
                     for w in (d[:, 0] ** 2, d[:, 1] ** 2, d[:, 0] * d[:, 1]))
    # Principal axes of each region's scatter: the line's direction and its rms offset.
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    direction = np.stack([np.cos(theta), np.sin(theta)], 1)
    normal = np.stack([-direction[:, 1], direction[:, 0]], 1)
    off = np.einsum("pk,pk->p", d, normal[ids])
    along = np.einsum("pk,pk->p", d, direction[ids])
    rms = np.sqrt(np.bincount(ids, off**2, regions) / np.maximum(count, 1))
    lo = np.full(regions, np.inf)
    hi = np.full(regions, -np.inf)
    np.minimum.at(lo, ids, along)
    np.maximum.at(hi, ids, along)
    keep = (count >= 10) & (rms < cfg.max_rms)
    lines = np.concatenate([normal, -np.einsum("rk,rk->r", normal, mean)[:, None]], 1)
    return lines[keep], mean[keep], (hi - lo)[keep]


def manhattan_support(lines: np.ndarray, centres: np.ndarray, lengths: np.ndarray, focals: np.ndarray,
                      triples: np.ndarray, tolerance_deg: float) -> np.ndarray:
    """Support (C,) of the best orthogonal triad for each candidate focal length (C,): the
    summed length of the segments (S; see :func:`line_segments`) that point at one of its
    vanishing points, each weighted by how closely; the triads are proposed by `triples`
    (T, 3), indices of segments.

    A segment of direction (ux, uy) at centre c points at a vanishing point K d (centred
    pixels) when the vector t = f (dx, dy) - c dz toward it is parallel to u: sin^2 of the
    angle between them is (t x u)^2 / |t|^2. Both are bilinear in d and the segment, so for
    all triads and segments at once they are two small matrix products per direction."""
    direction = np.stack([-lines[:, 1], lines[:, 0]], 1)
    cx, cy = centres[:, 0], centres[:, 1]
    # t x u = [dx, dy, dz] . [f uy, -f ux, cy ux - cx uy]; |t|^2 = [f^2 (dx^2 + dy^2), -2 f dz dx,
    # -2 f dz dy, dz^2] . [1, cx, cy, cx^2 + cy^2]. The segment halves, without f:
    cross_rows = np.stack([direction[:, 1], -direction[:, 0], cy * direction[:, 0] - cx * direction[:, 1]])  # (3, S)
    norm_rows = np.stack([np.ones_like(cx), cx, cy, cx**2 + cy**2])  # (4, S)
    inv_tol2 = 1.0 / math.sin(math.radians(tolerance_deg)) ** 2
    # The triads' directions for every focal length at once (small arrays; the same numbers
    # as one focal length at a time). The plane through the camera centre and a segment has
    # normal K^T l.
    f = focals[:, None, None]
    n = np.concatenate([lines[None, :, :2] * f, np.broadcast_to(lines[None, :, 2:], (len(focals), len(lines), 1))], 2)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    all_d1, ok1 = _unit(np.cross(n[:, triples[:, 0]], n[:, triples[:, 1]]))
    all_d2, ok2 = _unit(np.cross(all_d1, n[:, triples[:, 2]]))
    all_d3 = np.cross(all_d1, all_d2)
    # Segments on one line (or on one plane through the camera) propose no direction.
    proposes = ok1 & ok2
    support = np.zeros(len(focals))
    for k, fk in enumerate(focals):
        # The (T, S) votes one focal length at a time, in place: they stay in cache.
        closeness = None
        for d in (all_d1[k], all_d2[k], all_d3[k]):
            cross = (d * [fk, fk, 1.0]) @ cross_rows  # (T, S)
            dz = d[:, 2]
            norm2 = np.stack([fk * fk * (d[:, 0] ** 2 + d[:, 1] ** 2), -2.0 * fk * dz * d[:, 0],
                              -2.0 * fk * dz * d[:, 1], dz * dz], 1) @ norm_rows
            # A soft vote (1 on the point, 0 at the tolerance): a hard one is flat over a range
            # of focal lengths, and its argmax would take the range's first end.
            # vote = 1 - cross^2 / max(norm2, 1e-24) / sin^2(tolerance)
            np.multiply(cross, cross, out=cross)
            np.divide(cross, np.maximum(norm2, 1e-24, out=norm2), out=cross)
            np.multiply(cross, inv_tol2, out=cross)
            vote = np.subtract(1.0, cross, out=cross)
            closeness = np.maximum(vote, 0.0, out=vote) if closeness is None else np.maximum(closeness, vote,
                                                                                              out=closeness)
        support[k] = ((closeness @ lengths) * proposes[k]).max()
    return support


def _unit(v: np.ndarray, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (..., 3) of v and whether each was long enough (...) to have a direction."""
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(norm, eps), norm[..., 0] > eps


def curve_peak(values: np.ndarray, focals: np.ndarray, min_drop: float) -> float | None:
    """The focal length at the peak of a support curve (C,) over focals (C,), refined by a
    parabola on log f; None unless the curve falls by ``min_drop`` (relative) from its peak
    on both sides: a frame with a single finite vanishing point gives a flat curve."""
    best = int(np.argmax(values))
    top = values[best]
    if top <= 0 or max(values[: best + 1].min(), values[best:].min()) > (1.0 - min_drop) * top:
        return None
    before, at, after = values[best - 1 : best + 2]
    bend = before - 2.0 * at + after
    shift = 0.5 * (before - after) / bend if bend < 0 else 0.0
    return float(focals[best] * math.exp(shift * math.log(focals[best + 1] / focals[best])))


def agreeing_group(values: np.ndarray, agree: float) -> np.ndarray:
    """Mask (N,) of the largest group of values (N,) within `agree` (relative) of one of them."""
    logs = np.log(values)
    close = np.abs(logs[:, None] - logs[None]) < agree
    return close[int(close.sum(1).argmax())]


def estimate_focal_vp(frames, lens: pl.LensEstimate | None = None, cfg: VanishingConfig | None = None,
                      regions: pl.SampledRegions | None = None) -> VanishingFocal:
    """The focal length (pixels, principal point at the centre) of frames (list of (H, W, 3)
    uint8 RGB, one camera) from their vanishing points; `lens`: measured from straight
    edges (None or untrusted: a pinhole camera). regions: the frames' edge regions
    (``plumb_line.sample_regions`` with the plumb line's default edge settings), made once
    for this and the lens (None, or made for other frame settings: made here)."""
    cfg = cfg or VanishingConfig()
    edges = pl.PlumbLineConfig()
    if regions is None or not regions.serves(edges, cfg.max_frames, cfg.max_width):
        regions = pl.sample_regions(frames, edges, cfg.max_frames, cfg.max_width)
    scale = regions.scale
    corner_shift = lens.corner_shift if lens is not None and lens.trusted else 0.0
    focals = candidate_focals(regions.shape[1], cfg)
    rng = np.random.default_rng(cfg.seed)
    peaks = []
    for frame_regions in regions.regions:
        lines, centres, lengths = line_segments(frame_regions, corner_shift, cfg)
        if len(lines) < 3:
            continue
        triples = rng.integers(0, len(lines), (cfg.triads, 3))
        triples = triples[(triples[:, 0] != triples[:, 1]) & (triples[:, 1] != triples[:, 2])
                          & (triples[:, 0] != triples[:, 2])]
        if len(triples) == 0:
            continue
        support = manhattan_support(lines, centres, lengths, focals, triples, cfg.tolerance)
        peak = curve_peak(support, focals, cfg.min_drop)
        if peak is not None:
            peaks.append(peak)
    if not peaks:
        return VanishingFocal(0.0, 0.0, 0, 0, len(regions.regions), False)
    peaks = np.asarray(peaks)
    group = agreeing_group(peaks, cfg.agree)
    share = float(group.sum()) / len(regions.regions)
    trusted = share >= cfg.min_share and int(group.sum()) >= cfg.min_frames
    return VanishingFocal(float(np.median(peaks[group])) / scale, share, int(group.sum()), len(peaks),
                          len(regions.regions), trusted)


__all__ = ["VanishingConfig", "VanishingFocal", "agreeing_group", "candidate_focals",
           "curve_peak", "estimate_focal_vp", "line_segments", "manhattan_support"]
