"""Convert the FastDepth TF.js export into the model file that ships with recon.

FastDepth (Wofk, Ma, Yang, Karaman, Sze: "FastDepth: Fast Monocular Depth Estimation on
Embedded Systems", ICRA 2019; MIT licence) is recon's default depth prior. This script
was run once to make ``recon/priors/models/fastdepth.npz`` and its licence notice
``fastdepth.LICENSE`` from the TF.js export (model.json, group1-shard1of1.bin, LICENSE);
the format is :mod:`recon.priors.packaged`'s. It downloads nothing.

    python scripts/convert_fastdepth.py [--source ../shared/weights/fastdepth] [--out recon/priors/models]

The output depends only on the input files (tests/test_priors_packaged.py converts again
and compares bytes). Afterwards the script prints how far the packaged network's depth is
from the TF.js network's and, when the source has ``reference/``, from the authors'
reference prediction.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import textwrap
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# The repository's own recon, whatever is installed in the environment.
sys.path.insert(0, str(REPO))

from recon.priors.packaged import pack_graph, write_npz  # noqa: E402
from recon.priors.tfjs_format import read_weight_manifest  # noqa: E402

DEFAULT_SOURCE = REPO.parent / "shared" / "weights" / "fastdepth"
DEFAULT_OUT = REPO / "recon" / "priors" / "models"
MODEL_FILE = "fastdepth.npz"
LICENSE_FILE = "fastdepth.LICENSE"
CITATION = ('Wofk, Ma, Yang, Karaman, Sze, "FastDepth: Fast Monocular Depth Estimation on Embedded Systems",'
            ' ICRA 2019, https://github.com/dwofk/fast-depth')


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def provenance(spec: dict, source: Path) -> dict:
    """What was converted: the TF.js files by name and hash (no local paths, so the bytes
    do not depend on where the source lies), the TF.js converter, and this script."""
    files = ["model.json", *(p for group in spec["weightsManifest"] for p in group["paths"])]
    return {
        "model": "fastdepth",
        "citation": CITATION,
        "license": "MIT (see fastdepth.LICENSE)",
        "converted_from": "TF.js graph model: " + ", ".join(files),
        "sha256": {name: _sha256(source / name) for name in files},
        "tfjs": {key: spec.get(key) for key in ("format", "generatedBy", "convertedBy")},
        "signature": spec.get("signature"),
        "converted_by": "scripts/convert_fastdepth.py",
    }


def float16_rounding(weights: dict[str, np.ndarray]) -> float:
    """Largest relative change any float weight suffers in float16 (0: lossless)."""
    worst = 0.0
    for values in weights.values():
        if values.dtype.kind == "f" and values.size:
            back = values.astype(np.float16).astype(values.dtype)
            scale = np.maximum(np.abs(values), np.finfo(np.float16).tiny)
            worst = max(worst, float(np.max(np.abs(back - values) / scale)))
    return worst


def license_notice(source: Path) -> str:
    """The licence beside the packaged file: what it is, where from, by what; then the MIT text."""
    what = (f"{MODEL_FILE} holds the weights of FastDepth ({CITATION}), converted from its TF.js graph-model"
            " export (model.json + group1-shard1of1.bin, kept outside the repository in"
            " ../shared/weights/fastdepth) by scripts/convert_fastdepth.py: the same graph, the weights"
            " stored as float16 (as the export stores them). The licence of the original follows.")
    return textwrap.fill(what, width=88) + "\n\n" + (source / "LICENSE").read_text()


def convert(source: Path, out: Path) -> tuple[Path, Path, dict[str, np.ndarray]]:
    """Write ``out/fastdepth.npz`` and ``out/fastdepth.LICENSE``; returns both paths and the weights."""
    spec = json.loads((source / "model.json").read_text())
    weights = read_weight_manifest(spec["weightsManifest"], source)
    out.mkdir(parents=True, exist_ok=True)
    model, notice = out / MODEL_FILE, out / LICENSE_FILE
    write_npz(model, pack_graph(spec["modelTopology"], weights, provenance(spec, source)))
    notice.write_text(license_notice(source))
    return model, notice, weights


def _relative(a: np.ndarray, b: np.ndarray) -> str:
    valid = b > 0  # the network's final ReLU may give 0 ("no prediction")
    rel = np.abs(a - b)[valid] / b[valid]
    return f"max {rel.max():.3g}, median {np.median(rel):.3g}"


def compare(model: Path, source: Path) -> None:
    """Print the packaged network's depth against the TF.js network's and the authors' reference."""
    import torch

    from recon.priors.fastdepth import load_fastdepth

    reference = source / "reference"
    if (reference / "rgb.npy").is_file():
        rgb = np.load(reference / "rgb.npy").astype(np.float32)
    else:  # any frame will do for packaged against TF.js
        rgb = np.random.default_rng(0).random((224, 224, 3), dtype=np.float32)
    x = torch.from_numpy(rgb).permute(2, 0, 1)[None]
    depth = {}
    for label, path in (("packaged", model), ("tfjs", source / "model.json")):
        net, _ = load_fastdepth(path)
        with torch.inference_mode():
            depth[label] = net(x)[0][0, 0].numpy()
    print(f"depth, packaged (float16 weights) vs TF.js (float32): {_relative(depth['packaged'], depth['tfjs'])}")
    if (reference / "pred.npy").is_file():
        pred = np.load(reference / "pred.npy")[0, 0]
        for label in ("packaged", "tfjs"):
            print(f"depth, {label} vs the authors' reference prediction: {_relative(depth[label], pred)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, default=DEFAULT_SOURCE,
                        help="folder of the TF.js export (default %(default)s)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default %(default)s)")
    parser.add_argument("--no-compare", action="store_true", help="skip the depth comparison")
    args = parser.parse_args(argv)
    if not (args.source / "model.json").is_file():
        print(f"convert_fastdepth: no model.json in {args.source}", file=sys.stderr)
        return 2
    model, notice, weights = convert(args.source, args.out)
    count = sum(v.size for v in weights.values() if v.dtype.kind == "f")
    print(f"wrote {model} ({model.stat().st_size / 1e6:.2f} MB, {count} float weights) and {notice}")
    print(f"largest relative float16 rounding of a weight: {float16_rounding(weights):.3g}")
    if not args.no_compare:
        compare(model, args.source)
    return 0


if __name__ == "__main__":
    sys.exit(main())
