"""The TensorFlow.js graph-model file format: ``model.json`` (topology and weight
manifest) and its binary weight shards, read into a :class:`TFJSGraph` of nodes in
topological order with their weights as numpy arrays (no TensorFlow needed).

Turning the graph into a torch module is :mod:`recon.priors.tfjs`'s job.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ReconInputError

# TF.js stored dtypes (little-endian on disk).
_STORED_DTYPES = {
    "float32": "<f4",
    "float16": "<f2",
    "int32": "<i4",
    "uint8": "u1",
    "uint16": "<u2",
    "int8": "i1",
    "bool": "?",
}
CONV_OPS = ("Conv2D", "DepthwiseConv2dNative")
ACTIVATIONS = {"Relu": "relu", "Relu6": "relu6"}


class GraphError(ValueError):
    """The graph or its weights do not make a network we can build (corrupt or unsupported)."""


@dataclass
class GraphNode:
    """One TF node: ``inputs`` are producer names (``:0`` and control inputs stripped)."""

    name: str
    op: str
    inputs: list[str]
    attr: dict


@dataclass
class TFJSGraph:
    """A parsed TF.js graph model: nodes in topological order, constants as numpy arrays."""

    nodes: list[GraphNode]
    constants: dict[str, np.ndarray]
    input_shape: tuple[int, ...] | None = None
    source: str = ""


# --------------------------------------------------------------------------- reading
# Weight files are read here, not in recon/io: their format (a TF.js model.json and its
# shards) is this loader's business, and nothing else in recon reads or writes them.


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReconInputError(f"{path}: not a readable TF.js model.json ({type(exc).__name__}: {exc})") from None


def read_weight_manifest(manifest: list[dict], folder: Path) -> dict[str, np.ndarray]:
    """Decode every weight listed in a TF.js ``weightsManifest``.

    Each group's shards are concatenated and read entry by entry, advancing by each
    entry's *stored* size: quantised entries (``quantization.dtype``) take their stored
    dtype's size, the others their own dtype's (the int32 Pad constants of a float16
    export stay 4 bytes), so a single global element size would misalign everything after
    the first int constant.

    Returns:
        name -> array of the manifest's ``shape`` in its declared (dequantised) dtype.
    """
    weights: dict[str, np.ndarray] = {}
    for group in manifest:
        shards = [folder / p for p in group["paths"]]
        blobs = []
        for shard in shards:
            try:
                blobs.append(shard.read_bytes())
            except OSError as exc:
                raise ReconInputError(f"{shard}: cannot read weight shard ({exc.strerror or exc})") from None
        data = b"".join(blobs)
        where = shards[-1] if len(shards) == 1 else f"{shards[0].parent}/{{{','.join(s.name for s in shards)}}}"
        offset = 0
        for entry in group["weights"]:
            quant = entry.get("quantization")
            stored = np.dtype(_STORED_DTYPES[(quant or entry)["dtype"]])
            shape = [int(s) for s in entry["shape"]]
            count = int(np.prod(shape, dtype=np.int64))
            end = offset + count * stored.itemsize
            if end > len(data):
                raise ReconInputError(
                    f"{where}: truncated or wrong weight file: {entry['name']} needs bytes {offset}-{end}"
                    f" but the file has {len(data)}"
                )
            values = np.frombuffer(data, dtype=stored, count=count, offset=offset).reshape(shape)
            weights[entry["name"]] = _dequantise(values, entry, quant)
            offset = end
        if offset != len(data):
            raise ReconInputError(
                f"{where}: weight file has {len(data)} bytes but the manifest describes {offset}"
            )
    return weights


def _dequantise(values: np.ndarray, entry: dict, quant: dict | None) -> np.ndarray:
    target = np.dtype(_STORED_DTYPES[entry["dtype"]]).newbyteorder("=")
    if quant and quant["dtype"] in ("uint8", "uint16") and "scale" in quant:
        # Affine quantisation: value = q * scale + min.
        return (values.astype(np.float32) * quant["scale"] + quant.get("min", 0.0)).astype(target)
    return values.astype(target)


def _strip(name: str) -> str:
    return name.split(":")[0]


def _topological(nodes: list[GraphNode]) -> list[GraphNode]:
    """Kahn's algorithm, stable in file order (exported files are usually already sorted)."""
    by_name = {n.name: n for n in nodes}
    indegree = {n.name: sum(i in by_name for i in n.inputs) for n in nodes}
    consumers: dict[str, list[str]] = {n.name: [] for n in nodes}
    for n in nodes:
        for i in n.inputs:
            if i in by_name:
                consumers[i].append(n.name)
    order = {n.name: k for k, n in enumerate(nodes)}
    ready = sorted((n for n in indegree if indegree[n] == 0), key=order.get)
    out = []
    while ready:
        name = ready.pop(0)
        out.append(by_name[name])
        fresh = []
        for c in consumers[name]:
            indegree[c] -= 1
            if indegree[c] == 0:
                fresh.append(c)
        ready = sorted(ready + fresh, key=order.get)
    if len(out) != len(nodes):
        raise GraphError("graph has a cycle")
    return out


def load_tfjs_graph(model_json: str | Path) -> TFJSGraph:
    """Parse ``model.json`` and its weight shards.

    Raises:
        ReconInputError: unreadable/invalid JSON, missing or truncated shards, or a weight
            whose manifest shape disagrees with the graph's constant shape.
    """
    path = Path(model_json)
    spec = _read_json(path)
    try:
        raw_nodes = spec["modelTopology"]["node"]
        manifest = spec["weightsManifest"]
    except (KeyError, TypeError):
        raise ReconInputError(f"{path}: not a TF.js graph model (no modelTopology.node / weightsManifest)") from None
    return graph_from_topology(raw_nodes, read_weight_manifest(manifest, path.parent), str(path))


def graph_from_topology(raw_nodes: list[dict], weights: dict[str, np.ndarray], source: str) -> TFJSGraph:
    """A :class:`TFJSGraph` from a TF.js ``modelTopology.node`` list and its decoded weights.

    Shared by the TF.js reader above and the packaged model (:mod:`recon.priors.packaged`,
    which keeps the same topology beside float16 weights), so both are checked alike.

    Raises:
        ReconInputError: a constant without weights or with another shape, or a cycle;
            the message starts with ``source``.
    """
    nodes = []
    input_shape = None
    for raw in raw_nodes:
        node = GraphNode(
            name=raw["name"],
            op=raw["op"],
            inputs=[_strip(i) for i in raw.get("input", []) if not i.startswith("^")],
            attr=raw.get("attr", {}),
        )
        if node.op == "Const":
            if node.name not in weights:
                raise ReconInputError(f"{source}: constant {node.name} has no entry in the weight manifest")
            dims = node.attr.get("value", {}).get("tensor", {}).get("tensorShape", {}).get("dim")
            if dims is not None and [int(d["size"]) for d in dims] != list(weights[node.name].shape):
                raise ReconInputError(
                    f"{source}: constant {node.name} has shape {list(weights[node.name].shape)} in the manifest"
                    f" but {[int(d['size']) for d in dims]} in the graph"
                )
        if node.op == "Placeholder":
            dims = node.attr.get("shape", {}).get("shape", {}).get("dim", [])
            input_shape = tuple(int(d["size"]) for d in dims) or None
        nodes.append(node)
    try:
        nodes = _topological(nodes)
    except GraphError as exc:
        raise ReconInputError(f"{source}: {exc}") from None
    return TFJSGraph(nodes=nodes, constants=weights, input_shape=input_shape, source=source)


__all__ = ["GraphError", "GraphNode", "TFJSGraph", "graph_from_topology", "load_tfjs_graph", "read_weight_manifest"]
