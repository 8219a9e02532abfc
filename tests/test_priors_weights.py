"""Where model weights come from (recon.priors.weights): the lookup order (explicit path,
$RECON_WEIGHTS, ../shared, cache) and one-line errors listing every place looked in.
The lookup order needs ../shared/weights/fastdepth (skipped when absent)."""

from __future__ import annotations

import pytest

from recon.errors import ReconInputError
from recon.priors import FastDepthPrior, find_weights
from recon.priors.weights import ENV_VAR

from helpers import FASTDEPTH_WEIGHTS, copy_fastdepth_weights


def test_lookup_order(fastdepth_weights, tmp_path, monkeypatch):
    env_model = copy_fastdepth_weights(fastdepth_weights, tmp_path / "env" / "fastdepth")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "env"))
    assert find_weights("fastdepth", "model.json") == env_model
    # An explicit path wins, in any of its three forms.
    explicit = copy_fastdepth_weights(fastdepth_weights, tmp_path / "explicit" / "fastdepth")
    for given in (explicit, explicit.parent, explicit.parent.parent):
        assert find_weights("fastdepth", "model.json", given) == explicit
    monkeypatch.delenv(ENV_VAR)
    assert find_weights("fastdepth", "model.json") == FASTDEPTH_WEIGHTS / "model.json"


def test_missing_weights_lists_places(tmp_path):
    with pytest.raises(ReconInputError) as info:
        FastDepthPrior(weights=tmp_path / "nowhere", progress=False)
    message = str(info.value)
    assert "\n" not in message and "nowhere" in message


def test_missing_everywhere_lists_all_places(tmp_path, monkeypatch):
    import recon.priors.weights as weights

    monkeypatch.setenv(ENV_VAR, str(tmp_path / "env"))
    monkeypatch.setattr(weights, "SHARED_WEIGHTS", tmp_path / "shared")
    monkeypatch.setattr(weights, "CACHE_WEIGHTS", tmp_path / "cache")
    with pytest.raises(ReconInputError) as info:
        find_weights("fastdepth", "model.json")
    message = str(info.value)
    assert "\n" not in message
    for place in ("env", "shared", "cache"):
        assert str(tmp_path / place / "fastdepth" / "model.json") in message
