"""The quality gate of an estimated trajectory (recon.poses.checks.quality): frames without image
evidence are dropped and named; too little evidence is a tracking-lost error; where tracking
began to fail before a loss."""

from __future__ import annotations

import numpy as np
import pytest

from recon.poses import TrackingLostError
from recon.poses.checks.quality import GateConfig, failing_since, gate_trajectory, runs
from recon.poses.result import PoseResult


def _result(status, inlier=None, method="frontend"):
    n = len(status)
    diagnostics = {"method": method, "frame_status": status}
    if inlier is not None:
        diagnostics["frame_inlier"] = inlier
    return PoseResult(np.tile(np.eye(4), (n, 1, 1)), (100.0, 100.0, 50.0, 50.0), np.arange(n), 0.0, diagnostics)


def test_quality_gate_drops_frames_without_evidence_and_names_them():
    status = ["keyframe", "tracked", "interpolated", "interpolated", "relocalised", "recovered", "tracked", "tracked"]
    inlier = [np.nan, 0.9, np.nan, np.nan, 0.6, np.nan, 0.1, 0.8]
    gate = gate_trajectory(_result(status, inlier))
    assert gate.keep.tolist() == [True, True, False, False, True, True, False, True]
    summary = gate.summary([10 * i for i in range(8)])  # video frame numbers
    assert summary["dropped"] == 3 and summary["dropped_ranges"] == [[20, 30], [60, 60]]
    assert "interpolated" in summary["dropped_frames"][0]["reason"]
    assert "10%" in summary["dropped_frames"][2]["reason"]


def test_quality_gate_refuses_a_trajectory_with_too_little_evidence():
    status = ["keyframe", "tracked"] + ["interpolated"] * 6
    with pytest.raises(TrackingLostError, match=r"sfm: only 2 of 8 frames .* frames 2-7"):
        gate_trajectory(_result(status, method="sfm"))
    with pytest.raises(TrackingLostError, match=r"not tracked: frames 54-64$"):  # named as the video numbers them
        gate_trajectory(_result(status, method="sfm"), frame_numbers=range(50, 66, 2))
    assert gate_trajectory(_result(status), GateConfig(min_kept=0.2, min_frames=2)).keep.sum() == 2
    assert runs([1, 2, 3, 7, 9, 10]) == [(1, 3), (7, 7), (9, 10)]


def test_failing_since_dates_a_loss_back_to_the_last_good_run():
    good, weak = 0.95, 0.7
    # The synthetic walk-through's corner, frames 170-185 after the global BA (its loss at 186).
    corner = [0.96, 0.99, 0.81, 0.97, 0.98, 0.96, 0.76, 0.88, 0.65, 0.74, 0.86, 0.95, 0.72, 0.98, 0.83, 0.74]
    assert failing_since(np.array(corner), 0.85, 11) == 6  # frame 176: the last three good are 173-175
    assert failing_since(np.array([good] * 20), 0.85, 11) == 20  # a clean loss (a cut): nothing before it
    assert failing_since(np.array([good] * 10 + [weak] * 10), 0.85, 11) == 10
    assert failing_since(np.array([good] * 10 + [weak] * 10), 0.85, 4) == 16  # no further back than lookback
    # Two good frames in a row are not yet a sound map again; NaN (no evidence) is failing.
    assert failing_since(np.array([good] * 5 + [weak, good, good, weak, np.nan]), 0.85, 11) == 5
    assert failing_since(np.array([weak, weak]), 0.85, 11) == 0
