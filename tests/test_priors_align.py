"""Affine-invariant disparity turned into metric depth (recon.priors.align): a robust per-frame
scale and shift in disparity space against a sparse, partly wrong metric reference."""

from __future__ import annotations

import numpy as np
import pytest

from recon.priors import align_affine_disparity, fit_affine_disparity

from helpers import PRIOR_H as H
from helpers import PRIOR_W as W


def test_affine_fit_recovers_scale_shift_despite_outliers():
    rng = np.random.default_rng(2)
    true_depth = rng.uniform(0.5, 5.0, (2, H, W)).astype(np.float32)
    scale, shift = np.array([0.4, 2.5]), np.array([-0.1, 0.3])
    # Relative disparity d with 1/z = scale * d + shift.
    disparity = ((1.0 / true_depth - shift[:, None, None]) / scale[:, None, None]).astype(np.float32)
    reference = true_depth.copy()
    reference[rng.random(reference.shape) < 0.15] *= 3.0  # 15% wrong reference points
    reference[rng.random(reference.shape) < 0.5] = 0.0  # sparse
    for k in range(2):
        m = reference[k] > 0
        s, t = fit_affine_disparity(disparity[k][m], 1.0 / reference[k][m])
        assert s == pytest.approx(scale[k], rel=1e-4) and t == pytest.approx(shift[k], abs=1e-4)
    aligned = align_affine_disparity(disparity, reference)
    np.testing.assert_allclose(aligned, true_depth, rtol=1e-3)
    with pytest.raises(ValueError, match="frame 0"):
        align_affine_disparity(disparity, np.zeros_like(reference))
