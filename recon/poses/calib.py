"""Focal-length self-calibration for videos without intrinsics (phone clips).

This module owns the search: the principal point is taken at the image centre and
fx = fy = f; for each candidate f the first keyframes are bundle-adjusted (poses and
depths, the same dense BA as tracking, on the flows already computed, which do not depend
on f) and the final robust reprojection cost is the score. A coarse sweep over a log grid
of field-of-view candidates brackets the minimum, then golden-section search on log f
refines it. Rotation is what makes f observable: the flow of a rotating camera bends with
x^2 / f, which no choice of depths can imitate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass
class FocalSearch:
    """Result of :func:`search_focal`: the focal (pixels of the input frames), every
    (focal, score) evaluated, in order, and whether the minimum was bracketed."""

    focal: float
    evaluations: list[tuple[float, float]] = field(default_factory=list)
    bracketed: bool = True


def candidate_focals(width: int, height: int, fovs_deg=(100.0, 85.0, 72.0, 62.0, 53.0, 45.0, 38.0)) -> list[float]:
    """Focal lengths (pixels) giving the horizontal fields of view `fovs_deg` for a width-`width` image.

    The default spans ultra-wide (100 deg) to mild tele (38 deg), roughly geometric in f,
    which covers phone main and wide cameras and most action cameras after undistortion.
    """
    return [0.5 * width / math.tan(math.radians(fov) / 2.0) for fov in fovs_deg]


def search_focal(
    score: Callable[[float], float], candidates: list[float], tol: float = 0.003, max_evals: int = 12
) -> FocalSearch:
    """Minimise score(f) over f: sweep the candidates, then golden-section on log f between
    the neighbours of the best one until the bracket is within `tol` (relative) or
    `max_evals` further evaluations. A minimum at the end of the sweep is reported as not
    bracketed (the true focal may lie outside the candidates)."""
    cands = sorted(candidates)
    evals: list[tuple[float, float]] = []

    def f_eval(f: float) -> float:
        s = float(score(f))
        if not np.isfinite(s):
            s = float("inf")
        evals.append((f, s))
        return s

    scores = [f_eval(f) for f in cands]
    best = int(np.argmin(scores))
    bracketed = 0 < best < len(cands) - 1
    lo = math.log(cands[max(best - 1, 0)])
    hi = math.log(cands[min(best + 1, len(cands) - 1)])
    # Golden-section on log f inside [lo, hi].
    a, b = lo, hi
    c = b - GOLDEN * (b - a)
    d = a + GOLDEN * (b - a)
    fc, fd = f_eval(math.exp(c)), f_eval(math.exp(d))
    n = 2
    while (b - a) > tol and n < max_evals:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - GOLDEN * (b - a)
            fc = f_eval(math.exp(c))
        else:
            a, c, fc = c, d, fd
            d = a + GOLDEN * (b - a)
            fd = f_eval(math.exp(d))
        n += 1
    f_best, s_best = min(evals, key=lambda e: e[1])
    return FocalSearch(focal=float(f_best), evaluations=evals, bracketed=bracketed)
