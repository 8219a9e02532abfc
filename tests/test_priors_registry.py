"""Depth priors by name (recon.priors.registry) and the output every prior must give
(recon.priors.base.PriorOutput)."""

from __future__ import annotations

import numpy as np
import pytest

from recon.priors import PriorOutput, available_priors, make_prior


def test_registry_and_output_checks():
    assert set(available_priors()) >= {"fastdepth", "folder", "sensor", "hf"}
    with pytest.raises(ValueError, match="unknown depth prior"):
        make_prior("nope")
    with pytest.raises(ValueError):
        PriorOutput(depth=np.zeros((1, 2, 2), np.float32), kind="relative")
    with pytest.raises(ValueError):
        PriorOutput(depth=np.zeros((2, 2), np.float32), kind="metric")
