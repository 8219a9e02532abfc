"""Where a monocular trajectory's scale breaks: the map's depth against the metric prior's,
keyframe by keyframe.

While tracking holds, the ratio of the BA's keyframe depth (scale-free) to the depth
prior's (metric, noisy) wanders only by the prior's noise; where the map's scale slips it
steps or drifts and stays there, which one global rescale cannot undo. The check ORB-SLAM
and DROID-SLAM users do by hand against a depth sensor, with the prior as the sensor:
:func:`keyframe_log_ratios` (robust median per keyframe), :func:`find_breaks` (a change-point
test on running medians, in the spirit of CUSUM) and :func:`watch_scale`.
More: docs/poses.md#scale-breaks---on-break-and---no-join
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

# The standard error of a median of n samples of a normal variable is about this many
# standard deviations over sqrt(n).
_MEDIAN_EFFICIENCY = 1.2533
# MAD to standard deviation for normal data.
_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class ScaleWatchConfig:
    """window: keyframes on each side of a candidate step whose medians are compared;
    min_step: the smallest step (as a factor) called a break, whatever the noise: a few
        percent of scale change over a video is within what the prior's scale error does;
    z: how many standard errors the step must exceed (the prior's noise measured on the run
        itself, from keyframe to keyframe);
    min_keyframes: fewer keyframes than this are not judged (too little to tell noise from a
        step);
    drift_share, min_drift: a creep of the map's scale, with no step to find: the ratio is
        smoothed as a random walk whose step per keyframe is ``drift_share`` of the prior's
        noise (``smooth_log_ratio``) and a break is called where the smoothed ratio has
        moved by ``min_drift`` (a factor) since the start of its stretch; 0 turns it off.
        On the prior's noise alone (simulated, 0.22 a keyframe) the smoothed ratio of 200
        keyframes spans x1.24 in 99 runs of 100 (x1.14 at 0.05, x1.36 at 0.2)."""

    window: int = 8
    min_step: float = 1.25
    z: float = 5.0
    min_keyframes: int = 16
    drift_share: float = 0.1
    min_drift: float = 1.3


@dataclass(frozen=True)
class ScaleBreak:
    """A step in the map-to-prior depth ratio: between keyframes ``before`` and ``after``
    (frame indices), the map's depth changes by ``factor`` relative to the prior's (< 1: the
    map shrinks after it); ``z``: the step in standard errors of the prior's noise; ``kind``:
    "step", "drift" where the ratio crept by ``factor`` since the last break (``find_drifts``), or
    "lost" where tracking lost the camera and started again (``recon.poses.frontend.pieces``; factor 1)."""

    before: int
    after: int
    factor: float
    z: float
    kind: str = "step"


@dataclass
class ScaleWatch:
    """What report.json says: per keyframe (``frames``) the map's depth against the prior's,
    divided by the run's median (1 = at the run's scale); ``noise``: the prior's scale noise
    from keyframe to keyframe (standard deviation of the log ratio); ``breaks``; ``judged``:
    whether there were enough keyframes to judge; ``corrections``: per break, the factor that
    brings the stretch after it to the scale of the one before (``stretch_factors``);
    ``applied``: whether the front end applied them (``FrontendConfig.join_scale_breaks``);
    ``turning``: steps inside stretches where the camera turns on the spot, not counted as
    breaks (:meth:`without_turns`)."""

    frames: list[int]
    ratio: list[float]
    noise: float
    breaks: list[ScaleBreak] = field(default_factory=list)
    judged: bool = True
    corrections: list[float] = field(default_factory=list)
    applied: bool = False
    turning: list[ScaleBreak] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"frames": self.frames, "ratio": [round(r, 4) for r in self.ratio], "noise": self.noise,
                "breaks": [asdict(b) for b in self.breaks], "judged": self.judged, "corrections": self.corrections,
                "applied": self.applied, "turning": [asdict(b) for b in self.turning]}

    @classmethod
    def from_dict(cls, d: dict) -> "ScaleWatch":
        return cls(list(d["frames"]), list(d["ratio"]), d["noise"], [ScaleBreak(**b) for b in d["breaks"]],
                   d["judged"], list(d.get("corrections", [])), bool(d.get("applied", False)),
                   [ScaleBreak(**b) for b in d.get("turning", [])])

    def renumbered(self, names) -> "ScaleWatch":
        """The same with frame positions (0..N-1 of the frames tracked) replaced by names[i]
        (the video's frame numbers)."""
        def named(b: ScaleBreak) -> ScaleBreak:
            return replace(b, before=int(names[b.before]), after=int(names[b.after]))

        return ScaleWatch([int(names[i]) for i in self.frames], self.ratio, self.noise,
                          [named(b) for b in self.breaks], self.judged, self.corrections, self.applied,
                          [named(b) for b in self.turning])

    def without_turns(self, rotation_only: list[list[int]]) -> "ScaleWatch":
        """The same with the breaks that lie inside a stretch where the camera turns on the
        spot (``motion_checks``: [first, last] frames) moved to ``turning``: there the map has
        no scale to break (no parallax measures its depth;
        why: docs/decisions.md#joining-across-a-break). Breaks already
        applied (``corrections``) are kept as they are."""
        if self.applied or not self.breaks:
            return self
        inside = [any(a <= b.before and b.after <= z for a, z in rotation_only) for b in self.breaks]
        kept = [b for b, turn in zip(self.breaks, inside) if not turn]
        return replace(self, breaks=kept, turning=self.turning + [b for b, turn in zip(self.breaks, inside) if turn],
                       corrections=[c for c, turn in zip(self.corrections, inside) if not turn])

    def joined(self, later: "ScaleWatch", restart: ScaleBreak) -> "ScaleWatch":
        """The watch of a run followed by that of a later piece of it, `restart` the break
        between them (``recon.poses.frontend.pieces``; frames numbered in the whole video)."""
        return ScaleWatch(self.frames + later.frames, self.ratio + later.ratio,
                          float(np.nanmax([self.noise, later.noise])), self.breaks + [restart] + later.breaks,
                          self.judged or later.judged, self.corrections + [1.0] + later.corrections,
                          self.applied and later.applied, self.turning + later.turning)

    def frame_verdicts(self, count: int) -> list[str]:
        """Per frame of a run of `count` frames: "ok", or "after break N" from the first frame
        after break N on (N = 1, 2, ...), so that a viewer or a report can colour the stretches."""
        verdict = ["ok"] * count
        for n, b in enumerate(self.breaks, start=1):
            verdict[b.after:] = [f"after break {n}"] * max(count - b.after, 0)
        return verdict

    def describe(self) -> str:
        """One sentence naming the breaks' frames and factors (empty without breaks)."""
        if not self.breaks:
            return ""
        steps = ", ".join(_said(b) for b in self.breaks[:4])
        more = f" and {len(self.breaks) - 4} more" if len(self.breaks) > 4 else ""
        text = (f"the map's scale against the depth prior's {steps}{more}, beyond the prior's own noise "
                f"({100 * self.noise:.0f} % a keyframe)")
        if self.applied:
            return text + ("; each stretch after a step was brought to the scale of the one before it (by the depth "
                           "prior), so the trajectory is one piece, but its joints are as good as the prior's scale")
        return text + ": the trajectory's stretches on either side are at different scales"


def _said(b: ScaleBreak) -> str:
    if b.kind == "lost":
        return f"is lost with the camera by frames {b.before}-{b.after} (tracked again from {b.after})"
    return f"{'creeps' if b.kind == 'drift' else 'steps'} x{b.factor:.2f} by frames {b.before}-{b.after}"


def keyframe_log_ratios(map_disp: np.ndarray, prior_disp: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """log(prior depth / map depth) per keyframe, the median over its valid pixels.

    map_disp, prior_disp: (K, h, w) inverse depths of the keyframes (the map's and the
    prior's); valid: (K, h, w) bool, pixels where the prior has depth. Returns (K,) float64,
    NaN for a keyframe without valid pixels."""
    ratio = np.log(np.asarray(map_disp, np.float64) / np.asarray(prior_disp, np.float64))
    ratio = np.where(np.asarray(valid, bool) & np.isfinite(ratio), ratio, np.nan)
    flat = ratio.reshape(len(ratio), -1)
    out = np.full(len(flat), np.nan)
    has = ~np.isnan(flat).all(axis=1)
    out[has] = np.nanmedian(flat[has], axis=1)
    return out


def log_noise(log_ratio: np.ndarray) -> float:
    """Standard deviation of the prior's per-keyframe scale noise, robustly from the
    differences of neighbouring keyframes (a step adds one outlier difference, not a bias)."""
    diffs = np.diff(log_ratio[np.isfinite(log_ratio)])
    if diffs.size == 0:
        return float("nan")
    return float(_MAD_TO_SIGMA * np.median(np.abs(diffs - np.median(diffs))) / np.sqrt(2.0))


def step_statistics(log_ratio: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """(steps, positions): for each k with ``window`` keyframes on each side, the median of
    log_ratio[k:k+window] minus that of log_ratio[k-window:k]. log_ratio: (K,) without NaN."""
    K = len(log_ratio)
    positions = np.arange(window, K - window + 1)
    if positions.size == 0:
        return np.zeros(0), positions
    windows = np.lib.stride_tricks.sliding_window_view(log_ratio, window)  # (K - window + 1, window)
    medians = np.median(windows, axis=1)
    return medians[positions] - medians[positions - window], positions


def split_point(log_ratio: np.ndarray, k: int, window: int) -> int:
    """Where exactly a step found at k lies: medians of windows move only once half a window
    has crossed the step, so several k around it score alike. The split of
    log_ratio[k-window : k+window] into two runs that fits them best (least absolute
    deviations from each run's median) names the first keyframe after the step."""
    lo = max(k - window, 0)
    span = log_ratio[lo: k + window]
    costs = [np.abs(span[:c] - np.median(span[:c])).sum() + np.abs(span[c:] - np.median(span[c:])).sum()
             for c in range(1, len(span))]
    return lo + 1 + int(np.argmin(costs))


def find_breaks(log_ratio: np.ndarray, frames: np.ndarray, cfg: ScaleWatchConfig, noise: float) -> list[ScaleBreak]:
    """Steps of log_ratio (K,) larger than ``cfg.min_step`` and ``cfg.z`` standard errors of
    `noise`, one per run of significant positions (at its largest step), greedily from the
    largest. frames: (K,) frame index of each keyframe."""
    steps, positions = step_statistics(log_ratio, cfg.window)
    if steps.size == 0:
        return []
    std_error = _MEDIAN_EFFICIENCY * max(noise, 1e-6) * np.sqrt(2.0 / cfg.window)
    z = np.abs(steps) / std_error
    significant = (z >= cfg.z) & (np.abs(steps) >= np.log(cfg.min_step))
    breaks = []
    taken = np.zeros(len(steps), dtype=bool)
    for n in np.argsort(-np.abs(steps)):
        if not significant[n] or taken[max(0, n - cfg.window + 1): n + cfg.window].any():
            continue
        taken[n] = True
        k = split_point(log_ratio, int(positions[n]), cfg.window)
        breaks.append(ScaleBreak(before=int(frames[k - 1]), after=int(frames[k]), factor=float(np.exp(-steps[n])),
                                 z=float(z[n])))
    return sorted(breaks, key=lambda b: b.after)


def stretch_factors(log_ratio: np.ndarray, frames: np.ndarray, breaks: list[ScaleBreak]) -> list[float]:
    """Per break, the factor that brings the stretch after it to the scale of the stretch
    before it: exp of the difference of the two stretches' median log ratios (the whole
    stretch is a better estimate than the windows around the step). log_ratio, frames: (K,)
    as in :func:`watch_scale`, without NaN."""
    edges = [0, *[int(np.searchsorted(frames, b.after)) for b in breaks], len(frames)]
    medians = [float(np.median(log_ratio[a:b])) for a, b in zip(edges[:-1], edges[1:])]
    return [float(np.exp(after - before)) for before, after in zip(medians[:-1], medians[1:])]


def smooth_log_ratio(log_ratio: np.ndarray, noise: float, drift: float, huber: float = 2.0,
                     iters: int = 5) -> np.ndarray:
    """The map's slow scale drift under the prior's noise: the most likely path x (K,) of a
    local level model (random walk plus noise; Durbin and Koopman's simplest state-space
    model), log_ratio_k = x_k + e_k with e ~ N(0, noise^2) and x_k = x_{k-1} + w_k with
    w ~ N(0, (drift * noise)^2). The smoothed path solves the tridiagonal system
    (W / noise^2 + D'D / (drift noise)^2) x = W log_ratio / noise^2 (D the first
    difference), reweighted ``iters`` times with Huber weights W beyond ``huber`` standard
    deviations, so that a keyframe whose prior is off by much more than the prior's usual
    noise does not pull its neighbours. drift: the random walk's step per keyframe as a
    share of the noise (small: a long window; large: follow the ratio closely).
    log_ratio: (K,) without NaN."""
    from scipy.linalg import solve_banded

    y = np.asarray(log_ratio, np.float64)
    K = y.size
    if K < 2 or not (np.isfinite(noise) and noise > 0 and drift > 0):
        return np.full(K, np.median(y)) if K else y
    smooth = 1.0 / drift**2  # D'D / q^2 in units of 1 / noise^2
    couple = np.full(K, 2 * smooth)
    couple[[0, -1]] = smooth
    x = np.full(K, np.median(y))
    for _ in range(iters):
        r = np.abs(y - x) / noise
        w = np.where(r > huber, huber / np.maximum(r, 1e-12), 1.0)
        bands = np.zeros((3, K))
        bands[0, 1:] = -smooth
        bands[1] = w + couple
        bands[2, :-1] = -smooth
        x = solve_banded((1, 1), bands, w * y)
    return x


def find_drifts(log_ratio: np.ndarray, frames: np.ndarray, cfg: ScaleWatchConfig, noise: float,
                steps: list[ScaleBreak]) -> list[ScaleBreak]:
    """Where the map's scale has crept away from the prior's without a step: within each
    stretch between the ``steps`` (smoothed on its own, so that a step is not smeared into
    a creep around it), the ratio smoothed by ``smooth_log_ratio`` is followed from the
    stretch's start, and a break is called between the keyframe before and the keyframe
    at which it has moved by ``cfg.min_drift``; it is followed on from there. log_ratio,
    frames: (K,) as in :func:`watch_scale`, without NaN. The breaks' ``z`` is the creep
    in the prior's noise per keyframe."""
    if cfg.drift_share <= 0 or cfg.min_drift <= 1:
        return []
    bounds = [0, *[int(np.searchsorted(frames, b.after)) for b in steps], len(frames)]
    limit = np.log(cfg.min_drift)
    found = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < 2:
            continue
        path = smooth_log_ratio(log_ratio[a:b], noise, cfg.drift_share)
        anchor = path[0]
        for k in range(1, b - a):
            moved = path[k] - anchor
            if abs(moved) >= limit:
                found.append(ScaleBreak(before=int(frames[a + k - 1]), after=int(frames[a + k]),
                                        factor=float(np.exp(-moved)), z=float(abs(moved) / max(noise, 1e-6)),
                                        kind="drift"))
                anchor = path[k]
    return found


def watch_scale(map_disp: np.ndarray, prior_disp: np.ndarray, valid: np.ndarray, frames,
                cfg: ScaleWatchConfig | None = None) -> ScaleWatch:
    """The scale check of a front-end map (module docstring).

    map_disp, prior_disp, valid: (K, h, w) as in :func:`keyframe_log_ratios`; frames: (K,)
    the keyframes' frame indices, increasing. A break's factor is how the map's depth
    changes against the prior's across it: x0.5 means everything after it is mapped at half
    the size of what came before."""
    cfg = cfg or ScaleWatchConfig()
    frames = np.asarray(frames, dtype=np.int64)
    log_ratio = keyframe_log_ratios(map_disp, prior_disp, valid)
    ok = np.isfinite(log_ratio)
    frames, log_ratio = frames[ok], log_ratio[ok]
    if log_ratio.size == 0:
        return ScaleWatch([], [], float("nan"), judged=False)
    noise = log_noise(log_ratio)
    # The ratio is reported as the map's size against the prior's: exp(-log(prior/map)).
    centred = np.exp(-(log_ratio - np.median(log_ratio)))
    watch = ScaleWatch(frames.tolist(), centred.tolist(), noise, judged=log_ratio.size >= cfg.min_keyframes)
    if watch.judged:
        steps = find_breaks(log_ratio, frames, cfg, noise)
        watch.breaks = sorted(steps + find_drifts(log_ratio, frames, cfg, noise, steps), key=lambda b: b.after)
        watch.corrections = stretch_factors(log_ratio, frames, watch.breaks)
    return watch


__all__ = ["ScaleBreak", "ScaleWatch", "ScaleWatchConfig", "find_breaks", "find_drifts", "keyframe_log_ratios",
           "log_noise", "smooth_log_ratio", "split_point", "step_statistics", "stretch_factors", "watch_scale"]
