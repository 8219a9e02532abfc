"""The lens' radial distortion from straight edges: the plumb-line method.

Straight lines in the world are straight in a pinhole image; a radial lens bends them (D. C.
Brown, "Close-range camera calibration", 1971; Devernay and Faugeras, "Straight lines have
to be straight", MVA 2001). :func:`line_support` finds line-support regions of sub-pixel edge
pixels, :func:`line_rms` measures their straightness under a candidate lens and
:func:`estimate_lens` picks the lens that straightens them: that of ``projective.undistort``
(x recorded at ``x (1 + k1 |x|^2)``), measured as ``kappa R^2`` (the radial shift at the
corner) without the focal length; ``k1(f)`` converts it. Principal point: the image centre.
More: docs/poses.md#the-lens-from-straight-edges
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.result import evenly_apart
from recon.threads import map_on_cores


@dataclass(frozen=True)
class PlumbLineConfig:
    """Settings of :func:`estimate_lens`.

    corner_shifts: the candidate lenses, as the relative radial shift of the frame's corner
        (``kappa R^2``; -0.02 is the 7-Scenes colour lens, k1 -0.035 at 525 px).
    min_length: shortest line-support region used, as a fraction of the frame's width
        (120 px at 640); shorter edges bend too little to tell lenses apart.
    max_rms: a region counts as a straight edge when its rms distance from a line is below
        this (pixels) for some candidate lens.
    cap: a region's rms is capped here (pixels) in the score, so that an edge that is
        straight for only some candidates cannot outweigh the rest.
    min_regions: fewer straight regions than this (scenes without man-made edges, heavy
        texture) give no estimate.
    canny_low, canny_high: Canny's hysteresis thresholds on 8-bit grey levels.
    blur_sigma: Gaussian blur (pixels) before the gradients that place edges to sub-pixel.
    max_frames: frames used at most (evenly spaced among those given).
    max_width: wider frames are measured downscaled to this width (the corner shift is
        relative, so it does not depend on the resolution; the time does).
    """

    corner_shifts: tuple[float, ...] = tuple(float(v) for v in np.round(np.arange(-0.10, 0.0501, 0.0025), 4))
    min_length: float = 0.1875
    max_rms: float = 0.4
    cap: float = 0.5
    min_regions: int = 40
    canny_low: float = 40.0
    canny_high: float = 100.0
    blur_sigma: float = 1.0
    max_frames: int = 40
    max_width: int = 640

    @property
    def edge_settings(self) -> tuple[float, float, float]:
        """The settings :func:`edge_regions` reads (blur_sigma, canny_low, canny_high)."""
        return self.blur_sigma, self.canny_low, self.canny_high


@dataclass
class LensEstimate:
    """Result of :func:`estimate_lens`.

    corner_shift: relative radial shift at the frame's corner (``kappa R^2``; 0 when not
        trusted). half_diagonal: R in pixels of the frames given. regions: straight
        line-support regions used.
    trusted: enough straight regions and a minimum inside the candidates. scores: the
    score of every candidate (same order as the config's corner_shifts)."""

    corner_shift: float
    half_diagonal: float
    regions: int
    trusted: bool
    scores: list[float] = field(default_factory=list)

    def k1(self, focal: float) -> float:
        """The lens' k1 (``projective.undistort``) for a pinhole focal length `focal` (pixels)."""
        return self.corner_shift * (focal / self.half_diagonal) ** 2

    def to_dict(self) -> dict:
        return {"corner_shift": self.corner_shift, "regions": self.regions, "trusted": self.trusted}


def sample_grays(frames, max_frames: int, max_width: int) -> tuple[list[np.ndarray], float]:
    """Grey images (H', W') uint8 of at most `max_frames` frames (list of (H, W, 3) uint8 RGB),
    evenly spaced, downscaled to at most `max_width` wide; and that scale (H' = scale H)."""
    height, width = frames[0].shape[:2]
    scale = min(1.0, max_width / width)
    size = (round(width * scale), round(height * scale))
    chosen = evenly_apart(len(frames), max_frames)
    grays = [cv2.cvtColor(np.ascontiguousarray(frames[i]), cv2.COLOR_RGB2GRAY) for i in chosen]
    if scale < 1.0:
        grays = [cv2.resize(g, size, interpolation=cv2.INTER_AREA) for g in grays]
    return grays, scale


@dataclass(frozen=True)
class EdgeRegions:
    """The edge pixels of one grey frame grouped into regions, before the length filter of
    :func:`line_support`: per gradient-direction bin (8 bins, at two offsets) the sub-pixel
    edge points (n, 2) (x, y), their connected-component label (n,) (0: none) and every
    label's extent in pixels (L,). shape: the frame's (H, W)."""

    shape: tuple[int, int]
    bins: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]


@dataclass(frozen=True)
class SampledRegions:
    """``edge_regions`` (with ``edges``' settings) of the frames ``sample_grays`` picks for
    (max_frames, max_width), with that downscale: made once, read by :func:`estimate_lens`
    and ``vanishing.estimate_focal_vp`` when their settings match (``serves``)."""

    regions: tuple[EdgeRegions, ...]
    scale: float
    edges: PlumbLineConfig
    max_frames: int
    max_width: int

    @property
    def shape(self) -> tuple[int, int]:
        """The grey frames' (H', W')."""
        return self.regions[0].shape

    def serves(self, edges: PlumbLineConfig, max_frames: int, max_width: int) -> bool:
        """Whether these are the regions an estimator with these edge and frame settings finds."""
        return (self.edges.edge_settings, self.max_frames, self.max_width) == (edges.edge_settings, max_frames,
                                                                             max_width)


def edge_regions(gray: np.ndarray, cfg: PlumbLineConfig) -> EdgeRegions:
    """Sub-pixel edge points of a grey frame (H, W) uint8 grouped into connected regions of
    like gradient direction (cfg: blur_sigma, canny_low, canny_high)."""
    height, width = gray.shape
    g = cv2.GaussianBlur(gray, (0, 0), cfg.blur_sigma).astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    ys, xs = np.nonzero(cv2.Canny(gray, cfg.canny_low, cfg.canny_high, L2gradient=True))
    m0 = mag[ys, xs]
    nx, ny = gx[ys, xs] / np.maximum(m0, 1e-6), gy[ys, xs] / np.maximum(m0, 1e-6)

    def mag_at(sign: float) -> np.ndarray:
        xx = np.clip(np.rint(xs + sign * nx).astype(np.int64), 0, width - 1)
        yy = np.clip(np.rint(ys + sign * ny).astype(np.int64), 0, height - 1)
        return mag[yy, xx]

    ahead, behind = mag_at(1.0), mag_at(-1.0)
    curvature = ahead - 2.0 * m0 + behind
    peak = np.where(curvature < -1e-6, 0.5 * (behind - ahead) / np.where(curvature < -1e-6, curvature, -1.0), 0.0)
    peak = np.clip(peak, -0.5, 0.5)
    points = np.stack([xs + peak * nx, ys + peak * ny], 1)

    bins = 8
    angle = np.mod(np.arctan2(ny, nx), np.pi) / (np.pi / bins)
    found = []
    for offset in (0.0, 0.5):
        label_of_bin = np.floor(angle + offset).astype(np.int64) % bins
        for b in range(bins):
            sel = label_of_bin == b
            mask = np.zeros((height, width), np.uint8)
            mask[ys[sel], xs[sel]] = 1
            _, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
            extent = np.hypot(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
            found.append((points[sel], labels[ys[sel], xs[sel]], extent))
    return EdgeRegions((height, width), tuple(found))


def regions_longer(regions: EdgeRegions, min_length: float) -> tuple[np.ndarray, np.ndarray]:
    """The edge points (P, 2) (x, y) of the regions at least ``min_length`` x W long and their
    region ids (P,) int64, 0..regions-1 (``line_support``)."""
    min_extent = min_length * regions.shape[1]
    all_points, all_ids, count = [], [], 0
    for points, labels, extent in regions.bins:
        keep = np.nonzero(extent >= min_extent)[0]
        keep = keep[keep > 0]  # label 0 is the background
        if len(keep) == 0:
            continue
        region = np.full(len(extent), -1, dtype=np.int64)
        region[keep] = np.arange(len(keep)) + count
        ids = region[labels]
        inside = ids >= 0
        all_points.append(points[inside])
        all_ids.append(ids[inside])
        count += len(keep)
    if not all_points:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    return np.concatenate(all_points), np.concatenate(all_ids)


def line_support(gray: np.ndarray, cfg: PlumbLineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel edge points (P, 2) (x, y) of a grey frame (H, W) uint8 and their region ids
    (P,) int64, 0..regions-1; only regions at least ``cfg.min_length`` x W long."""
    return regions_longer(edge_regions(gray, cfg), cfg.min_length)


def sample_regions(frames, cfg: PlumbLineConfig, max_frames: int, max_width: int) -> SampledRegions:
    """``edge_regions`` (cfg's edge settings) of the frames (list of (H, W, 3) uint8 RGB)
    ``sample_grays`` picks for max_frames and max_width."""
    grays, scale = sample_grays(frames, max_frames, max_width)
    # Mostly OpenCV and numpy calls that release the GIL: the frames on every core.
    regions = tuple(map_on_cores(lambda gray: edge_regions(gray, cfg), grays))
    return SampledRegions(regions, scale, cfg, max_frames, max_width)


def line_rms(points: torch.Tensor, ids: torch.Tensor, centre: tuple[float, float], half_diagonal: float,
             corner_shifts) -> torch.Tensor:
    """rms distance (R, K) of each region's undistorted points from its total-least-squares
    line, for K candidate lenses. points (P, 2) float64 pixels, ids (P,) region ids 0..R-1;
    corner_shifts: the candidates as relative radial shifts at distance half_diagonal."""
    regions = int(ids.max()) + 1
    count = torch.bincount(ids, minlength=regions).double()
    # With the focal length set to the half diagonal, k1 is the corner shift itself.
    intr = torch.tensor([half_diagonal, half_diagonal, *centre], dtype=torch.float64)

    def region_mean(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros(regions, dtype=torch.float64).index_add_(0, ids, values) / count

    rms = []
    for shift in corner_shifts:
        u, _ = pj.undistort(points, intr, float(shift))
        dx = u[:, 0] - region_mean(u[:, 0])[ids]
        dy = u[:, 1] - region_mean(u[:, 1])[ids]
        sxx, syy, sxy = region_mean(dx * dx), region_mean(dy * dy), region_mean(dx * dy)
        half_trace = 0.5 * (sxx + syy)
        smallest = half_trace - torch.sqrt(torch.clamp(half_trace**2 - (sxx * syy - sxy * sxy), min=0.0))
        rms.append(torch.sqrt(torch.clamp(smallest, min=0.0)))
    return torch.stack(rms, 1)


def estimate_lens(frames, cfg: PlumbLineConfig | None = None, regions: SampledRegions | None = None) -> LensEstimate:
    """The radial lens of frames (list of (H, W, 3) uint8 RGB, one camera) from their straight
    edges, principal point at the image centre. An untrusted estimate has corner_shift 0.
    regions: the frames' ``sample_regions`` with cfg's edge settings, made once for this and
    the vanishing points (None, or made for other frame settings: made here)."""
    cfg = cfg or PlumbLineConfig()
    height, width = frames[0].shape[:2]
    half_diagonal = 0.5 * float(np.hypot(width - 1, height - 1))
    if regions is None or not regions.serves(cfg, cfg.max_frames, cfg.max_width):
        regions = sample_regions(frames, cfg, cfg.max_frames, cfg.max_width)
    size = regions.shape[::-1]
    centre = ((size[0] - 1) / 2.0, (size[1] - 1) / 2.0)
    points, ids, count = [], [], 0
    for frame_regions in regions.regions:
        p, r = regions_longer(frame_regions, cfg.min_length)
        points.append(p)
        ids.append(r + count)
        count += int(r.max()) + 1 if len(r) else 0
    candidates = np.asarray(cfg.corner_shifts, dtype=np.float64)
    if count == 0:
        return LensEstimate(0.0, half_diagonal, 0, False)
    ids_t = torch.from_numpy(np.concatenate(ids))
    rms = line_rms(torch.from_numpy(np.concatenate(points)), ids_t, centre,
                   0.5 * float(np.hypot(size[0] - 1, size[1] - 1)), candidates)
    straight = rms.min(1).values < cfg.max_rms
    length = torch.bincount(ids_t, minlength=rms.shape[0]).double()
    scores = (length[straight, None] * torch.clamp(rms[straight], max=cfg.cap) ** 2).sum(0).numpy()
    best = int(np.argmin(scores))
    regions = int(straight.sum())
    inside = 0 < best < len(candidates) - 1
    if not (inside and regions >= cfg.min_regions):
        return LensEstimate(0.0, half_diagonal, regions, False, scores.tolist())
    before, at, after = scores[best - 1 : best + 2]
    bend = before - 2.0 * at + after
    step = candidates[best + 1] - candidates[best]
    vertex = candidates[best] + (0.5 * (before - after) / bend * step if bend > 0 else 0.0)
    return LensEstimate(float(vertex), half_diagonal, regions, True, scores.tolist())


__all__ = ["EdgeRegions", "LensEstimate", "PlumbLineConfig", "SampledRegions", "edge_regions", "estimate_lens",
           "line_rms", "line_support", "regions_longer", "sample_grays", "sample_regions"]
