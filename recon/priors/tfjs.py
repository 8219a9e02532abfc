"""Compiling a TensorFlow.js graph (read by :mod:`recon.priors.tfjs_format`) into a plain
torch module.

It supports the ops that convolutional encoder-decoders such as FastDepth are exported with
(anything else is reported, not guessed), fuses ``Pad -> Conv -> Add(bias) -> Relu/Relu6``
chains into one ``nn.Conv2d`` and replaces resize-to-a-baked-size by an integer nearest
upsampling factor, so the network is fully convolutional.
More: docs/depth.md#the-packaged-model-file
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .tfjs_format import ACTIVATIONS, CONV_OPS, GraphError, GraphNode, TFJSGraph

# --------------------------------------------------------------------------- compiling


def _attr_string(node: GraphNode, key: str, default: str = "") -> str:
    value = node.attr.get(key, {}).get("s")
    return base64.b64decode(value).decode() if value is not None else default


def _attr_ints(node: GraphNode, key: str) -> list[int]:
    return [int(i) for i in node.attr.get(key, {}).get("list", {}).get("i", [])]


class FusedConv2d(nn.Conv2d):
    """Conv2d with its bias and activation ("none", "relu", "relu6") applied in one place."""

    def __init__(self, *args, activation: str = "none", **kwargs):
        super().__init__(*args, **kwargs)
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = super().forward(x)
        if self.activation == "relu":
            return torch.relu_(y) if not y.requires_grad else torch.relu(y)
        if self.activation == "relu6":
            return y.clamp_(0.0, 6.0) if not y.requires_grad else y.clamp(0.0, 6.0)
        return y

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, activation={self.activation}"


@dataclass
class TensorInfo:
    """Static facts about one graph tensor, for the graph's reference input size.

    op: producing op ("Relu6", "Conv2D", ...); stride: input size / tensor size (rows, cols).
    """

    op: str
    channels: int
    stride: tuple[float, float]
    order: int


@dataclass
class _Step:
    kind: str  # "conv", "add", "add_const", "act", "resize", "pad"
    inputs: tuple[int, ...]
    output: int
    arg: object = None
    release: tuple[int, ...] = field(default=())


class GraphNet(nn.Module):
    """A compiled TF graph: NCHW float input -> NCHW output, plus named intermediate taps.

    ``tensors`` maps every graph tensor name to its :class:`TensorInfo` (channels and stride
    relative to the input), so callers can pick feature layers by structure.
    """

    def __init__(self, layers, constants, steps, input_slot, output_slot, slots, tensors, num_slots, multiple):
        super().__init__()
        self.layers = nn.ModuleList(layers)
        for k, value in enumerate(constants):
            self.register_buffer(f"const{k}", value)
        self.steps = steps
        self.input_slot = input_slot
        self.output_slot = output_slot
        self.slots = slots
        self.tensors = tensors
        self.num_slots = num_slots
        # Height and width must be multiples of this (product of the strides).
        self.multiple = multiple

    def forward(self, x: torch.Tensor, taps: tuple[str, ...] = ()) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: (B, C, H, W) with H, W multiples of ``self.multiple``.

        Returns:
            the output (B, C', H', W') and {tap name: (B, c, h, w)}.
        """
        if x.shape[-2] % self.multiple or x.shape[-1] % self.multiple:
            raise ValueError(f"input size {tuple(x.shape[-2:])} is not a multiple of {self.multiple}")
        keep = {self.slots[t] for t in taps}
        values: list[torch.Tensor | None] = [None] * self.num_slots
        values[self.input_slot] = x
        for step in self.steps:
            args = [values[i] for i in step.inputs]
            if step.kind == "conv":
                out = self.layers[step.arg](args[0])
            elif step.kind == "add":
                out = args[0] + args[1]
            elif step.kind == "add_const":
                out = args[0] + getattr(self, f"const{step.arg}")
            elif step.kind == "act":
                out = torch.relu(args[0]) if step.arg == "relu" else args[0].clamp(0.0, 6.0)
            elif step.kind == "resize":
                out = F.interpolate(args[0], scale_factor=step.arg, mode="nearest")
            else:  # pad: (left, right, top, bottom)
                out = F.pad(args[0], step.arg)
            values[step.output] = out
            # Drop intermediates after their last use: keeps large-frame batches in memory.
            for slot in step.release:
                if slot not in keep:
                    values[slot] = None
        return values[self.output_slot], {t: values[self.slots[t]] for t in taps}


def compile_graph(graph: TFJSGraph) -> GraphNet:
    """Build a :class:`GraphNet` by walking the graph in topological order.

    Raises:
        GraphError: unsupported op or attribute, or tensor shapes that do not fit together.
    """
    return _GraphCompiler(graph).compile()


class _GraphCompiler:
    """The state of one :func:`compile_graph` walk; one handler per supported op type."""

    def __init__(self, graph: TFJSGraph):
        self.graph = graph
        self.consts = graph.constants
        self.consumers: dict[str, int] = {}
        for node in graph.nodes:
            for i in node.inputs:
                self.consumers[i] = self.consumers.get(i, 0) + 1
        self.slots: dict[str, int] = {}  # tensor name -> slot
        self.shapes: dict[int, tuple[int, int, int]] = {}  # slot -> (C, H, W) at the reference size
        self.producer: dict[int, _Step] = {}
        self.deferred_pad: dict[str, tuple[str, int, int]] = {}  # Pad name -> (input, pad_h, pad_w)
        self.steps: list[_Step] = []
        self.layers: list[FusedConv2d] = []
        self.buffers: list[torch.Tensor] = []
        self.tensors: dict[str, TensorInfo] = {}
        self.input_slot = None
        self.in_h = self.in_w = None

    def compile(self) -> GraphNet:
        graph = self.graph
        for order, node in enumerate(graph.nodes):
            if node.op == "Const":
                continue
            handler = _OP_HANDLERS.get(node.op)
            if handler is None:
                raise GraphError(f"{node.name}: unsupported op {node.op}")
            handler(self, node)
            if node.name in self.slots:
                c, h, w = self.shapes[self.slots[node.name]]
                self.tensors[node.name] = TensorInfo(
                    op=node.op, channels=c, stride=(self.in_h / h, self.in_w / w), order=order
                )

        outputs = [n.name for n in graph.nodes if n.op != "Const" and self.consumers.get(n.name, 0) == 0]
        if self.input_slot is None or len(outputs) != 1:
            raise GraphError(f"expected one input and one output, found outputs {outputs}")
        output_slot = self.slots[outputs[0]]
        _set_releases(self.steps, output_slot)
        multiple = int(round(max(max(t.stride) for t in self.tensors.values())))
        return GraphNet(self.layers, self.buffers, self.steps, self.input_slot, output_slot, self.slots,
                        self.tensors, len(self.shapes), multiple)

    def new_slot(self, name: str, shape: tuple[int, int, int], step: _Step | None) -> int:
        slot = len(self.shapes)
        self.slots[name] = slot
        self.shapes[slot] = shape
        if step is not None:
            step.output = slot
            self.steps.append(step)
            self.producer[slot] = step
        return slot

    def fusable(self, tensor: str, kind: str) -> _Step | None:
        """The conv step producing ``tensor`` if it can absorb the next op of ``kind``."""
        slot = self.slots[tensor]
        step = self.producer.get(slot)
        if step is None or step.kind != "conv" or self.consumers.get(tensor, 0) != 1:
            return None
        layer = self.layers[step.arg]
        if kind == "bias" and layer.bias is None and layer.activation == "none":
            return step
        if kind == "act" and layer.activation == "none":
            return step
        return None

    def placeholder(self, node: GraphNode) -> None:
        if not self.graph.input_shape or len(self.graph.input_shape) != 4:
            raise GraphError(f"input {node.name} needs a static NHWC shape")
        _, self.in_h, self.in_w, channels = self.graph.input_shape
        self.input_slot = self.new_slot(node.name, (channels, self.in_h, self.in_w), None)

    def identity(self, node: GraphNode) -> None:
        self.slots[node.name] = self.slots[node.inputs[0]]

    def pad(self, node: GraphNode) -> None:
        name = node.name
        source, pads = node.inputs[0], self.consts[node.inputs[1]].astype(int)
        (b0, b1), (top, bottom), (left, right), (c0, c1) = pads
        if b0 or b1 or c0 or c1:
            raise GraphError(f"{name}: padding of batch or channel axes is not supported")
        users = [n for n in self.graph.nodes if name in n.inputs]
        if top == bottom and left == right and len(users) == 1 and users[0].op in CONV_OPS:
            self.deferred_pad[name] = (source, int(top), int(left))
            return
        c, h, w = self.shapes[self.slots[source]]
        self.new_slot(name, (c, h + top + bottom, w + left + right),
                      _Step("pad", (self.slots[source],), -1, (int(left), int(right), int(top), int(bottom))))

    def conv(self, node: GraphNode) -> None:
        name = node.name
        source, kernel = node.inputs[0], self.consts[node.inputs[1]]
        pad_h = pad_w = 0
        if source in self.deferred_pad:
            source, pad_h, pad_w = self.deferred_pad.pop(source)
        stride, (pad_h, pad_w) = _conv_geometry(node, kernel.shape[:2], pad_h, pad_w)
        kh, kw = kernel.shape[:2]
        c_in, h, w = self.shapes[self.slots[source]]
        weight, c_out, groups = _conv_weight(node, kernel, c_in)
        layer = FusedConv2d(
            c_in, c_out, (kh, kw), stride=stride, padding=(pad_h, pad_w), groups=groups, bias=False
        )
        with torch.no_grad():
            layer.weight.copy_(torch.from_numpy(np.ascontiguousarray(weight, dtype=np.float32)))
        self.layers.append(layer)
        out_h = (h + 2 * pad_h - kh) // stride[0] + 1
        out_w = (w + 2 * pad_w - kw) // stride[1] + 1
        self.new_slot(name, (c_out, out_h, out_w), _Step("conv", (self.slots[source],), -1, len(self.layers) - 1))

    def add(self, node: GraphNode) -> None:
        name, slots, shapes, consts = node.name, self.slots, self.shapes, self.consts
        a, b = node.inputs
        if b in consts or a in consts:
            tensor, const = (a, consts[b]) if b in consts else (b, consts[a])
            c = shapes[slots[tensor]][0]
            if const.size != c or (const.ndim and const.shape[-1] != c):
                raise GraphError(f"{name}: constant of shape {const.shape} does not fit {c} channels")
            step = self.fusable(tensor, "bias")
            if step is not None:
                self.layers[step.arg].bias = nn.Parameter(torch.from_numpy(const.reshape(c).astype(np.float32)))
                slots[name] = slots[tensor]
            else:
                self.buffers.append(torch.from_numpy(const.reshape(1, c, 1, 1).astype(np.float32)))
                self.new_slot(name, shapes[slots[tensor]],
                              _Step("add_const", (slots[tensor],), -1, len(self.buffers) - 1))
        else:
            if shapes[slots[a]] != shapes[slots[b]]:
                raise GraphError(f"{name}: adding shapes {shapes[slots[a]]} and {shapes[slots[b]]}")
            self.new_slot(name, shapes[slots[a]], _Step("add", (slots[a], slots[b]), -1))

    def activation(self, node: GraphNode) -> None:
        tensor, kind = node.inputs[0], ACTIVATIONS[node.op]
        step = self.fusable(tensor, "act")
        if step is not None:
            self.layers[step.arg].activation = kind
            self.slots[node.name] = self.slots[tensor]
        else:
            self.new_slot(node.name, self.shapes[self.slots[tensor]], _Step("act", (self.slots[tensor],), -1, kind))

    def resize(self, node: GraphNode) -> None:
        name = node.name
        if node.attr.get("align_corners", {}).get("b", False):
            raise GraphError(f"{name}: align_corners resizing is not supported")
        tensor, size = node.inputs[0], self.consts[node.inputs[1]].astype(int)
        c, h, w = self.shapes[self.slots[tensor]]
        # The export bakes the target size for its own input size; only the (integer)
        # factor matters, which makes the network work at any multiple-of-stride size.
        # With half_pixel_centers an integer factor picks the same pixels as torch "nearest".
        if size[0] % h or size[1] % w:
            raise GraphError(f"{name}: resize {h}x{w} -> {size[0]}x{size[1]} is not an integer factor")
        factor = (float(size[0] // h), float(size[1] // w))
        self.new_slot(name, (c, int(size[0]), int(size[1])), _Step("resize", (self.slots[tensor],), -1, factor))


def _conv_geometry(node: GraphNode, kernel_hw, pad_h: int, pad_w: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """Check a conv node's attributes; returns its (row, col) stride and (pad_h, pad_w).

    ``pad_h``/``pad_w`` come from a fused Pad node (0 if none).
    """
    name = node.name
    if _attr_string(node, "data_format", "NHWC") != "NHWC":
        raise GraphError(f"{name}: only NHWC graphs are supported")
    if any(d != 1 for d in _attr_ints(node, "dilations") or [1]):
        raise GraphError(f"{name}: dilated convolutions are not supported")
    strides = _attr_ints(node, "strides") or [1, 1, 1, 1]
    stride = (strides[1], strides[2])
    kh, kw = kernel_hw
    padding = _attr_string(node, "padding", "VALID")
    if padding == "SAME":
        if stride != (1, 1) or kh % 2 == 0 or kw % 2 == 0 or pad_h or pad_w:
            raise GraphError(f"{name}: SAME padding is only supported for odd kernels at stride 1")
        pad_h, pad_w = kh // 2, kw // 2
    elif padding != "VALID":
        raise GraphError(f"{name}: padding {padding} is not supported")
    return stride, (pad_h, pad_w)


def _conv_weight(node: GraphNode, kernel: np.ndarray, c_in: int) -> tuple[np.ndarray, int, int]:
    """A TF conv kernel as a torch weight (OIHW); returns (weight, output channels, groups)."""
    kh, kw = kernel.shape[:2]
    if node.op == "Conv2D":
        if kernel.shape[2] != c_in:
            raise GraphError(f"{node.name}: kernel {kernel.shape} does not fit {c_in} input channels")
        return kernel.transpose(3, 2, 0, 1), kernel.shape[3], 1  # HWIO -> OIHW
    if kernel.shape[2] != c_in:
        raise GraphError(f"{node.name}: depthwise kernel {kernel.shape} does not fit {c_in} channels")
    c_out = kernel.shape[2] * kernel.shape[3]
    # HWCM -> (C*M, 1, H, W); TF orders output channels c*M + m, as does torch.
    return kernel.transpose(2, 3, 0, 1).reshape(c_out, 1, kh, kw), c_out, c_in


_OP_HANDLERS = {
    "Placeholder": _GraphCompiler.placeholder,
    "Identity": _GraphCompiler.identity,
    "Pad": _GraphCompiler.pad,
    **{op: _GraphCompiler.conv for op in CONV_OPS},
    **{op: _GraphCompiler.add for op in ("AddV2", "Add", "BiasAdd")},
    **{op: _GraphCompiler.activation for op in ACTIVATIONS},
    "ResizeNearestNeighbor": _GraphCompiler.resize,
}


def _set_releases(steps: list[_Step], output_slot: int) -> None:
    """Mark, on each step, the slots whose last reader it is."""
    last: dict[int, int] = {}
    for k, step in enumerate(steps):
        for slot in step.inputs:
            last[slot] = k
    for k, step in enumerate(steps):
        step.release = tuple(s for s in set(step.inputs) if last[s] == k and s != output_slot)


def activation_bounds(net: GraphNet, low: float, high: float) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """Per-channel bounds every slot can take for any input in [low, high] (interval arithmetic).

    Sound but not tight: a channel with equal bounds is constant for *every* input (e.g.
    pruned filters whose ReLU never fires), never just for the images seen so far. Zero
    padding adds 0 to the range of padded convolutions.

    Returns:
        slot -> (lower (C,), upper (C,)).
    """
    channels = net.tensors[next(n for n, s in net.slots.items() if s == net.input_slot)].channels
    bounds = {net.input_slot: (torch.full((channels,), float(low)), torch.full((channels,), float(high)))}
    with torch.no_grad():
        for step in net.steps:
            lo, hi = bounds[step.inputs[0]]
            if step.kind == "conv":
                layer = net.layers[step.arg]
                if layer.padding != (0, 0):
                    lo, hi = lo.clamp(max=0.0), hi.clamp(min=0.0)
                w = layer.weight.detach().float()
                pos, neg = w.clamp(min=0.0).sum((2, 3)), w.clamp(max=0.0).sum((2, 3))  # (O, I/groups)
                if layer.groups == 1:
                    lo, hi = pos @ lo + neg @ hi, pos @ hi + neg @ lo
                else:
                    per_group = w.shape[0] // layer.groups
                    lo_in, hi_in = lo.repeat_interleave(per_group), hi.repeat_interleave(per_group)
                    lo, hi = ((pos * lo_in[:, None] + neg * hi_in[:, None]).sum(1),
                              (pos * hi_in[:, None] + neg * lo_in[:, None]).sum(1))
                if layer.bias is not None:
                    lo, hi = lo + layer.bias.detach(), hi + layer.bias.detach()
                top = {"relu": float("inf"), "relu6": 6.0}.get(layer.activation)
                if top is not None:
                    lo, hi = lo.clamp(0.0, top), hi.clamp(0.0, top)
            elif step.kind == "add":
                lo2, hi2 = bounds[step.inputs[1]]
                lo, hi = lo + lo2, hi + hi2
            elif step.kind == "add_const":
                const = getattr(net, f"const{step.arg}").flatten()
                lo, hi = lo + const, hi + const
            elif step.kind == "act":
                top = float("inf") if step.arg == "relu" else 6.0
                lo, hi = lo.clamp(0.0, top), hi.clamp(0.0, top)
            elif step.kind == "pad":
                lo, hi = lo.clamp(max=0.0), hi.clamp(min=0.0)
            bounds[step.output] = (lo, hi)
    return bounds
