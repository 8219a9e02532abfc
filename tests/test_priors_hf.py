"""Local Hugging Face depth models as priors (recon.priors.hf): tiny DPT (affine disparity) and
Depth Anything (metric) models saved on the spot, a missing folder, and a missing
transformers install."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.priors import make_prior

from helpers import one_line, prior_frames, save_tiny_depth_anything, save_tiny_dpt

needs_transformers = pytest.mark.skipif(importlib.util.find_spec("transformers") is None,
                                        reason="transformers (optional extra 'hf') not installed")


@needs_transformers
def test_hf_tiny_dpt_is_affine_disparity(tmp_path):
    prior = make_prior("hf", model=save_tiny_dpt(tmp_path), batch_size=2, progress=False)
    out = prior(prior_frames(3, 40, 56))
    assert out.kind == "affine_disparity" and out.info["model_type"] == "dpt"
    assert out.depth.shape == (3, 40, 56) and out.depth.dtype == np.float32 and np.isfinite(out.depth).all()


@needs_transformers
def test_hf_tiny_depth_anything_metric(tmp_path):
    out = make_prior("hf", model=save_tiny_depth_anything(tmp_path), progress=False)(prior_frames(2, 30, 40))
    assert out.kind == "metric" and out.depth.shape == (2, 30, 40)


@needs_transformers
def test_hf_missing_model_folder(tmp_path):
    with pytest.raises(ReconInputError, match="never downloaded"):
        make_prior("hf", model=tmp_path / "nothing", progress=False)


def test_hf_without_transformers_says_how_to_install(tmp_path, monkeypatch):
    import sys

    (tmp_path / "config.json").write_text('{"model_type": "dpt"}')  # a model folder, as far as can be seen
    monkeypatch.setitem(sys.modules, "transformers", None)  # makes `import transformers` fail
    with pytest.raises(ReconInputError, match="recon\\[hf\\]"):
        make_prior("hf", model=tmp_path, progress=False)


def test_hf_model_path_that_is_not_a_model_folder(tmp_path):
    (tmp_path / "model.safetensors").write_bytes(b"")
    for path, words in [(tmp_path / "nothing", ["no such", "never downloaded"]),
                        (tmp_path / "model.safetensors", ["not a folder", "config.json"]),
                        (tmp_path, ["no config.json", "never downloaded"])]:
        with pytest.raises(ReconInputError) as info:
            make_prior("hf", model=path, progress=False)
        assert all(word in one_line(info) for word in words), (words, str(info.value))


def _spoil(folder, how: str) -> None:
    import json

    config = folder / "config.json"
    if how == "bad-json":
        config.write_text("{not json")
    elif how == "not-a-depth-model":
        config.write_text(json.dumps({"model_type": "bert"}))
    elif how == "no-weights":
        for path in folder.glob("*.safetensors"):
            path.unlink()
    elif how == "wrong-sizes":
        values = json.loads(config.read_text())
        config.write_text(json.dumps({**values, "hidden_size": 32, "intermediate_size": 64}))
    elif how == "truncated-weights":
        for path in folder.glob("*.safetensors"):
            path.write_bytes(path.read_bytes()[:100])


@needs_transformers
@pytest.mark.parametrize("how", ["bad-json", "not-a-depth-model", "no-weights", "wrong-sizes", "truncated-weights"])
def test_hf_model_transformers_cannot_load_is_one_line(tmp_path, capfd, how):
    """Whatever transformers raises on a bad folder is one line naming it; transformers' own load
    report (a table on stderr) is not shown."""
    _spoil(save_tiny_dpt(tmp_path), how)
    capfd.readouterr()  # saving it shows a bar
    with pytest.raises(ReconInputError) as info:
        make_prior("hf", model=tmp_path, progress=False)
    assert one_line(info).startswith(f"{tmp_path}: cannot load the depth model (")
    assert "report" not in str(info.value)
    assert capfd.readouterr().err == ""
