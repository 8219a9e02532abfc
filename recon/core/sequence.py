"""The sequence bundle: the frames of a run and everything known per frame, kept in step.

Stages hand one :class:`Sequence` to the next instead of parallel arrays, so that leaving
frames out (``take``), resampling them into the pinhole camera (``undistort``) or to one
instant per frame (``unroll``, a rolling shutter) changes every per-frame array at once;
a window of a streamed run is a ``Sequence`` too, cut with ``take``.
Conventions (README): rgb (N, H, W, 3) uint8; depth (N, H, W) metres, 0 = invalid;
intrinsics (fx, fy, cx, cy) in pixels of ``rgb``; poses (N, 4, 4) camera-to-world, OpenCV
axes; features (N, C, h, w) covering the whole frame at a lower resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..geometry import rolling_shutter as rs
from ..geometry.lens import undistort_features, undistort_images


@dataclass(frozen=True)
class Sequence:
    """Selected frames with their names, camera, prior depth, features and poses.

    indices (N,) int64: frame numbers in the input; timestamps (N,) float64 seconds;
    rgb (N, H, W, 3) uint8; names: N per-frame names (depth file names, depth-folder
    matching); intrinsics: (fx, fy, cx, cy) or None while unknown; prior_depth (N, H, W)
    metres, features (N, C, h, w) and poses (N, 4, 4) camera-to-world, each None until the
    stage that makes it has run.
    """

    indices: np.ndarray
    timestamps: np.ndarray
    rgb: np.ndarray
    names: list[str]
    intrinsics: tuple[float, float, float, float] | None = None
    prior_depth: np.ndarray | None = None
    features: np.ndarray | None = None
    poses: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.indices)
        for label, value in self._per_frame().items():
            if value is not None and len(value) != n:
                raise ValueError(f"sequence of {n} frames got {len(value)} {label}")

    def _per_frame(self) -> dict:
        return {"timestamps": self.timestamps, "rgb": self.rgb, "names": self.names,
                "prior_depth": self.prior_depth, "features": self.features, "poses": self.poses}

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the frames."""
        return tuple(self.rgb.shape[1:3])

    def with_(self, **fields) -> Sequence:
        """A copy with some fields replaced (checked like a new one)."""
        return replace(self, **fields)

    def take(self, keep) -> Sequence:
        """The frames at positions ``keep`` (indices or a boolean mask), every array alike."""
        keep = np.flatnonzero(keep) if np.asarray(keep).dtype == bool else np.asarray(keep, dtype=np.int64)
        picked = {label: None if value is None else
                  ([value[k] for k in keep] if isinstance(value, list) else value[keep])
                  for label, value in self._per_frame().items()}
        return replace(self, indices=self.indices[keep], **picked)

    @staticmethod
    def concatenate(parts: list[Sequence]) -> Sequence:
        """The frames of ``parts`` one after another (the first part's camera); a field is
        None where the first part's is."""
        first = parts[0]
        joined = {label: None if value is None else
                  (sum((getattr(p, label) for p in parts), []) if isinstance(value, list)
                   else np.concatenate([getattr(p, label) for p in parts]))
                  for label, value in first._per_frame().items()}
        return replace(first, indices=np.concatenate([p.indices for p in parts]), **joined)

    def undistort(self, k1: float) -> Sequence:
        """Frames, prior depth and features resampled into the pinhole camera of a lens with
        radial term ``k1`` (recon.geometry.lens); the intrinsics are the pinhole camera's already.
        Depth is resampled without interpolation (mixing across edges invents surfaces)."""
        if self.intrinsics is None:
            raise ValueError("undistorting needs the intrinsics")
        return replace(
            self,
            rgb=undistort_images(self.rgb, self.intrinsics, k1),
            prior_depth=None if self.prior_depth is None else
            undistort_images(self.prior_depth, self.intrinsics, k1, nearest=True),
            features=None if self.features is None else
            undistort_features(self.features, self.intrinsics, self.size, k1),
        )

    def unroll(self, omega: np.ndarray, readout: float) -> tuple[Sequence, np.ndarray]:
        """Frames, prior depth and features of a rolling-shutter camera resampled to each
        frame's timestamp (recon.geometry.rolling_shutter), given the body angular velocity omega
        (N, 3) rad/s and the readout time in seconds. Frames the shutter bends by less than
        rolling_shutter.MIN_SHIFT_PX stay as they are. Returns the sequence and the largest
        shift of each frame (pixels)."""
        if self.intrinsics is None:
            raise ValueError("unrolling needs the intrinsics")
        rgb, prior, features = self.rgb.copy(), None if self.prior_depth is None else self.prior_depth.copy(), (
            None if self.features is None else self.features.copy())
        shifts = np.zeros(len(self))
        for k in range(len(self)):
            pos = rs.recorded_position(omega[k], self.intrinsics, self.size, readout)
            shifts[k] = float(rs.largest_shift(pos[None])[0])
            if shifts[k] < rs.MIN_SHIFT_PX:
                continue
            rgb[k] = rs.unroll_images(self.rgb[k:k + 1], pos[None])[0]
            if prior is not None:
                prior[k] = rs.unroll_images(self.prior_depth[k:k + 1], pos[None], nearest=True)[0]
            if features is not None:
                features[k] = rs.unroll_features(self.features[k:k + 1], pos[None])[0]
        return replace(self, rgb=rgb, prior_depth=prior, features=features), shifts


__all__ = ["Sequence"]
