"""The depth-prior interface shared by every prior (the factory is :mod:`.registry`).

A prior maps RGB frames ``(N, H, W, 3) uint8`` (and optionally their intrinsics
``fx, fy, cx, cy``) to a :class:`PriorOutput`: per-frame depth ``(N, H, W)`` at the input
resolution, optional dense encoder features, and what kind of depth it is. This module
owns that contract (batching, progress bar, input checks, alignment of affine-invariant
output to a metric reference); each prior module owns only its own ``predict_batch``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace

import numpy as np
from tqdm.auto import tqdm

PRIOR_KINDS = ("metric", "up_to_scale", "affine_disparity")


@dataclass
class PriorOutput:
    """What a prior produced for N frames.

    depth: (N, H, W) float32 at the input frame resolution; 0 marks invalid pixels. In
        metres for kind "metric"; metres up to one unknown scale per sequence for
        "up_to_scale"; for "affine_disparity" it holds the affine-invariant *disparity*
        (larger = nearer, unknown per-frame scale and shift), to be turned into depth by
        :func:`recon.priors.align.align_affine_disparity`.
    kind: one of PRIOR_KINDS.
    features: optional (N, C, h, w) float32 dense encoder features covering the whole frame.
    feature_stride: (rows, cols) input-image pixels per feature pixel, when features are set.
    info: what was done (model, preprocessing, feature layer, alignment reference, ...).
    """

    depth: np.ndarray
    kind: str
    features: np.ndarray | None = None
    feature_stride: tuple[float, float] | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in PRIOR_KINDS:
            raise ValueError(f"prior kind {self.kind!r} is not one of {PRIOR_KINDS}")
        if self.depth.ndim != 3:
            raise ValueError(f"prior depth must be (N, H, W), got {self.depth.shape}")
        if self.features is not None and (self.features.ndim != 4 or len(self.features) != len(self.depth)):
            raise ValueError(f"prior features must be (N, C, h, w) for N={len(self.depth)}, got {self.features.shape}")


def check_frames(frames) -> np.ndarray:
    """frames: (N, H, W, 3) uint8 RGB (or one (H, W, 3) frame) -> (N, H, W, 3) uint8."""
    frames = np.asarray(frames)
    if frames.ndim == 3:
        frames = frames[None]
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames must be (N, H, W, 3) RGB, got shape {frames.shape}")
    if frames.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 RGB, got {frames.dtype}")
    return frames


def check_intrinsics(intrinsics, count: int) -> np.ndarray | None:
    """(4,) or (N, 4) fx, fy, cx, cy -> (N, 4) float64, or None."""
    if intrinsics is None:
        return None
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    if intrinsics.shape == (4,):
        intrinsics = np.broadcast_to(intrinsics, (count, 4))
    if intrinsics.shape != (count, 4):
        raise ValueError(f"intrinsics must be (4,) or ({count}, 4), got {intrinsics.shape}")
    return intrinsics


def concat_outputs(parts: list[PriorOutput]) -> PriorOutput:
    """Join per-batch outputs along frames (info and stride come from the first batch)."""
    first = parts[0]
    features = None
    if first.features is not None:
        features = np.concatenate([p.features for p in parts])
    return PriorOutput(
        depth=np.concatenate([p.depth for p in parts]),
        kind=first.kind,
        features=features,
        feature_stride=first.feature_stride,
        info=dict(first.info),
    )


class DepthPrior(ABC):
    """Base class: batching, device, progress bar and optional metric alignment.

    Args:
        batch_size: frames per forward pass.
        device: "cpu" or "cuda" (priors without a network ignore it).
        progress: show a tqdm bar.
        align_to: for priors whose output kind is "affine_disparity": a metric reference
            to fit each frame's scale and shift against, either a DepthPrior run on the same
            frames (e.g. FastDepth) or an (N, H, W) array of sparse/dense metric depth (0 =
            none). The result is then kind "metric" with ``info["aligned_to"]`` saying which.
    """

    name = "prior"

    def __init__(self, batch_size: int = 8, device: str = "cpu", progress: bool = True, align_to=None):
        if batch_size < 1:
            raise ValueError("batch_size must be at least 1")
        self.batch_size = int(batch_size)
        self.device = device
        self.progress = progress
        self.align_to = align_to

    def plan(self, frames: np.ndarray, intrinsics: np.ndarray | None):
        """Decisions made once per call from all frames and passed to every batch (default: None)."""
        return None

    @abstractmethod
    def predict_batch(self, frames: np.ndarray, intrinsics: np.ndarray | None, indices: range,
                      plan=None) -> PriorOutput:
        """frames (B, H, W, 3) uint8, intrinsics (B, 4) or None, indices of these frames in the
        call, and the call's plan."""

    def finalize(self, output: PriorOutput) -> PriorOutput:
        """Whole-sequence post-processing after all batches (default: none)."""
        return output

    def __call__(self, frames, intrinsics=None) -> PriorOutput:
        """Predict for all frames.

        Args:
            frames: (N, H, W, 3) uint8 RGB.
            intrinsics: optional (4,) or (N, 4) fx, fy, cx, cy in pixels of the frames.
        """
        frames = check_frames(frames)
        count = len(frames)
        intrinsics = check_intrinsics(intrinsics, count)
        plan = self.plan(frames, intrinsics)
        parts = []
        with tqdm(total=count, desc=f"depth prior ({self.name})", unit="frame", disable=not self.progress,
                  leave=False) as bar:
            for start in range(0, count, self.batch_size):
                stop = min(start + self.batch_size, count)
                batch_intrinsics = None if intrinsics is None else intrinsics[start:stop]
                parts.append(self.predict_batch(frames[start:stop], batch_intrinsics, range(start, stop), plan))
                bar.update(stop - start)
        output = self.finalize(concat_outputs(parts))
        if output.kind == "affine_disparity" and self.align_to is not None:
            output = self._align(output, frames, intrinsics)
        return output

    def _align(self, output: PriorOutput, frames: np.ndarray, intrinsics) -> PriorOutput:
        from .align import align_affine_disparity

        if isinstance(self.align_to, DepthPrior):
            reference = self.align_to(frames, intrinsics)
            if reference.kind != "metric":
                raise ValueError(f"alignment reference {self.align_to.name} is {reference.kind}, not metric")
            reference_depth, source = reference.depth, f"prior:{self.align_to.name}"
        else:
            reference_depth, source = np.asarray(self.align_to, dtype=np.float32), "given reference depth"
            if reference_depth.shape != output.depth.shape:
                raise ValueError(
                    f"alignment reference depth {reference_depth.shape} does not match the frames {output.depth.shape}"
                )
        depth = align_affine_disparity(output.depth, reference_depth)
        return replace(output, depth=depth, kind="metric", info={**output.info, "aligned_to": source})
