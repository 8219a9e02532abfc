"""Local Hugging Face depth models as priors (recon.priors.hf): tiny DPT (affine disparity) and
Depth Anything (metric) models saved on the spot, a missing folder, and a missing
transformers install."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.priors import make_prior

from helpers import prior_frames

needs_transformers = pytest.mark.skipif(importlib.util.find_spec("transformers") is None,
                                        reason="transformers (optional extra 'hf') not installed")


@needs_transformers
def test_hf_tiny_dpt_is_affine_disparity(tmp_path):
    import transformers as T

    config = T.DPTConfig(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, intermediate_size=32,
                         image_size=32, patch_size=8, backbone_out_indices=[0, 1, 2, 3],
                         neck_hidden_sizes=[8, 8, 8, 8], fusion_hidden_size=8)
    T.DPTForDepthEstimation(config).save_pretrained(tmp_path)
    T.DPTImageProcessor(size={"height": 32, "width": 32}).save_pretrained(tmp_path)
    prior = make_prior("hf", model=tmp_path, batch_size=2, progress=False)
    out = prior(prior_frames(3, 40, 56))
    assert out.kind == "affine_disparity" and out.info["model_type"] == "dpt"
    assert out.depth.shape == (3, 40, 56) and out.depth.dtype == np.float32 and np.isfinite(out.depth).all()


@needs_transformers
def test_hf_tiny_depth_anything_metric(tmp_path):
    import transformers as T

    backbone = T.Dinov2Config(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=2,
                              image_size=28, patch_size=14, out_indices=[1, 2, 3, 4], reshape_hidden_states=False)
    config = T.DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=16, neck_hidden_sizes=[8, 8, 8, 8],
                                   fusion_hidden_size=8, head_hidden_size=8, depth_estimation_type="metric",
                                   max_depth=10)
    T.DepthAnythingForDepthEstimation(config).save_pretrained(tmp_path)
    T.DPTImageProcessor(size={"height": 28, "width": 28}).save_pretrained(tmp_path)
    out = make_prior("hf", model=tmp_path, progress=False)(prior_frames(2, 30, 40))
    assert out.kind == "metric" and out.depth.shape == (2, 30, 40)


@needs_transformers
def test_hf_missing_model_folder(tmp_path):
    with pytest.raises(ReconInputError, match="never downloaded"):
        make_prior("hf", model=tmp_path / "nothing", progress=False)


def test_hf_without_transformers_says_how_to_install(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "transformers", None)  # makes `import transformers` fail
    with pytest.raises(ReconInputError, match="recon\\[hf\\]"):
        make_prior("hf", model=tmp_path, progress=False)
