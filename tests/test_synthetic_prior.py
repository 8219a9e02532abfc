"""The simulated monocular prior (recon.synthetic.prior) on the synthetic room (conftest:
small_room): its error and inconsistency, the scales it reports, and invalid pixels."""

from __future__ import annotations

import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.synthetic import simulate_prior, simulate_prior_with_truth


def test_prior_error_and_inconsistency(small_room):
    out = simulate_prior_with_truth(small_room.depth, seed=0)
    prior, gt = out.depth, small_room.depth
    assert prior.shape == gt.shape and prior.dtype == np.float32
    abs_rel = np.mean(np.abs(prior - gt) / gt)
    assert 0.15 <= abs_rel <= 0.25
    ratio = np.median((prior / gt).reshape(len(gt), -1), axis=1)
    assert ratio.std() > 0.08
    # The reported scales explain the per-frame distortion up to noise and edge blur.
    for i in range(len(gt)):
        explained = np.median(prior[i] / (gt[i] * out.scale_field(i)))
        assert explained == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(np.median(np.log(prior / gt), axis=(1, 2)),
                               np.log(out.global_scale) + np.median(out.log_grids, axis=(1, 2)), atol=0.12)
    np.testing.assert_array_equal(prior, simulate_prior(small_room.depth, seed=0))
    assert not np.array_equal(prior, simulate_prior(small_room.depth, seed=1))


def test_prior_keeps_invalid_pixels(small_room):
    depth = small_room.depth[:3].copy()
    depth[:, :20, :30] = 0.0
    prior = simulate_prior(depth, seed=2)
    assert (prior[:, :20, :30] == 0).all()
    assert (prior[depth > 0] > 0).all() and np.isfinite(prior).all()
    # Zeros do not leak through the blur: the border pixels keep a sensible scale.
    assert np.abs(np.log(prior[:, 20, :30] / depth[:, 20, :30])).max() < 1.5
    with pytest.raises(ReconInputError):
        simulate_prior(np.full((2, 4, 4), np.nan, dtype=np.float32))
    with pytest.raises(ReconInputError):
        simulate_prior(np.ones((4, 4), dtype=np.float32))
