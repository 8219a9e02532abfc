"""Depth metrics against values computed by hand on tiny arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from recon.eval.depth import depth_metrics


def test_single_frame_hand_computed():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # the 0 is invalid ground truth
    pred = np.array([[1.5, 2.0], [3.0, 9.0]])
    m = depth_metrics(pred, gt)
    # Valid pixels: (1.5 vs 1), (2 vs 2), (3 vs 4).
    assert m["abs_diff"] == pytest.approx((0.5 + 0 + 1) / 3)
    assert m["abs_rel"] == pytest.approx((0.5 / 1 + 0 + 1 / 4) / 3)
    assert m["sq_rel"] == pytest.approx((0.25 / 1 + 0 + 1 / 4) / 3)
    assert m["rmse"] == pytest.approx(math.sqrt((0.25 + 0 + 1) / 3))
    assert m["log_rmse"] == pytest.approx(math.sqrt((math.log(1.5) ** 2 + math.log(0.75) ** 2) / 3))
    # Ratios max(p/g, g/p): 1.5, 1, 4/3 -> below 1.25: one of three; below 1.5625: all.
    assert m["delta1"] == pytest.approx(1 / 3)
    assert m["delta2"] == pytest.approx(1.0)
    assert m["coverage"] == pytest.approx(1.0)
    assert m["frames"] == 1


def test_missing_predictions_lower_coverage_and_range_limits_pixels():
    gt = np.array([[1.0, 2.0, 20.0]])
    pred = np.array([[1.0, 0.0, 1.0]])  # second pixel not predicted; third out of range
    m = depth_metrics(pred, gt, max_depth=10.0)
    assert m["abs_rel"] == pytest.approx(0.0)
    assert m["coverage"] == pytest.approx(0.5)


def test_frames_are_averaged_not_pooled():
    gt = np.ones((2, 1, 4))
    pred = np.ones((2, 1, 4))
    pred[1] = 2.0
    pred[0, 0, 1:] = np.nan  # frame 0 keeps a single valid pixel
    m = depth_metrics(pred, gt)
    # Per frame: abs rel 0 and 1, mean 0.5 (pooling the pixels would give 0.8).
    assert m["abs_rel"] == pytest.approx(0.5)


def test_median_scaling():
    gt = np.array([[[1.0, 2.0, 3.0]], [[2.0, 4.0, 6.0]]])
    pred = gt * np.array([0.5, 3.0])[:, None, None]
    per_frame = depth_metrics(pred, gt, align="median_frame")
    assert per_frame["abs_rel"] == pytest.approx(0.0, abs=1e-12)
    per_sequence = depth_metrics(pred, gt, align="median_sequence")
    # One scale for both frames: median(gt) / median(pred) = 2.5 / 3.75; the frames'
    # scaled abs rel are |0.5 * s - 1| and |3 * s - 1|.
    s = 2.5 / 3.75
    assert per_sequence["scale"] == pytest.approx(s)
    assert per_sequence["abs_rel"] == pytest.approx((abs(0.5 * s - 1) + abs(3 * s - 1)) / 2)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shape"):
        depth_metrics(np.ones((2, 2)), np.ones((2, 3)))
