"""Per-frame tensors at the resolutions MEDeA optimises on.

The photometric and depth terms work at `image_scale` of the prior's size (1/4 in the
paper); the feature term works at the features' own resolution, so many-channel
features are never upsampled to the image grid. Everything here is computed once
before optimisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .geometry import scale_intrinsics

# Frames are resized in chunks so that temporaries stay small for long sequences.
_CHUNK = 64


@dataclass
class Level:
    """All frames at one resolution.

    packed: (N, C + 2, H, W) the signal warped between views (RGB or features, C
        channels), then the prior depth D0 (0 where invalid), then its validity (0/1),
        stored together so one grid_sample fetches all three from frame j.
    intrinsics: (N, 4) fx, fy, cx, cy at this resolution.
    """

    packed: torch.Tensor
    intrinsics: torch.Tensor

    @property
    def maps(self) -> torch.Tensor:
        """(N, C, H, W)."""
        return self.packed[:, :-2]

    @property
    def prior(self) -> torch.Tensor:
        """(N, H, W)."""
        return self.packed[:, -2]

    @property
    def valid(self) -> torch.Tensor:
        """(N, H, W) bool."""
        return self.packed[:, -1] > 0.5

    @property
    def size(self) -> tuple[int, int]:
        return tuple(self.packed.shape[-2:])


@dataclass
class FrameData:
    """poses: (N, 4, 4) camera-to-world; image: RGB level; features: feature level or None."""

    poses: torch.Tensor
    image: Level
    features: Level | None

    @property
    def num_frames(self) -> int:
        return self.poses.shape[0]


def _resize(maps: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Antialiased resize of (N, C, H, W) maps, chunked over frames."""
    if tuple(maps.shape[-2:]) == tuple(size):
        return maps.float()
    out = [
        F.interpolate(chunk.float(), size=size, mode="bilinear", antialias=True, align_corners=False)
        for chunk in maps.split(_CHUNK)
    ]
    return torch.cat(out)


def resize_depth(depth: torch.Tensor, size: tuple[int, int], min_coverage: float = 0.999):
    """Resize depth (N, H, W) by averaging valid pixels only.

    A pixel of the result is valid only where (almost) its whole footprint was valid, so
    that holes in sensor depth never blend into their neighbours.

    Returns:
        depth (N, h, w) with 0 where invalid, and valid (N, h, w) bool.
    """
    valid = (depth > 0) & torch.isfinite(depth)
    depth = torch.where(valid, depth, torch.zeros_like(depth))
    if tuple(depth.shape[-2:]) == tuple(size):
        return depth.float(), valid
    total = _resize((depth * valid)[:, None], size)[:, 0]
    coverage = _resize(valid[:, None].float(), size)[:, 0]
    small_valid = coverage >= min_coverage
    small = torch.where(small_valid, total / coverage.clamp(min=1e-6), torch.zeros_like(total))
    return small, small_valid


def make_level(
    prior: torch.Tensor, intrinsics: torch.Tensor, maps: torch.Tensor, size: tuple[int, int]
) -> Level:
    """Bring prior (N, H, W), intrinsics (N, 4) of that prior, and maps (N, C, h', w') to size."""
    height, width = prior.shape[-2:]
    depth, valid = resize_depth(prior, size)
    scaled = scale_intrinsics(intrinsics, size[1] / width, size[0] / height)
    packed = torch.cat([_resize(maps, size), depth[:, None], valid[:, None].float()], dim=1)
    return Level(packed=packed.contiguous(), intrinsics=scaled)


def most_varying_channels(features: torch.Tensor, count: int) -> torch.Tensor:
    """Indices (count,) of the channels of features (N, C, h, w) with the largest variance
    over all frames and pixels, in their original order. Selecting channels (rather than
    projecting them) keeps them non-negative, which the S-form loss assumes."""
    if count >= features.shape[1]:
        return torch.arange(features.shape[1], device=features.device)
    total = sum(chunk.float().sum(dim=(0, 2, 3)) for chunk in features.split(_CHUNK))
    squares = sum(chunk.float().square().sum(dim=(0, 2, 3)) for chunk in features.split(_CHUNK))
    samples = features.shape[0] * features.shape[2] * features.shape[3]
    variance = squares / samples - (total / samples).square()
    return variance.topk(count).indices.sort().values


def working_size(height: int, width: int, scale: float) -> tuple[int, int]:
    return max(1, round(height * scale)), max(1, round(width * scale))


def prepare_frames(
    images: torch.Tensor,
    prior: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    features: torch.Tensor | None,
    image_scale: float,
    device: torch.device | str,
    feature_channels: int | None = None,
) -> FrameData:
    """Build the optimisation tensors on `device`.

    Args:
        images: (N, 3, H', W') RGB in [0, 1], any resolution with the prior's aspect.
        prior: (N, H, W) prior depth in metres, 0 (or NaN) where invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (N, 4) or (4,) fx, fy, cx, cy in pixels of the prior's resolution.
        features: (N, C, h, w) or None, covering the same field of view.
        image_scale: working resolution relative to the prior (0.25 in the paper).
        feature_channels: keep this many channels (see most_varying_channels); None: all.
    """
    num = prior.shape[0]
    intrinsics = intrinsics.to(device=device, dtype=torch.float32)
    if intrinsics.dim() == 1:
        intrinsics = intrinsics.expand(num, 4)
    prior = prior.to(device)
    size = working_size(*prior.shape[-2:], image_scale)
    image = make_level(prior, intrinsics, images.to(device), size)
    feature_level = None
    if features is not None:
        if feature_channels is not None:
            features = features[:, most_varying_channels(features, feature_channels).to(features.device)]
        feature_level = make_level(prior, intrinsics, features.to(device), tuple(features.shape[-2:]))
    return FrameData(poses=poses.to(device=device, dtype=torch.float64), image=image, features=feature_level)
