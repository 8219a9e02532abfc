"""The model file that ships with recon (recon.priors.packaged) and scripts/convert_fastdepth.py:
the packaged FastDepth builds the RGB -> depth network with float32 weights, its bytes are
reproducible, bad files give one-line errors; against ../shared/weights/fastdepth, the packaged
network is the TF.js one (same weights, same depth) and a fresh conversion gives the committed
files (those two skip when ../shared is absent)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from recon.errors import ReconInputError
from recon.priors import FastDepthPrior, load_fastdepth
from recon.priors.packaged import HEADER_KEY, pack_graph, read_graph, read_parts, write_npz
from recon.priors.weights import packaged_weights

from helpers import REPO

PACKAGED = packaged_weights("fastdepth")


def test_packaged_fastdepth_is_the_default_and_builds():
    assert PACKAGED.is_file() and (PACKAGED.parent / "fastdepth.LICENSE").is_file()
    graph = read_graph(PACKAGED)
    floats = [v for v in graph.constants.values() if v.dtype.kind == "f"]
    # Stored as float16, given to the network as float32 (as the TF.js reader dequantises).
    assert floats and all(v.dtype == np.float32 for v in floats)
    assert sum(v.size for v in floats) == 1352225
    net, path = load_fastdepth(PACKAGED)
    assert path == PACKAGED
    with torch.inference_mode():
        depth, _ = net(torch.rand(1, 3, 64, 96))
    assert depth.shape == (1, 1, 64, 96) and torch.isfinite(depth).all()


def test_writer_reproduces_the_packaged_bytes(tmp_path):
    """Reading the packaged file and writing it again gives the same bytes: the writer
    depends on nothing but its inputs (no timestamps, no compression)."""
    header, weights = read_parts(PACKAGED)
    members = pack_graph(header["modelTopology"], weights, header["source"])
    assert list(members)[0] == HEADER_KEY
    write_npz(tmp_path / "again.npz", members)
    assert (tmp_path / "again.npz").read_bytes() == PACKAGED.read_bytes()


def test_weight_beyond_float16_is_refused():
    with pytest.raises(ValueError, match="float16"):
        pack_graph({"node": []}, {"big": np.array([1e6], np.float32)}, {})


@pytest.mark.parametrize("content", ["zip-garbage", "other-npz", "truncated"])
def test_bad_model_file_is_one_line(tmp_path, content):
    bad = tmp_path / "fastdepth.npz"
    if content == "zip-garbage":
        bad.write_bytes(b"PK\x03\x04" + b"\0" * 100)
    elif content == "other-npz":
        np.savez(bad, depth=np.zeros(3))
    else:
        bad.write_bytes(PACKAGED.read_bytes()[: PACKAGED.stat().st_size // 2])
    with pytest.raises(ReconInputError) as info:
        FastDepthPrior(weights=bad, progress=False)
    message = str(info.value)
    assert "\n" not in message and str(bad) in message and "recon model file" in message


# --------------------------------------------------------------------------- against the TF.js export


def test_packaged_network_is_the_tfjs_network(fastdepth_weights):
    """The TF.js export already holds float16 weights, so storing them as float16 loses
    nothing: same weights bit for bit, same depth (measured difference 0 on the authors'
    reference frame and on a random frame)."""
    packaged, _ = load_fastdepth(PACKAGED)
    tfjs, _ = load_fastdepth(fastdepth_weights / "model.json")
    ours, theirs = packaged.state_dict(), tfjs.state_dict()
    assert list(ours) == list(theirs)
    for name in ours:
        assert torch.equal(ours[name], theirs[name]), name
    rgb = np.load(fastdepth_weights / "reference" / "rgb.npy").astype(np.float32)
    random = torch.rand(2, 3, 128, 160, generator=torch.Generator().manual_seed(0))
    frames = [torch.from_numpy(rgb).permute(2, 0, 1)[None], random]
    with torch.inference_mode():
        for x in frames:
            assert torch.equal(packaged(x)[0], tfjs(x)[0])


def test_conversion_reproduces_the_committed_files(fastdepth_weights, tmp_path):
    out = tmp_path / "models"
    run = subprocess.run([sys.executable, str(REPO / "scripts" / "convert_fastdepth.py"), "--source",
                          str(fastdepth_weights), "--out", str(out), "--no-compare"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "largest relative float16 rounding of a weight: 0" in run.stdout
    assert (out / "fastdepth.npz").read_bytes() == PACKAGED.read_bytes()
    assert (out / "fastdepth.LICENSE").read_text() == (PACKAGED.parent / "fastdepth.LICENSE").read_text()
