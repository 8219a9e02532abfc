"""The project's own model file: a TF.js graph's topology and its weights in one ``.npz``.

This module owns that format (writing and reading it) and :func:`read_graph`, which reads a
network from either it or a TF.js ``model.json``. The default FastDepth prior ships in this
format as ``recon/priors/models/fastdepth.npz``, converted once by
``scripts/convert_fastdepth.py``. A plain numpy ``.npz`` readable without pickle: a JSON
``header`` and one array per constant (float weights as float16, as the TF.js export holds
them, cast back at load); the writer makes the same bytes from the same inputs on any machine.
More: docs/depth.md#the-packaged-model-file
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

from ..errors import ReconInputError
from .tfjs_format import TFJSGraph, graph_from_topology, load_tfjs_graph

FORMAT = "recon-graph-npz"
VERSION = 1
HEADER_KEY = "header"
_ZIP_MAGIC = b"PK\x03\x04"
# Zip's earliest date: a fixed member timestamp makes the file byte-reproducible.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


# --------------------------------------------------------------------------- writing


def _stored(values: np.ndarray) -> np.ndarray:
    """The array as stored: floats as little-endian float16, anything else unchanged."""
    if values.dtype.kind == "f":
        with np.errstate(over="ignore"):  # pack_graph reports overflow with the weight's name
            return values.astype("<f2")
    return values.astype(values.dtype.newbyteorder("<"))


def pack_graph(topology: dict, weights: dict[str, np.ndarray], source: dict) -> dict[str, np.ndarray]:
    """The members of a packaged model: ``header`` first, then one array per weight.

    topology: a TF.js ``modelTopology``; weights: decoded constants (name -> array, in
    manifest order); source: provenance, written into the header as is.

    Raises:
        ValueError: a float weight outside float16's range (it would become inf).
    """
    entries, members = [], {}
    for k, (name, values) in enumerate(weights.items()):
        stored = _stored(values)
        if values.dtype.kind == "f" and not np.isfinite(stored[np.isfinite(values)]).all():
            raise ValueError(f"weight {name} does not fit in float16 (max |value| {np.abs(values).max():g})")
        key = f"w{k:03d}"
        entries.append({"key": key, "name": name, "dtype": values.dtype.name, "shape": list(values.shape)})
        members[key] = stored
    header = {"format": FORMAT, "version": VERSION, "source": source, "modelTopology": topology, "weights": entries}
    text = json.dumps(header, sort_keys=True, indent=None, separators=(",", ":"))
    return {HEADER_KEY: np.frombuffer(text.encode("utf-8"), dtype=np.uint8), **members}


def write_npz(path: str | Path, members: dict[str, np.ndarray]) -> None:
    """Write ``members`` as an ``.npz`` whose bytes depend on nothing but the arrays."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for key, values in members.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.ascontiguousarray(values), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_EPOCH)
            info.create_system = 3  # Unix, whatever machine converts
            info.external_attr = 0o644 << 16
            archive.writestr(info, buffer.getvalue())


# --------------------------------------------------------------------------- reading


def _read_members(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and every other member of a packaged model."""
    with np.load(path, allow_pickle=False) as npz:
        header = json.loads(npz[HEADER_KEY].tobytes().decode("utf-8"))
        arrays = {key: npz[key] for key in npz.files if key != HEADER_KEY}
    return header, arrays


def _check_header(header: dict) -> None:
    """Raise ValueError unless ``header`` is this format's, with a topology node list."""
    if not isinstance(header, dict):
        raise ValueError("the header is not a JSON object")
    if header.get("format") != FORMAT or header.get("version") != VERSION:
        raise ValueError(f"format {header.get('format')!r} version {header.get('version')!r},"
                         f" expected {FORMAT!r} version {VERSION}")
    if not isinstance(header.get("modelTopology"), dict) or not isinstance(header["modelTopology"].get("node"), list):
        raise ValueError("the header has no modelTopology.node list")


def _weights(header: dict, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Constants by TF name, cast back to their declared dtype (float16 -> float32)."""
    weights = {}
    for entry in header["weights"]:
        values = arrays[entry["key"]]
        if list(values.shape) != list(entry["shape"]):
            raise ValueError(f"{entry['name']} has shape {list(values.shape)}, the header says {entry['shape']}")
        weights[entry["name"]] = values.astype(np.dtype(entry["dtype"]))
    return weights


def read_parts(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The header and the weights (by TF name, declared dtype) of a packaged model.

    Raises:
        ReconInputError: one line naming the file when it is not a readable packaged model.
    """
    path = Path(path)
    try:
        header, arrays = _read_members(path)
        _check_header(header)
        weights = _weights(header, arrays)
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        # json and Unicode decoding errors are ValueErrors too.
        raise ReconInputError(f"{path}: not a readable recon model file ({type(exc).__name__}: {exc})") from None
    return header, weights


def read_packaged(path: str | Path) -> TFJSGraph:
    """The graph of a packaged model, ready for :func:`recon.priors.tfjs.compile_graph`.

    Raises:
        ReconInputError: one line naming the file when it is not a readable packaged model.
    """
    header, weights = read_parts(path)
    return graph_from_topology(header["modelTopology"]["node"], weights, str(path))


def read_graph(path: str | Path) -> TFJSGraph:
    """A packaged ``.npz`` model or a TF.js ``model.json``, told apart by content (a zip or not)."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            magic = handle.read(len(_ZIP_MAGIC))
    except OSError as exc:
        raise ReconInputError(f"{path}: cannot read model file ({exc.strerror or exc})") from None
    return read_packaged(path) if magic == _ZIP_MAGIC else load_tfjs_graph(path)


__all__ = ["FORMAT", "VERSION", "pack_graph", "read_graph", "read_packaged", "read_parts", "write_npz"]
