"""Whether the metric scale that a monocular trajectory takes from the depth prior can be
trusted: does the prior's depth follow the scene as the images measured it?

The trajectory's metres come from the depth network as one factor, only as good as the
network is on this scene. Depth triangulated from the frames' flow (or SfM's points) is
independent of the network, so comparing the two *shapes* (the scale-free part of Eigen et
al. 2014's scale-invariant log error) tells whether the network saw this scene: a necessary
condition, not a sufficient one. :func:`judge_agreement` gives the verdict report.json
carries; keyframes whose measured depth barely varies are not counted.
More: docs/poses.md#metric-scale-the-depth-prior-cannot-vouch-for
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from recon.geometry import projective as pj


@dataclass(frozen=True)
class AgreementConfig:
    """min_correlation: the median over keyframes of the prior's log depth against the
        measured depth (Pearson) below which the prior's scale is not trusted.
        why: docs/decisions.md#metric-scale-the-depth-prior-cannot-vouch-for
    min_spread: the least standard deviation of a keyframe's measured log depth for it to
        count (0.05: depth varying by +-5 % over the image, a wall seen face on);
    min_keyframes: fewer counted keyframes than this are not judged;
    min_pixels: the least measured pixels (or SfM points) for a keyframe to count;
    max_error: a pixel counts as measured where its depth, triangulated from its flow alone
        (:func:`triangulated_depth`), is known within this share of it."""

    min_correlation: float = 0.4
    min_spread: float = 0.05
    min_keyframes: int = 3
    min_pixels: int = 50
    max_error: float = 0.2


@dataclass
class PriorAgreement:
    """What report.json says (``poses.metric_scale``): per counted keyframe its frame and
    correlation, their median, and the verdict. ``judged`` is False where too few keyframes
    could tell; ``trusted`` is then True (nothing speaks against the prior)."""

    frames: list[int]
    correlation: list[float]
    median: float
    judged: bool
    trusted: bool
    min_correlation: float

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "PriorAgreement":
        return cls(**d)

    def renumbered(self, names) -> "PriorAgreement":
        """The same with frames renamed by ``names[frame]`` (e.g. video frame numbers)."""
        return PriorAgreement([int(names[f]) for f in self.frames], list(self.correlation), self.median,
                              self.judged, self.trusted, self.min_correlation)

    def finding(self) -> str:
        """What the check found, in one clause: the frames and the correlation."""
        first, last = (min(self.frames), max(self.frames)) if self.frames else (0, 0)
        return (f"the depth prior does not follow the scene's geometry at frames {first}-{last}: its log depth "
                f"correlates {self.median:+.2f} with the depth the frames' parallax measures (the median over "
                f"{len(self.frames)} keyframes; {self.min_correlation:g} is needed, and a prior that sees the scene "
                f"reaches 0.7-0.95)")

    def said(self) -> str:
        """What is wrong and what the run does about it, in one sentence without its end."""
        return (f"{self.finding()}: the scene is outside what the depth model knows (a close-up, an outdoor "
                f"view) or the camera moves too little to measure it, so the result is written at a size that "
                f"is not to be trusted (the trajectory, depth and mesh may be x1.5 to several times off in "
                f"scale; their shape is not affected); a depth model made for such scenes (--prior hf) or the "
                f"scene's depth maps (--prior folder) give the metres, --on-break stop refuses such a result")

    def refusal(self) -> str:
        """The stop of ``--on-break stop``, in one sentence."""
        return (f"stopped (--on-break stop): {self.finding()}, so the metric scale of the trajectory, depth and "
                f"mesh may be off by x1.5 to several times. Give a depth model made for such scenes (--prior hf) "
                f"or the scene's depth maps (--prior folder), or run without --on-break stop to take the result "
                f"marked as of untrusted scale")


def _pearson(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Pearson correlation of x and y along the last axis, and x's standard
    deviation. x, y, w: (K, P); w 0/1 masks. Returns (K,), (K,) (NaN where w sums to 0)."""
    n = w.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = (w * x).sum(-1) / n
        my = (w * y).sum(-1) / n
        dx, dy = np.where(w > 0, x - mx[:, None], 0.0), np.where(w > 0, y - my[:, None], 0.0)
        vx, vy = (dx * dx).sum(-1) / n, (dy * dy).sum(-1) / n
        corr = (dx * dy).sum(-1) / n / np.sqrt(vx * vy)
    return corr, np.sqrt(vx)


def log_depth_correlation(map_depth: np.ndarray, prior_depth: np.ndarray, measured: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per keyframe, the correlation of the prior's log depth with the map's over the pixels
    the map measured.

    map_depth, prior_depth: (K, h, w) depth (any unit; <= 0 or non-finite: none); measured:
    (K, h, w) bool, pixels whose depth the images measured (for the front end: pixels whose
    depth :func:`triangulated_depth` knows within ``AgreementConfig.max_error``). Returns
    (correlation, spread, pixels), each (K,): spread is the standard deviation of the map's
    log depth over those pixels."""
    m = np.asarray(map_depth, np.float64)
    p = np.asarray(prior_depth, np.float64)
    ok = np.asarray(measured, bool) & (m > 0) & (p > 0) & np.isfinite(m) & np.isfinite(p)
    k = len(m)
    lm = np.log(np.where(ok, m, 1.0)).reshape(k, -1)
    lp = np.log(np.where(ok, p, 1.0)).reshape(k, -1)
    w = ok.reshape(k, -1).astype(np.float64)
    corr, spread = _pearson(lm, lp, w)
    return corr, spread, w.sum(-1).astype(np.int64)


def triangulated_depth(T_ji: torch.Tensor, targets: torch.Tensor, weights: torch.Tensor, intr: torch.Tensor,
                       k1: float = 0.0, flow_sigma: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth of a keyframe's pixels from its flow to other keyframes alone, without the prior.

    The bundle adjustment's own depth is not independent of the prior: it starts there and
    a weak term holds it there wherever the flow says little (the synthetic room with its
    prior mirrored came back with a map correlating +0.45 with that prior). Here each pixel
    is triangulated from where its flow lands in the other keyframes, at the BA's poses:
    with r its ray and q = (x, y) where it lands (normalised coordinates), the depth z solves
    q (R r z + t)_z = (R r z + t)_xy, two linear equations per edge, solved together by
    least squares weighted by each landing's confidence and precision.

    T_ji: (E, 4, 4) float64 from the keyframe's camera to each other keyframe's; targets:
    (E, h, w, 2) BA-grid pixels where its flow lands there; weights: (E, h, w) the flow's
    confidence; intr: (4,) BA-grid intrinsics; k1: the lens' radial term (targets and rays
    are undistorted first); flow_sigma: the flow's error (BA-grid pixels) the precision is
    given for. Returns depth (h, w) and its standard error relative to it (h, w), inf where
    the flow does not measure it (no parallax, no weight, behind a camera)."""
    h, w = targets.shape[1:3]
    grid = pj.pixel_grid(h, w, dtype=torch.float64)
    fx, fy, cx, cy = intr.double().unbind(-1)
    focal = torch.stack([fx, fy])
    centre = torch.stack([cx, cy])
    ray = torch.cat([(pj.undistort(grid, intr, k1)[0] - centre) / focal, torch.ones(h, w, 1, dtype=torch.float64)], -1)
    q = (pj.undistort(targets.double(), intr, k1)[0] - centre) / focal                     # (E, h, w, 2)
    R, t = T_ji[:, None, None, :3, :3].double(), T_ji[:, None, None, :3, 3].double()
    Rr = (R @ ray[None, ..., None])[..., 0]                                                # (E, h, w, 3)
    a = q * Rr[..., 2:] - Rr[..., :2]
    b = t[..., :2] - q * t[..., 2:]
    wt = weights.double()
    # Each equation's error is the landing's error times the point's depth in the other
    # camera, so the weights need the depth: solved once plainly, then weighted by it.
    z = ((wt[..., None] * a * b).sum((0, -1)) / (wt[..., None] * a * a).sum((0, -1)).clamp(min=1e-12))
    for _ in range(2):
        depth_j = Rr[..., 2] * z + t[..., 2]
        info = wt * (a * a).sum(-1) / (flow_sigma / focal.mean() * depth_j.clamp(min=1e-6)) ** 2
        info = torch.where(depth_j > 0, info, torch.zeros_like(info))
        total = info.sum(0)
        z = (info[..., None] * a * b / (a * a).sum(-1, keepdim=True).clamp(min=1e-12)).sum((0, -1)) \
            / total.clamp(min=1e-12)
    rel = torch.where((total > 0) & (z > 0), 1.0 / (total.clamp(min=1e-12).sqrt() * z.abs().clamp(min=1e-12)),
                      torch.full_like(z, float("inf")))
    return z, rel


def keyframe_triangulations(T_cw: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, targets: torch.Tensor,
                            weights: torch.Tensor, intr: torch.Tensor, k1: float = 0.0
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`triangulated_depth` of every keyframe from its outgoing edges.

    T_cw: (K, 4, 4) world-to-camera poses; ii, jj: (E,) each edge's keyframes (from ii to
    jj); targets (E, h, w, 2), weights (E, h, w) as the BA's edges hold them. Returns depth
    and relative error, (K, h, w) each (inf error for a keyframe without edges)."""
    k, (h, w) = len(T_cw), targets.shape[1:3]
    depth = torch.zeros(k, h, w, dtype=torch.float64)
    rel = torch.full((k, h, w), float("inf"), dtype=torch.float64)
    T_wc = torch.linalg.inv(T_cw.double())
    for i in torch.unique(ii).tolist():
        out = ii == i
        T_ji = T_cw[jj[out]].double() @ T_wc[i]
        depth[i], rel[i] = triangulated_depth(T_ji, targets[out], weights[out], intr, k1)
    return depth, rel


def point_log_correlation(point_depth: np.ndarray, prior_depth: np.ndarray) -> tuple[float, float, int]:
    """The same for one image's triangulated points: point_depth (P,) their depth in the
    camera (SfM units), prior_depth (P,) the prior's at their pixels. Returns (correlation,
    spread, points)."""
    z = np.asarray(point_depth, np.float64)
    d = np.asarray(prior_depth, np.float64)
    ok = (z > 0) & (d > 0) & np.isfinite(z) & np.isfinite(d)
    if not ok.any():
        return float("nan"), float("nan"), 0
    corr, spread = _pearson(np.log(z[ok])[None], np.log(d[ok])[None], np.ones((1, int(ok.sum()))))
    return float(corr[0]), float(spread[0]), int(ok.sum())


def judge_agreement(frames, correlation, spread, pixels, cfg: AgreementConfig | None = None) -> PriorAgreement:
    """The verdict over keyframes (module docstring): frames (K,) their frame indices,
    correlation, spread and pixels (K,) as :func:`log_depth_correlation` returns them;
    keyframes below the spread or pixel floors, or without a value, are not counted."""
    cfg = cfg or AgreementConfig()
    corr = np.asarray(correlation, np.float64)
    count = (np.asarray(spread, np.float64) >= cfg.min_spread) & (np.asarray(pixels) >= cfg.min_pixels) \
        & np.isfinite(corr)
    return _verdict([int(f) for f, c in zip(frames, count) if c], corr[count], cfg)


def joined(parts: list[PriorAgreement], cfg: AgreementConfig | None = None) -> PriorAgreement:
    """One verdict over several pieces' counted keyframes (frames already in one numbering)."""
    return _verdict([f for p in parts for f in p.frames], np.array([c for p in parts for c in p.correlation]),
                    cfg or AgreementConfig())


def _verdict(frames: list[int], values: np.ndarray, cfg: AgreementConfig) -> PriorAgreement:
    """The median of the counted keyframes' correlations against the threshold."""
    judged = len(frames) >= cfg.min_keyframes
    median = float(np.median(values)) if values.size else float("nan")
    return PriorAgreement(frames, [round(float(v), 4) for v in values], median, judged,
                          trusted=not judged or median >= cfg.min_correlation, min_correlation=cfg.min_correlation)


__all__ = ["AgreementConfig", "PriorAgreement", "judge_agreement", "joined", "keyframe_triangulations",
           "log_depth_correlation", "point_log_correlation", "triangulated_depth"]
