"""The quality gate of an estimated trajectory: which frames' poses rest on their own image
evidence, which are guesses, and whether enough is left to reconstruct from.

Every estimator reports a per-frame state (``result.FRAME_STATES`` in
``diagnostics["frame_status"]``) and, where it has one, per-frame evidence
(``diagnostics["frame_inlier"]``: the share of the frame's flow or features its pose
explains). A frame is kept when its state is trusted and its evidence (when given) reaches
``min_inlier``; the others are named, so that the pipeline drops them from depth
adjustment and fusion with a warning instead of fusing depth at a guessed pose. Too few
frames left is an error that says which frames could not be tracked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon.poses.result import TRUSTED_STATES, PoseResult, TrackingLostError, frame_spans, numbered


@dataclass
class GateConfig:
    """min_inlier: least evidence a trusted frame needs (NaN evidence passes);
    min_kept: least share of the frames that must pass, else the trajectory is refused;
    min_frames: ... and least count."""

    min_inlier: float = 0.25
    min_kept: float = 0.5
    min_frames: int = 3


@dataclass
class GateResult:
    """keep: (N,) bool, frames whose pose is trusted; dropped: {frame: why} for the others."""

    keep: np.ndarray
    dropped: dict[int, str] = field(default_factory=dict)

    def summary(self, frame_names=None) -> dict:
        """What report.json says: counts, the dropped frames and the runs they form."""
        idx = sorted(self.dropped)
        name = (lambda i: int(i)) if frame_names is None else (lambda i: frame_names[i])
        return {"frames": int(len(self.keep)), "kept": int(self.keep.sum()), "dropped": len(idx),
                "dropped_frames": [{"frame": name(i), "reason": self.dropped[i]} for i in idx],
                "dropped_ranges": [[name(a), name(b)] for a, b in runs(idx)]}


def runs(indices) -> list[tuple[int, int]]:
    """Consecutive runs [(first, last), ...] of sorted integer indices."""
    out: list[tuple[int, int]] = []
    for i in indices:
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out


# Frames in a row with good evidence that say tracking was still sound there.
GOOD_RUN = 3


def failing_since(evidence: np.ndarray, share: float, lookback: int, good_run: int = GOOD_RUN) -> int:
    """Where tracking began to fail before the camera was lost: the first of the last
    `lookback` frames after which no `good_run` frames in a row have evidence of at least
    `share` (evidence: (n,) per frame up to the first lost one, NaN counted as failing).
    n when the last `good_run` frames have it (a clean loss, as at a cut); n - lookback at
    most.

    Why: a front end is lost only after its map has gone wrong, and the frames just before
    pass every check one by one (the synthetic walk-through's corner: frames 176-185, 0.2-1.6
    m off); what gives them away is that their poses, once the map is solved as a whole,
    keep explaining less of their flow than the frames of a sound map do."""
    n = len(evidence)
    good = np.asarray(evidence, dtype=np.float64) >= share
    for end in range(n, max(n - lookback, 0) - 1, -1):
        if end >= good_run and good[end - good_run:end].all():
            return end
    return max(n - lookback, 0)


def gate_trajectory(result: PoseResult, config: GateConfig | None = None, frame_numbers=None) -> GateResult:
    """Per-frame verdict on an estimate; raises TrackingLostError when too little is left
    (frames named by ``frame_numbers``, ``result.numbered``)."""
    config = config or GateConfig()
    n = len(result.poses)
    status = list(result.diagnostics.get("frame_status") or ["tracked"] * n)
    evidence = np.asarray(result.diagnostics.get("frame_inlier", [np.nan] * n), dtype=np.float64)
    if len(status) != n or len(evidence) != n:
        raise ValueError(f"frame_status / frame_inlier must have one entry per frame ({n})")
    finite = np.isfinite(result.poses).all(axis=(1, 2))
    keep = np.zeros(n, dtype=bool)
    dropped: dict[int, str] = {}
    for i in range(n):
        if not finite[i]:
            dropped[i] = "no pose"
        elif status[i] not in TRUSTED_STATES:
            dropped[i] = f"{status[i]}: no image evidence for its pose"
        elif np.isfinite(evidence[i]) and evidence[i] < config.min_inlier:
            dropped[i] = f"pose explains only {evidence[i]:.0%} of its evidence (< {config.min_inlier:.0%})"
        else:
            keep[i] = True
    kept = int(keep.sum())
    if kept < max(config.min_frames, config.min_kept * n):
        spans = frame_spans(runs(sorted(dropped))[:5], numbered(frame_numbers))
        method = result.diagnostics.get("method", "the estimator")
        raise TrackingLostError(
            f"{method}: only {kept} of {n} frames have a pose backed by the images (need {config.min_kept:.0%}); "
            f"not tracked: frames {spans}", frame=min(dropped) if dropped else None)
    return GateResult(keep, dropped)
