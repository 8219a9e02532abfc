"""TensorFlow.js graph models read into torch (recon.priors.tfjs): damaged files give one-line
errors naming the culprit, and the module is built from the graph's structure.
Needs ../shared/weights/fastdepth (skipped when absent)."""

from __future__ import annotations

import json

import pytest

from recon.errors import ReconInputError
from recon.priors import FastDepthPrior
from recon.priors.tfjs import compile_graph
from recon.priors.tfjs_format import load_tfjs_graph

from helpers import copy_fastdepth_weights


@pytest.mark.parametrize("damage", ["truncated", "bad_json", "wrong_shape", "extra_bytes"])
def test_corrupt_weights_one_line_error(fastdepth_weights, tmp_path, damage):
    model = copy_fastdepth_weights(fastdepth_weights, tmp_path / "fastdepth")
    shard = model.parent / "group1-shard1of1.bin"
    if damage == "truncated":
        shard.write_bytes(shard.read_bytes()[:-1000])
        culprit = shard
    elif damage == "extra_bytes":
        shard.write_bytes(shard.read_bytes() + b"\0" * 8)
        culprit = shard
    elif damage == "bad_json":
        model.write_text(model.read_text()[:-10])
        culprit = model
    else:
        spec = json.loads(model.read_text())
        weights = spec["weightsManifest"][0]["weights"]
        entry = next(w for w in weights if w["name"].endswith("conv2d_1/Conv2D/ReadVariableOp"))
        entry["shape"] = [1, 1, 56, 16]  # same size, transposed: only a shape check can tell
        model.write_text(json.dumps(spec))
        culprit = model
    with pytest.raises(ReconInputError) as info:
        FastDepthPrior(weights=tmp_path, progress=False)
    message = str(info.value)
    assert "\n" not in message and str(culprit) in message


def test_graph_walk_is_structural(fastdepth_weights):
    """The module is built from the graph: 38 fused convs, 5 upsamplings, 3 skip additions."""
    net = compile_graph(load_tfjs_graph(fastdepth_weights / "model.json"))
    kinds = [s.kind for s in net.steps]
    assert kinds.count("conv") == 38 and kinds.count("resize") == 5 and kinds.count("add") == 3
    assert all(layer.bias is not None for layer in net.layers)
    assert net.multiple == 32
