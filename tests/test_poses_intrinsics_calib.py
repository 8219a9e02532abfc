"""The focal search's one-dimensional minimisation (recon.poses.intrinsics.calib): the sweep
over fields of view, then Brent's method on log f. The scores here are cheap functions of f
with a known minimum; the search on real flows is tested with the front end
(tests/test_poses_frontend_streaming.py)."""

from __future__ import annotations

import math

import pytest

from recon.poses.intrinsics.calib import brent_minimise, candidate_focals, search_focal


def _score(true_focal: float, skew: float = 0.3):
    """A smooth score of f, lowest at true_focal, steeper on one side (as a BA cost is)."""
    def score(f: float) -> float:
        x = math.log(f / true_focal)
        return 1.0 + x * x + skew * x**3
    return score


@pytest.mark.parametrize("true_focal", [320.0, 525.0, 560.0, 700.0])
def test_the_search_finds_a_minimum_between_the_candidates_in_few_evaluations(true_focal):
    """Within the tolerance of the true minimum, with fewer evaluations than golden-section
    search needs for the same bracket (7 for the sweep, then about 10)."""
    candidates = candidate_focals(640, 480)
    result = search_focal(_score(true_focal), candidates, tol=0.01)
    assert result.bracketed
    assert abs(math.log(result.focal / true_focal)) <= 0.01
    assert len(result.evaluations) <= len(candidates) + 5
    assert [f for f, _ in result.evaluations[: len(candidates)]] == sorted(candidates)


def test_a_minimum_beyond_the_candidates_is_not_bracketed():
    """The best candidate at an end: the search goes on in the last interval, towards the end,
    and says the minimum was not bracketed."""
    candidates = candidate_focals(640, 480)
    result = search_focal(_score(3000.0), candidates, tol=0.01)
    assert not result.bracketed
    assert result.focal == pytest.approx(max(candidates), rel=0.01)
    assert result.focal <= max(candidates)


def test_brent_steps_to_a_parabola_s_minimum_at_once():
    """On a parabola the first parabolic step lands on the minimum: one evaluation there and
    the bracket closes around it."""
    calls = []

    def parabola(x: float) -> float:
        calls.append(x)
        return (x - 0.3) ** 2

    x, fx = brent_minimise(parabola, -1.0, 1.0, (0.0, parabola(0.0)), [(-1.0, parabola(-1.0)), (1.0, parabola(1.0))],
                           tol=1e-4, max_evals=20)
    assert x == pytest.approx(0.3, abs=1e-4) and fx <= 1e-8
    assert calls[3] == pytest.approx(0.3, abs=1e-12)  # the first step, after the three given points
    assert len(calls) <= 3 + 4


def test_brent_stops_at_max_evals():
    calls = []

    def wiggly(x: float) -> float:
        calls.append(x)
        return abs(x - 0.123) + 0.01 * math.sin(200 * x)

    brent_minimise(wiggly, 0.0, 1.0, (0.5, wiggly(0.5)), [(0.0, wiggly(0.0)), (1.0, wiggly(1.0))], tol=1e-9,
                   max_evals=6)
    assert len(calls) == 3 + 6
