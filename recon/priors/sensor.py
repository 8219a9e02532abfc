"""Sensor depth as a prior: the depth channel of an RGB-D recording, already loaded as arrays.

Holes stay holes (0); nothing is filled or smoothed, so MEDeA sees only measured depth.
"""

from __future__ import annotations

import numpy as np

from ..errors import ReconInputError
from .base import DepthPrior, PriorOutput
from .resample import resize_nearest


def clean_depth(depth: np.ndarray, scale: float = 1.0, invalid_values=()) -> np.ndarray:
    """depth (..., H, W) raw -> float32 metres with NaN, inf, non-positive and ``invalid_values`` as 0."""
    raw = np.asarray(depth)
    bad = np.zeros(raw.shape, dtype=bool)
    for value in invalid_values:
        bad |= raw == value
    metres = raw.astype(np.float32) * np.float32(scale)
    bad |= ~np.isfinite(metres) | (metres <= 0)
    metres[bad] = 0.0
    return metres


class SensorDepthPrior(DepthPrior):
    """Metric depth from given sensor depth maps.

    Args:
        depth: (N, H', W') raw depth, one map per frame, in any numeric dtype.
        depth_scale: metres per raw unit (1 for metres, 0.001 for millimetres, 1/5000 for TUM).
        invalid_values: raw values meaning "no measurement" besides 0 and NaN (e.g. 65535).
        source: how errors name the source (e.g. the recording's folder).
        files: optional (N,) depth file of each map, named in errors about that frame.
        Maps whose size differs from the frames are resized with nearest neighbours (no
        blending across holes) when the aspect ratios agree.
    """

    name = "sensor"

    def __init__(self, depth, depth_scale: float = 1.0, invalid_values=(), source: str = "sensor depth",
                 files=None, batch_size: int = 64, device: str = "cpu", progress: bool = False):
        super().__init__(batch_size=batch_size, device=device, progress=progress)
        self.depth = depth
        if np.ndim(depth) != 3:
            raise ReconInputError(f"{source}: sensor depth must be (N, H, W), got shape {np.shape(depth)}")
        self.depth_scale = float(depth_scale)
        self.invalid_values = tuple(invalid_values)
        self.source = source
        self.files = None if files is None else [str(f) for f in files]
        if self.files is not None and len(self.files) != len(depth):
            raise ReconInputError(f"{source}: {len(self.files)} depth file names for {len(depth)} depth maps")

    @classmethod
    def from_dataset(cls, dataset, **options) -> "SensorDepthPrior":
        """The depth channel of an opened RGB-D dataset (:mod:`recon.io.datasets`), in metres.

        Errors about a frame name its depth file.
        """
        if not dataset.has_depth:
            raise ReconInputError(f"{dataset.root}: this {dataset.kind} recording has no depth")
        return cls(dataset.load_depth_batch(), source=str(dataset.root), files=dataset.depth_paths, **options)

    def plan(self, frames, intrinsics):
        if len(self.depth) != len(frames):
            raise ReconInputError(f"{self.source}: {len(self.depth)} depth maps for {len(frames)} frames")
        return None

    def _where(self, frame: int) -> str:
        return self.source if self.files is None else self.files[frame]

    def predict_batch(self, frames, intrinsics, indices, plan=None) -> PriorOutput:
        height, width = frames.shape[1:3]
        depth = clean_depth(np.asarray(self.depth[indices.start : indices.stop]), self.depth_scale, self.invalid_values)
        if depth.shape[1:] != (height, width):
            try:
                depth = resize_nearest(depth, (height, width))
            except ValueError as exc:
                raise ReconInputError(f"{self.source}: {exc}") from None
        # A frame without any measurement has nothing for MEDeA to adjust (D = D0 * S stays 0).
        empty = np.flatnonzero(~(depth > 0).any(axis=(1, 2)))
        if empty.size:
            frame = indices.start + int(empty[0])
            raise ReconInputError(f"{self._where(frame)}: sensor depth of frame {frame} has no valid pixel"
                                  " (all zero, NaN or invalid); drop that frame")
        return PriorOutput(depth=depth, kind="metric", info={"model": "sensor", "source": self.source})
