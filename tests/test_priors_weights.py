"""Where model weights come from (recon.priors.weights): the lookup order (explicit path,
$RECON_WEIGHTS, the packaged model) and one-line errors listing every place looked in.
The TF.js forms of the lookup need ../shared/weights/fastdepth (skipped when absent); the
packaged forms do not."""

from __future__ import annotations

import shutil

import pytest

from recon.errors import ReconInputError
from recon.priors import FastDepthPrior, find_weights
from recon.priors.weights import ENV_VAR, packaged_weights

from helpers import copy_fastdepth_weights

PACKAGED = packaged_weights("fastdepth")


def test_lookup_order(fastdepth_weights, tmp_path, monkeypatch):
    env_model = copy_fastdepth_weights(fastdepth_weights, tmp_path / "env" / "fastdepth")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "env"))
    assert find_weights("fastdepth", "model.json") == env_model
    # An explicit path wins, in any of its three forms.
    explicit = copy_fastdepth_weights(fastdepth_weights, tmp_path / "explicit" / "fastdepth")
    for given in (explicit, explicit.parent, explicit.parent.parent):
        assert find_weights("fastdepth", "model.json", given) == explicit
    monkeypatch.delenv(ENV_VAR)
    assert find_weights("fastdepth", "model.json") == PACKAGED


def test_packaged_file_is_the_default_and_can_be_given(tmp_path, monkeypatch):
    """Without --weights and $RECON_WEIGHTS the packaged file is used, whatever lies in
    ../shared or ~/.cache; a copy of it works as --weights (the file or its folder) and in
    $RECON_WEIGHTS."""
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert find_weights("fastdepth", "model.json") == PACKAGED
    copy = tmp_path / "mine" / "fastdepth.npz"
    copy.parent.mkdir()
    shutil.copy(PACKAGED, copy)
    assert find_weights("fastdepth", "model.json", copy) == copy
    assert find_weights("fastdepth", "model.json", copy.parent) == copy
    monkeypatch.setenv(ENV_VAR, str(copy.parent))
    assert find_weights("fastdepth", "model.json") == copy
    # $RECON_WEIGHTS that holds nothing falls through to the packaged file.
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "empty"))
    assert find_weights("fastdepth", "model.json") == PACKAGED


def test_missing_weights_lists_places(tmp_path):
    with pytest.raises(ReconInputError) as info:
        FastDepthPrior(weights=tmp_path / "nowhere", progress=False)
    message = str(info.value)
    assert "\n" not in message and "nowhere" in message


def test_missing_everywhere_lists_all_places(tmp_path, monkeypatch):
    """Only a broken install lacks the packaged file; the error names it and $RECON_WEIGHTS."""
    import recon.priors.weights as weights

    monkeypatch.setenv(ENV_VAR, str(tmp_path / "env"))
    monkeypatch.setattr(weights, "PACKAGED_MODELS", tmp_path / "package")
    with pytest.raises(ReconInputError) as info:
        find_weights("fastdepth", "model.json")
    message = str(info.value)
    assert "\n" not in message
    assert str(tmp_path / "env" / "fastdepth" / "model.json") in message
    assert str(tmp_path / "package" / "fastdepth.npz") in message
    assert "shared" not in message and ".cache" not in message
