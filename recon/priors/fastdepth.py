"""FastDepth, the default metric depth prior (Wofk et al., ICRA 2019; MIT licence).

This module owns everything FastDepth-specific: loading the network (the packaged model or a
TF.js export, :mod:`recon.priors.weights`) through :mod:`recon.priors.tfjs` (cached), the
preprocessing that maps an arbitrary camera onto what the network saw in training (NYU Depth
v2: the whole frame resized so that its focal lengths at the input match the training ones,
:data:`TRAIN_FOCAL_AT_INPUT`), picking encoder feature layers for MEDeA's feature-metric
loss, and the :class:`FastDepthPrior` itself. More: docs/depth.md#the-packaged-model-file
why: docs/decisions.md#the-priors-input-size
"""

from __future__ import annotations

import copy
import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import ReconInputError
from .base import DepthPrior, PriorOutput
from .packaged import read_graph
from .tfjs import GraphNet, activation_bounds, compile_graph
from .tfjs_format import GraphError
from .weights import find_weights

MODEL_NAME = "fastdepth"
MODEL_FILE = "model.json"

# NYU Depth v2 colour camera (480x640), published calibration.
NYU_SIZE = (480, 640)
NYU_FOCAL = (518.8579, 519.4696)
# Training pipeline: scale 250/480, centre crop 228x304, resize to 224x224.
_NYU_SCALE = 250.0 / 480.0
NYU_CROP_FRACTION = 228.0 / 250.0  # of each axis (304 / (640 * 250/480) is the same 0.912)
TRAIN_INPUT = (224, 224)
TRAIN_FOCAL_AT_INPUT = (
    NYU_FOCAL[0] * _NYU_SCALE * TRAIN_INPUT[1] / 304.0,  # fx ~ 199.1 px
    NYU_FOCAL[1] * _NYU_SCALE * TRAIN_INPUT[0] / 228.0,  # fy ~ 265.8 px
)

# Encoder feature layers offered for MEDeA: the last ReLU6 output at each stride.
FEATURE_LAYERS = {"stride4": 4, "stride8": 8}
# Minimum network input side: the encoder downsamples by 32.
_MIN_SIDE = 64


# ---------------------------------------------------------------------------- model


def load_fastdepth(weights: str | os.PathLike | None = None) -> tuple[GraphNet, Path]:
    """The FastDepth network (CPU, eval mode, shared cache) and the file it came from.

    weights: a TF.js ``model.json``, a packaged ``.npz`` or a folder holding one (see
        :func:`recon.priors.weights.find_weights`); None: $RECON_WEIGHTS, then the model
        packaged with recon (``recon/priors/models/fastdepth.npz``).

    Raises:
        ReconInputError: weights not found (lists the places tried) or corrupt.
    """
    path = find_weights(MODEL_NAME, MODEL_FILE, weights)
    stat = path.stat()
    return _load_cached(str(path.resolve()), stat.st_mtime_ns, stat.st_size), path


@functools.lru_cache(maxsize=2)
def _load_cached(path: str, mtime_ns: int, size: int) -> GraphNet:
    graph = read_graph(path)  # either format gives the same TF.js graph
    try:
        net = compile_graph(graph)
    except (GraphError, KeyError, IndexError) as exc:
        raise ReconInputError(f"{path}: not a usable FastDepth graph ({exc})") from None
    names = [n for n, s in net.slots.items() if s == net.input_slot]
    out_channels = net.tensors[next(n for n, s in net.slots.items() if s == net.output_slot)].channels
    if net.tensors[names[0]].channels != 3 or out_channels != 1:
        raise ReconInputError(f"{path}: expected an RGB -> depth network, got {net.tensors[names[0]].channels}"
                              f" input and {out_channels} output channels")
    return net.eval().requires_grad_(False)


@functools.lru_cache(maxsize=4)
def _on_device(net: GraphNet, device: str, channels_last: bool) -> GraphNet:
    """A copy of the shared network on ``device`` (the CPU original is never moved)."""
    moved = copy.deepcopy(net).to(device)
    return moved.to(memory_format=torch.channels_last) if channels_last else moved


def feature_tensor(net: GraphNet, layer: str) -> str:
    """Graph tensor name of ``layer`` ("stride4" | "stride8"): the encoder's last ReLU6 at that stride."""
    if layer not in FEATURE_LAYERS:
        raise ValueError(f"feature_layer must be one of {', '.join(FEATURE_LAYERS)}, got {layer!r}")
    stride = FEATURE_LAYERS[layer]
    found = [(info.order, name) for name, info in net.tensors.items()
             if info.op == "Relu6" and info.stride == (stride, stride)]
    if not found:
        raise ValueError(f"the network has no ReLU6 output at stride {stride}")
    return max(found)[1]


@functools.lru_cache(maxsize=8)
def kept_channels(net: GraphNet, tensor: str) -> np.ndarray:
    """Indices of the channels of ``tensor`` that are not provably constant.

    Pruning left filters whose ReLU6 can never fire; interval arithmetic over all inputs in
    [0, 1] proves them constant, from the weights alone, so the kept set is the same for
    every sequence. (On real frames about 10 more channels at stride 8 happen to stay 0;
    they cost a little compute but add nothing to MEDeA's S-form loss.)
    """
    lo, hi = activation_bounds(net, 0.0, 1.0)[net.slots[tensor]]
    return np.flatnonzero((hi - lo).numpy() > 0)


# ---------------------------------------------------------------------------- preprocessing


def _round_to(value: float, multiple: int = 32) -> int:
    return max(_MIN_SIDE, int(round(value / multiple)) * multiple)


def assumed_intrinsics(height: int, width: int) -> np.ndarray:
    """fx, fy, cx, cy of a camera with NYU's field of view, for frames given without intrinsics."""
    return np.array([NYU_FOCAL[0] * width / NYU_SIZE[1], NYU_FOCAL[1] * height / NYU_SIZE[0],
                     width / 2.0, height / 2.0])


def network_size(height: int, width: int, intrinsics: np.ndarray, resize: str) -> tuple[int, int]:
    """Network input (h, w), multiples of 32, for frames (height, width) with intrinsics (4,).

    resize: "focal" sizes the input so the camera's focal lengths there match the training
        focal lengths (the scale of the depth cues the network learnt); "HxW" is fixed.
        "nyu_crop" uses "focal" for its full-frame pass.
    """
    if resize in ("focal", "nyu_crop"):
        fx, fy = intrinsics[:2]
        return _round_to(height * TRAIN_FOCAL_AT_INPUT[1] / fy), _round_to(width * TRAIN_FOCAL_AT_INPUT[0] / fx)
    try:
        h, w = (int(v) for v in resize.lower().split("x"))
    except ValueError:
        raise ValueError(f"resize must be 'focal', 'nyu_crop' or 'HxW', got {resize!r}") from None
    if h % 32 or w % 32 or h < 32 or w < 32:
        raise ValueError(f"resize {resize}: height and width must be positive multiples of 32")
    return h, w


def focal_factor(intrinsics: np.ndarray, box_hw: tuple[int, int], net_hw: tuple[int, int]) -> np.ndarray:
    """Depth correction (B,) for a camera whose focal at the network input differs from training.

    A camera seeing the scene k times larger than the training camera makes the network
    predict k times nearer; multiply by k. Per axis k = f * (net / box) / f_train (box is
    the image region fed to the network); the two axes are combined geometrically.

    intrinsics: (B, 4) in pixels of the frames; box_hw: region size in frame pixels.
    """
    kx = intrinsics[:, 0] * net_hw[1] / box_hw[1] / TRAIN_FOCAL_AT_INPUT[0]
    ky = intrinsics[:, 1] * net_hw[0] / box_hw[0] / TRAIN_FOCAL_AT_INPUT[1]
    return np.sqrt(kx * ky)


def crop_box(height: int, width: int, fraction: float = NYU_CROP_FRACTION) -> tuple[int, int, int, int]:
    """Centred (top, left, h, w) keeping ``fraction`` of each axis, as NYU training did."""
    h, w = int(round(height * fraction)), int(round(width * fraction))
    return (height - h) // 2, (width - w) // 2, h, w


def to_network_input(frames: torch.Tensor, size: tuple[int, int], interpolation: str = "area") -> torch.Tensor:
    """frames (B, H, W, 3) uint8 -> (B, 3, h, w) float RGB in [0, 1] at the network size.

    "area" is antialiased bilinear (what a careful downscale does); "nearest" mimics the
    training pipeline's scipy imresize(..., 'nearest').
    """
    if interpolation not in ("area", "bilinear", "nearest"):
        raise ValueError(f"interpolation must be 'area', 'bilinear' or 'nearest', got {interpolation!r}")
    # (B, 3, H, W) view of NHWC memory: the channels-last layout CPU kernels like best.
    x = frames.permute(0, 3, 1, 2)
    if tuple(x.shape[-2:]) != tuple(size):
        # On CPU, resizing the uint8 image first is ~5x faster than resizing floats (a
        # dedicated uint8 kernel) and differs by at most one grey level.
        if x.device.type != "cpu":
            x = x.float()
        if interpolation == "nearest":
            x = F.interpolate(x, size=size, mode="nearest")
        else:
            x = F.interpolate(x, size=size, mode="bilinear", antialias=interpolation == "area", align_corners=False)
    return x.float().div_(255.0)


def upsample_depth(depth: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """depth (B, h, w) -> (B, H, W), bilinear, staying 0 where the nearest prediction is 0."""
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth
    x = depth[:, None]
    smooth = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
    # Bilinear would smear the ReLU's zeros ("no prediction") into small positive depths.
    valid = F.interpolate((x > 0).float(), size=size, mode="nearest") > 0
    return torch.where(valid, smooth, torch.zeros_like(smooth))[:, 0]


# ---------------------------------------------------------------------------- prior


@dataclass(frozen=True)
class _Plan:
    """Per-call decisions shared by all batches (so every batch has the same feature shape)."""

    net_size: tuple[int, int]
    crop: tuple[int, int, int, int] | None


class FastDepthPrior(DepthPrior):
    """Metric depth from FastDepth, with optional encoder features for MEDeA.

    Args:
        weights: explicit weights location (file, model folder, or folder holding
            ``fastdepth/``); otherwise $RECON_WEIGHTS, then the packaged model.
        resize: network input, see :func:`network_size`. Default "focal": the whole frame at
            the training focal lengths (224x224 for 640x480 at fx=585, 256x256 at fx=525).
            "nyu_crop" runs the NYU crop at 224x224 plus a full-frame "focal" pass that
            fills the borders (2 passes, and less accurate on 7-Scenes and TUM).
        focal_scaling: multiply depth by :func:`focal_factor` (camera vs training focal at
            the network input). Off by default: the network follows apparent size only
            partly. why: docs/decisions.md#the-priors-input-size
        interpolation: input resampling, "area" | "bilinear" | "nearest".
        features: also return encoder features from the same forward pass.
        feature_layer: "stride8" (256 channels before dropping) or "stride4" (120).
        drop_constant: drop feature channels that are provably constant (see kept_channels).
        channels_last: NHWC memory layout (faster depthwise convs on CPU).
        batch_size, device, progress, align_to: see DepthPrior.
    """

    name = "fastdepth"

    def __init__(
        self,
        weights: str | os.PathLike | None = None,
        resize: str = "focal",
        focal_scaling: bool = False,
        interpolation: str = "area",
        features: bool = False,
        feature_layer: str = "stride8",
        drop_constant: bool = True,
        channels_last: bool = True,
        batch_size: int = 8,
        device: str = "cpu",
        progress: bool = True,
        align_to=None,
    ):
        super().__init__(batch_size=batch_size, device=device, progress=progress, align_to=align_to)
        network_size(480, 640, assumed_intrinsics(480, 640), resize)  # validate early
        self.base_net, self.weights_path = load_fastdepth(weights)
        self.net = _on_device(self.base_net, str(torch.device(device)), channels_last)
        self.resize = resize
        self.focal_scaling = focal_scaling
        self.interpolation = interpolation
        self.features = features
        self.feature_layer = feature_layer
        self.tap = feature_tensor(self.base_net, feature_layer)
        self.keep = kept_channels(self.base_net, self.tap) if drop_constant else None
        self.channels_last = channels_last

    def plan(self, frames: np.ndarray, intrinsics: np.ndarray | None) -> _Plan:
        height, width = frames.shape[1:3]
        reference = assumed_intrinsics(height, width) if intrinsics is None else np.median(intrinsics, axis=0)
        crop = crop_box(height, width) if self.resize == "nyu_crop" else None
        return _Plan(net_size=network_size(height, width, reference, self.resize), crop=crop)

    def _run(self, x: torch.Tensor, taps: tuple[str, ...]) -> tuple[torch.Tensor, dict]:
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        out, tapped = self.net(x, taps)
        return out[:, 0], tapped

    @torch.inference_mode()
    def predict_batch(self, frames, intrinsics, indices, plan: _Plan | None = None) -> PriorOutput:
        plan = plan or self.plan(frames, intrinsics)
        height, width = frames.shape[1:3]
        if intrinsics is None:
            intrinsics = np.broadcast_to(assumed_intrinsics(height, width), (len(frames), 4))
        device = torch.device(self.device)
        rgb = torch.from_numpy(np.ascontiguousarray(frames)).to(device)
        taps = (self.tap,) if self.features else ()

        depth, tapped = self._run(to_network_input(rgb, plan.net_size, self.interpolation), taps)
        if self.focal_scaling:
            depth = depth * self._factor(intrinsics, (height, width), plan.net_size, device)
        depth = upsample_depth(depth, (height, width))

        if plan.crop is not None:
            top, left, h, w = plan.crop
            crop_depth, _ = self._run(to_network_input(rgb[:, top : top + h, left : left + w], TRAIN_INPUT,
                                                       self.interpolation), ())
            if self.focal_scaling:
                crop_depth = crop_depth * self._factor(intrinsics, (h, w), TRAIN_INPUT, device)
            depth[:, top : top + h, left : left + w] = upsample_depth(crop_depth, (h, w))

        features = stride = None
        info = {"model": "fastdepth", "weights": str(self.weights_path), "resize": self.resize,
                "network_input": plan.net_size, "focal_scaling": self.focal_scaling,
                "interpolation": self.interpolation}
        if self.features:
            maps = tapped[self.tap]
            if self.keep is not None:
                maps = maps[:, torch.as_tensor(self.keep, device=maps.device)]
            features = maps.contiguous().float().cpu().numpy()
            stride = (height / maps.shape[-2], width / maps.shape[-1])
            info.update(feature_layer=self.feature_layer, feature_tensor=self.tap,
                        feature_channels=int(maps.shape[1]))
        return PriorOutput(depth=depth.float().cpu().numpy(), kind="metric", features=features,
                           feature_stride=stride, info=info)

    @staticmethod
    def _factor(intrinsics, box_hw, net_hw, device) -> torch.Tensor:
        factor = focal_factor(np.asarray(intrinsics, dtype=np.float64), box_hw, net_hw)
        return torch.as_tensor(factor, dtype=torch.float32, device=device)[:, None, None]
