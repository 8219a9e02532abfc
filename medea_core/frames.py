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
        """The warped signal of every frame, a view into `packed`.

        Returns:
            (N, C, H, W) RGB in [0, 1] or features.
        """
        return self.packed[:, :-2]

    @property
    def prior(self) -> torch.Tensor:
        """The prior depth of every frame at this resolution, a view into `packed`.

        Returns:
            (N, H, W) depth in metres, 0 = invalid.
        """
        return self.packed[:, -2]

    @property
    def valid(self) -> torch.Tensor:
        """Where the prior depth at this resolution is valid.

        Returns:
            (N, H, W) bool.
        """
        return self.packed[:, -1] > 0.5

    @property
    def size(self) -> tuple[int, int]:
        """The resolution of this level.

        Returns:
            (H, W) in pixels.
        """
        return tuple(self.packed.shape[-2:])


@dataclass
class FrameData:
    """poses: (N, 4, 4) camera-to-world; image: RGB level; features: feature level or None."""

    poses: torch.Tensor
    image: Level
    features: Level | None

    @property
    def num_frames(self) -> int:
        """The number of frames N.

        Returns:
            N, the first dimension of `poses`.
        """
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
    that holes in sensor depth never blend into their neighbours. At the input's own size
    the depth is returned as float with invalid pixels set to 0.

    Args:
        depth: (N, H, W) depth in metres; <= 0 and non-finite values are invalid.
        size: (h, w) target resolution in pixels.
        min_coverage: fraction of a result pixel's antialiased footprint that must be
            valid for the pixel to be valid.

    Returns:
        depth (N, h, w) in metres with 0 where invalid, and valid (N, h, w) bool.
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
    """Bring the prior, its intrinsics and a signal to one working resolution.

    The maps are resized with antialiased bilinear interpolation, the prior with
    resize_depth, and the intrinsics with scale_intrinsics.

    Args:
        prior: (N, H, W) prior depth in metres, 0 (or NaN) = invalid.
        intrinsics: (N, 4) fx, fy, cx, cy in pixels of the prior's resolution (H, W).
        maps: (N, C, h', w') RGB or features, any resolution covering the same field of view.
        size: (h, w) resolution of the level in pixels.

    Returns:
        Level with packed (N, C + 2, h, w) maps, depth and validity, and intrinsics (N, 4)
        in pixels of (h, w).
    """
    height, width = prior.shape[-2:]
    depth, valid = resize_depth(prior, size)
    scaled = scale_intrinsics(intrinsics, size[1] / width, size[0] / height)
    packed = torch.cat([_resize(maps, size), depth[:, None], valid[:, None].float()], dim=1)
    return Level(packed=packed.contiguous(), intrinsics=scaled)


def most_varying_channels(features: torch.Tensor, count: int) -> torch.Tensor:
    """Indices of the feature channels with the largest variance over all frames and pixels.

    Selecting channels (rather than projecting them) keeps them non-negative, which the
    S-form loss assumes.

    Args:
        features: (N, C, h, w) feature maps.
        count: number of channels to keep.

    Returns:
        (count,) int64 channel indices in their original (ascending) order, on the features'
        device; all C indices when count >= C.
    """
    if count >= features.shape[1]:
        return torch.arange(features.shape[1], device=features.device)
    total = sum(chunk.float().sum(dim=(0, 2, 3)) for chunk in features.split(_CHUNK))
    squares = sum(chunk.float().square().sum(dim=(0, 2, 3)) for chunk in features.split(_CHUNK))
    samples = features.shape[0] * features.shape[2] * features.shape[3]
    variance = squares / samples - (total / samples).square()
    return variance.topk(count).indices.sort().values


def working_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """The resolution at which a (height, width) image is optimised.

    Args:
        height: image height in pixels.
        width: image width in pixels.
        scale: fraction of the input size (e.g. 0.25).

    Returns:
        (h, w) = each side times scale, rounded, at least 1.
    """
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
        device: device the tensors are built on.
        feature_channels: keep this many channels (see most_varying_channels); None: all.

    Returns:
        FrameData with float64 poses (N, 4, 4), the RGB level at working_size of the prior
        and the feature level at the features' own resolution (None without features).
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
