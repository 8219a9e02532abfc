"""A streamed run's second opinion (recon.drivers.stream_track): asked of SfM on the
depth frames where the front end doubts its trajectory, with --pose-method auto and not under
--on-break keep; the verdict lands in the result's diagnostics for report.json."""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import numpy as np
import pytest

from recon.drivers import stream_track
from recon.poses.result import PoseResult

# The module (recon.poses exports a function of the same name).
so = importlib.import_module("recon.poses.second_opinion")


def _poser(pose_method: str, stop_untrusted: bool):
    poser = stream_track._Poser.__new__(stream_track._Poser)
    poser.config = SimpleNamespace(pose_method=pose_method)
    poser.frontend_config = SimpleNamespace(stop_untrusted=stop_untrusted)
    poser.intrinsics = None
    # Tracked under --start: position p is the video's frame 100 + p.
    poser.frame_number = {p: 100 + p for p in range(12)}
    # The store keeps the colour of the depth frames 0, 3, 6, 9 only.
    poser.store = SimpleNamespace(has=lambda p, kind: kind == "rgb" and p % 3 == 0, get=lambda p, kind: None)
    return poser


def _result(doubt: bool) -> PoseResult:
    diagnostics = {"motion_checks": {"short_flow": [[4, 9]] if doubt else []}}
    return PoseResult(np.tile(np.eye(4), (12, 1, 1)), (100.0, 100.0, 50.0, 40.0), np.arange(0, 12, 3), 0.0,
                      diagnostics)


@pytest.mark.parametrize("pose_method, stop_untrusted, doubt, asked", [
    ("auto", True, True, True), ("auto", True, False, False), ("frontend", True, True, False),
    ("auto", False, True, False)])
def test_sfm_is_asked_where_the_front_end_doubts(monkeypatch, pose_method, stop_untrusted, doubt, asked):
    calls = []

    def opinion(poses, views, frame, intrinsics, said, stretch):
        calls.append((list(views), said))
        return so.SecondOpinion(said, 4, 0.05, "disagree", "front end", "SfM posed some frames only")

    monkeypatch.setattr(so, "on_views", opinion)
    result = _result(doubt)
    _poser(pose_method, stop_untrusted)._second_opinion(result)
    assert bool(calls) == asked
    assert ("second_opinion" in result.diagnostics) == asked
    if asked:
        assert calls[0][0] == [0, 3, 6, 9] and "frames 104-109" in calls[0][1]
        assert result.diagnostics["second_opinion"]["verdict"] == "disagree"
