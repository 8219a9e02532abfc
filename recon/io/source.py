"""The frame-source interface and what every source shares.

This module owns :class:`FrameSource` (iterate ``Frame(index, timestamp, rgb)``, plus count,
fps, working size and a description), :class:`FrameBatch`, resizing to a working width and
the selection rule (:class:`Selection`), identical for every source: frames whose timestamp
t (seconds from the first frame) satisfies ``start_time <= t < end_time``, then every
``stride``-th of those from the first, then at most ``max_frames``. ``index`` is the frame's
position in the whole source, never in the selection. Frames are read one at a time; the
sources are in :mod:`recon.io.frames` and :mod:`recon.io.video`.
More: docs/input.md#which-frames
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, NamedTuple

import cv2
import numpy as np

from recon.errors import ReconInputError

MIN_WIDTH = 8


class Frame(NamedTuple):
    """One frame: source index, timestamp in seconds, (H, W, 3) uint8 RGB at working size."""

    index: int
    timestamp: float
    rgb: np.ndarray


@dataclass(frozen=True)
class FrameBatch:
    """All selected frames in memory: indices (N,) int64, timestamps (N,) float64, rgb (N, H, W, 3) uint8."""

    indices: np.ndarray
    timestamps: np.ndarray
    rgb: np.ndarray

    def __len__(self) -> int:
        return len(self.indices)


@dataclass(frozen=True)
class Selection:
    """Which frames to keep (see the module docstring for the rule)."""

    stride: int = 1
    max_frames: int | None = None
    start_time: float | None = None
    end_time: float | None = None

    def describe(self) -> str:
        parts = [f"stride {self.stride}"]
        if self.start_time is not None or self.end_time is not None:
            lo = "start" if self.start_time is None else f"{self.start_time:g} s"
            hi = "end" if self.end_time is None else f"{self.end_time:g} s"
            parts.append(f"time {lo} to {hi}")
        if self.max_frames is not None:
            parts.append(f"max {self.max_frames} frames")
        return ", ".join(parts)

    def apply(self, times: np.ndarray) -> np.ndarray:
        """Source indices (M,) selected among frames with timestamps `times` (N,) seconds from the first."""
        keep = np.ones(len(times), dtype=bool)
        if self.start_time is not None:
            keep &= times >= self.start_time - 1e-6
        if self.end_time is not None:
            keep &= times < self.end_time - 1e-6
        idx = np.flatnonzero(keep)[:: self.stride]
        return idx if self.max_frames is None else idx[: self.max_frames]


def make_selection(stride=1, max_frames=None, start_time=None, end_time=None) -> Selection:
    """A validated Selection; bad values (they come from the command line) give a one-line error."""
    if int(stride) != stride or stride < 1:
        raise ReconInputError(f"stride must be a whole number >= 1, got {stride}")
    if max_frames is not None and (int(max_frames) != max_frames or max_frames < 1):
        raise ReconInputError(f"max_frames must be a whole number >= 1, got {max_frames}")
    for name, value in (("start_time", start_time), ("end_time", end_time)):
        if value is not None and not (np.isfinite(value) and value >= 0):
            raise ReconInputError(f"{name} must be a number of seconds >= 0, got {value}")
    if start_time is not None and end_time is not None and end_time <= start_time:
        raise ReconInputError(f"end_time ({end_time} s) must be after start_time ({start_time} s)")
    return Selection(
        int(stride),
        None if max_frames is None else int(max_frames),
        None if start_time is None else float(start_time),
        None if end_time is None else float(end_time),
    )


# --------------------------------------------------------------------------- resizing


def wxh(shape: tuple[int, int]) -> str:
    """"WxH" text of an (H, W) shape, the order people read image sizes in."""
    return f"{shape[1]}x{shape[0]}"


def size_at_width(height: int, width: int, target_width: int | None, where="") -> tuple[int, int]:
    """(H, W) of a (`height`, `width`) image resized to `target_width` pixels wide, aspect
    kept (height rounded, at least 1); `target_width` None keeps the size."""
    if target_width is None:
        return height, width
    if int(target_width) != target_width or target_width < MIN_WIDTH:
        raise ReconInputError(
            f"{where}: working width must be a whole number >= {MIN_WIDTH}, got {target_width}"
        )
    return max(1, int(round(height * target_width / width))), int(target_width)


def resize_rgb(rgb: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) image resized to `shape` (H', W'); INTER_AREA when shrinking to avoid aliasing."""
    if rgb.shape[:2] == tuple(shape):
        return rgb
    shrink = shape[1] < rgb.shape[1]
    return cv2.resize(rgb, (shape[1], shape[0]), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def resize_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) depth resized to `shape` (H', W') by nearest neighbour: never blends across edges or holes."""
    if depth.shape == tuple(shape):
        return depth
    return cv2.resize(depth, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST_EXACT)


# --------------------------------------------------------------------------- interface


class FrameSource(ABC):
    """A stream of frames: ``for index, timestamp, rgb in source``.

    Properties: ``count`` (selected frames; an estimate for videos, see ``count_is_exact``),
    ``fps``, ``shape`` (H, W) after resizing, ``native_shape`` (H, W) before, ``description``,
    ``intrinsics`` (scaled to ``shape``; None when the source does not know them),
    ``distortion`` (the lens of those intrinsics, OpenCV's k1, k2, p1, p2[, k3]; None when
    the source knows none).

    After :meth:`to_pinhole` every frame (and a dataset's sensor depth) comes resampled into
    the pinhole camera of the same intrinsics, so that every later stage sees a pinhole
    camera; subclasses yield the frames as recorded from ``_frames``.
    """

    kind: str = ""
    path: Path
    native_shape: tuple[int, int]  # (H, W) as decoded
    selection: Selection
    # Set by every subclass's constructor.
    _fps: float
    _shape: tuple[int, int]  # (H, W) at working size
    selected: np.ndarray  # (count,) indices of the selected frames, where known up front
    _lens_maps: tuple[np.ndarray, np.ndarray] | None = None  # set by to_pinhole
    undistorted: dict | None = None  # what to_pinhole did, for the report

    @property
    def fps(self) -> float:
        return self._fps

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the frames at working size."""
        return self._shape

    @property
    def count(self) -> int:
        return len(self.selected)

    @property
    def count_is_exact(self) -> bool:
        return True

    @property
    @abstractmethod
    def description(self) -> str: ...

    @property
    def intrinsics(self) -> tuple[float, float, float, float] | None:
        return None

    @property
    def distortion(self) -> tuple[float, ...] | None:
        return None

    def to_pinhole(self, intrinsics, distortion, known_from: str = "given") -> dict:
        """From now on, resample every frame into the pinhole camera of `intrinsics` (fx, fy,
        cx, cy at working size) whose lens has OpenCV's `distortion` coefficients (known_from:
        where they came from). Returns what report.json says of it, also kept as
        ``undistorted``: the coefficients, their source and the largest shift (pixels) that
        moves a pixel. Pixels the lens did not record come out black (depth 0)."""
        from recon.geometry.camera import largest_lens_shift, undistortion_maps

        self._lens_maps = undistortion_maps(intrinsics, distortion, self.shape)
        self.undistorted = {"distortion": [float(v) for v in distortion], "source": known_from,
                            "max_shift_px": largest_lens_shift(self._lens_maps)}
        return self.undistorted

    def pinhole(self, image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """`image` (H, W[, C]) at working size as the pinhole camera sees it (unchanged when no
        lens is set); nearest: no interpolation (depth, where blending invents surfaces)."""
        if self._lens_maps is None:
            return image
        mode = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(image, *self._lens_maps, mode, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def __iter__(self) -> Iterator[Frame]:
        for frame in self._frames():
            yield frame if self._lens_maps is None else frame._replace(rgb=self.pinhole(frame.rgb))

    @abstractmethod
    def _frames(self) -> Iterator[Frame]:
        """The selected frames at working size, as recorded."""

    def count_at_least(self, n: int) -> int:
        """min(n, number of selected frames) (sources with an exact count need no scan)."""
        return min(n, self.count)

    def read_all(self) -> FrameBatch:
        """Every selected frame stacked in memory (use at working resolution)."""
        indices, times, images = [], [], []
        for frame in self:
            indices.append(frame.index)
            times.append(frame.timestamp)
            images.append(frame.rgb)
        rgb = np.stack(images) if images else np.zeros((0, *self._shape, 3), np.uint8)
        return FrameBatch(np.asarray(indices, np.int64), np.asarray(times, np.float64), rgb)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description}>"

