"""Frame sources: one streaming interface over videos, image folders and RGB-D datasets.

This module owns the :class:`FrameSource` interface (iterate ``Frame(index, timestamp,
rgb)``, plus count, fps, working size and a description), the image-folder and dataset
sources, the shared selection rule (time range, stride, max frames), resizing to a working
width with the matching intrinsics scaling, and :func:`open_source`, which picks the right
source for a path. Videos are handled in :mod:`recon.io.video`.

Selection rule, identical for every source: keep frames whose timestamp t, in seconds from
the source's first frame, satisfies ``start_time <= t < end_time``; then every ``stride``-th
of those, starting with the first; then at most ``max_frames``. The yielded ``index`` is the
frame's position in the whole source (video frame number, image number in natural order,
dataset frame number), never its position in the selection.

Frames are read one at a time, so iterating a long video or a big folder needs memory for
one frame only; :meth:`FrameSource.read_all` stacks everything for callers that want arrays
(fine at working resolution: 1000 frames at 320x240 are 230 MB).
"""

from __future__ import annotations

import re
import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import cv2
import numpy as np

from recon.errors import ReconInputError
from recon.io.datasets import detect_dataset
from recon.io.datasets.base import RGBDDataset

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
DEFAULT_FOLDER_FPS = 30.0  # assumed frame rate of an image folder (timestamps = index / fps)
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


def working_size(native: tuple[int, int], width: int | None, where="") -> tuple[int, int]:
    """(width, height) after resizing `native` (w, h) to `width`, keeping the aspect ratio."""
    if width is None:
        return native
    if int(width) != width or width < MIN_WIDTH:
        raise ReconInputError(f"{where}: working width must be a whole number >= {MIN_WIDTH}, got {width}")
    w, h = native
    return int(width), max(1, int(round(h * width / w)))


def resize_rgb(rgb: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) image resized to `size` (w, h); INTER_AREA when shrinking to avoid aliasing."""
    if (rgb.shape[1], rgb.shape[0]) == tuple(size):
        return rgb
    shrink = size[0] < rgb.shape[1]
    return cv2.resize(rgb, tuple(size), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def resize_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) depth resized to `size` (w, h) by nearest neighbour: never blends across edges or holes."""
    if (depth.shape[1], depth.shape[0]) == tuple(size):
        return depth
    return cv2.resize(depth, tuple(size), interpolation=cv2.INTER_NEAREST_EXACT)


def scale_intrinsics(intrinsics, sx: float, sy: float | None = None) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) for an image scaled by `sx` horizontally and `sy` (default sx) vertically.

    Pixel centres sit at integer coordinates, so the scaling is about the image corner
    (-0.5, -0.5): cx' = (cx + 0.5) * sx - 0.5, and likewise for cy.
    """
    sy = sx if sy is None else sy
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)


def resize_intrinsics(intrinsics, native: tuple[int, int], size: tuple[int, int]) -> tuple[float, float, float, float]:
    """Intrinsics of an image of `native` (w, h) after resizing to `size` (w, h)."""
    return scale_intrinsics(intrinsics, size[0] / native[0], size[1] / native[1])


# --------------------------------------------------------------------------- interface


class FrameSource(ABC):
    """A stream of frames: ``for index, timestamp, rgb in source``.

    Properties: ``count`` (selected frames; an estimate for videos, see ``count_is_exact``),
    ``fps``, ``size`` (width, height) after resizing, ``native_size`` before, ``description``,
    ``intrinsics`` (scaled to ``size``; None when the source does not know them).
    """

    kind: str = ""
    path: Path
    native_size: tuple[int, int]
    selection: Selection
    # Set by every subclass's constructor.
    _fps: float
    _size: tuple[int, int]
    selected: np.ndarray  # (count,) indices of the selected frames, where known up front

    @property
    def fps(self) -> float:
        return self._fps

    @property
    def size(self) -> tuple[int, int]:
        return self._size

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

    @abstractmethod
    def __iter__(self) -> Iterator[Frame]: ...

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
        w, h = self.size
        rgb = np.stack(images) if images else np.zeros((0, h, w, 3), np.uint8)
        return FrameBatch(np.asarray(indices, np.int64), np.asarray(times, np.float64), rgb)

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description}>"


# --------------------------------------------------------------------------- image folders


def natural_key(name: str) -> list:
    """Sort key that orders 'frame2' before 'frame10' (digit runs compare as numbers)."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name)]


def list_image_files(folder: Path) -> list[Path]:
    """Image files directly in `folder` (hidden files skipped), in natural order."""
    files = [
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_size(f) -> tuple[int, int] | None:
    """(w, h) from a JPEG's start-of-frame marker, reading only the headers before it."""
    if f.read(2) != b"\xff\xd8":
        return None
    while True:
        byte = f.read(1)
        while byte == b"\xff":  # fill bytes before a marker
            byte = f.read(1)
        if not byte:
            return None
        marker = byte[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:
            continue  # markers without a length
        length_bytes = f.read(2)
        if len(length_bytes) < 2:
            return None
        (length,) = struct.unpack(">H", length_bytes)
        if marker in _JPEG_SOF:
            data = f.read(5)
            if len(data) < 5:
                return None
            h, w = struct.unpack(">HH", data[1:5])
            return w, h
        f.seek(length - 2, 1)


def image_header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) stored in a PNG/JPEG header without decoding; None for other formats.

    Raises ReconInputError when a .png/.jpg file does not carry a valid header. The size is
    the stored one, before any EXIF rotation (decoding checks the oriented size again).
    """
    suffix = path.suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        return None
    try:
        with open(path, "rb") as f:
            if suffix == ".png":
                head = f.read(24)
                size = struct.unpack(">II", head[16:24]) if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" else None
            else:
                size = _jpeg_size(f)
    except OSError as exc:
        raise ReconInputError(f"{path}: cannot read image file ({exc.strerror})") from None
    if size is None:
        raise ReconInputError(f"{path}: cannot read image (not a valid {suffix[1:].upper()} file)")
    return int(size[0]), int(size[1])


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file (EXIF orientation applied), or a one-line error."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ReconInputError(f"{path}: cannot read image (unreadable or corrupt file)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _mixed_sizes(path: Path, size, first: Path, first_size) -> ReconInputError:
    return ReconInputError(
        f"{path}: image is {size[0]}x{size[1]} but {first.name} is {first_size[0]}x{first_size[1]} "
        "(all images of a folder must have the same size)"
    )


class ImageFolderSource(FrameSource):
    """Image files of one folder in natural order; timestamps = index / fps (fps assumed)."""

    kind = "images"

    def __init__(self, folder, selection: Selection = Selection(), width: int | None = None, fps: float | None = None):
        self.path = Path(folder)
        self.selection = selection
        self.files = list_image_files(self.path)
        if not self.files:
            raise ReconInputError(
                f"{self.path}: folder has no images ({', '.join(IMAGE_SUFFIXES)}) and is not a known RGB-D dataset layout"
            )
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise ReconInputError(f"{self.path}: fps must be > 0, got {fps}")
        self._fps = float(fps) if fps is not None else DEFAULT_FOLDER_FPS
        self._check_header_sizes()
        # Decode the first image: its (EXIF-oriented) size is the reference for all others.
        self.native_size = tuple(read_image(self.files[0]).shape[1::-1])
        self._size = working_size(self.native_size, width, self.path)
        self.selected = selection.apply(np.arange(len(self.files)) / self._fps)

    def _check_header_sizes(self) -> None:
        """Mixed sizes and non-images fail now, from headers alone, not hours into a run."""
        first_size = None
        for path in self.files:
            size = image_header_size(path)
            if size is None:
                continue
            if first_size is None:
                first, first_size = path, size
            elif size != first_size:
                raise _mixed_sizes(path, size, first, first_size)

    @property
    def description(self) -> str:
        return (
            f"image folder {self.path} ({len(self.files)} images, {self.native_size[0]}x{self.native_size[1]}) "
            f"-> {self.count} frames at {self.size[0]}x{self.size[1]}, {self.selection.describe()}"
        )

    def __iter__(self) -> Iterator[Frame]:
        for i in self.selected:
            path = self.files[i]
            rgb = read_image(path)
            size = (rgb.shape[1], rgb.shape[0])
            if size != self.native_size:
                raise _mixed_sizes(path, size, self.files[0], self.native_size)
            yield Frame(int(i), float(i / self._fps), resize_rgb(rgb, self._size))


# --------------------------------------------------------------------------- datasets


def _dataset_fps(dataset: RGBDDataset) -> tuple[float, np.ndarray]:
    """(fps, timestamps (N,) seconds): the dataset's own timestamps when it has them."""
    if dataset.timestamps is not None and len(dataset) > 1:
        steps = np.diff(dataset.timestamps)
        steps = steps[steps > 0]
        if steps.size:
            return float(1.0 / np.median(steps)), np.asarray(dataset.timestamps, np.float64)
    # 7-Scenes, ScanNet and Redwood record at 30 Hz and store no timestamps.
    return 30.0, np.arange(len(dataset), dtype=np.float64) / 30.0


class DatasetSource(FrameSource):
    """Frames of an RGB-D dataset folder, with its sensor depth, poses and intrinsics.

    Iteration yields ``Frame(dataset index, timestamp, rgb)``: timestamps are the dataset's
    own (e.g. TUM's Unix times, so trajectories compare with its ground truth), or
    index / 30 when it has none; the time range counts from the first frame.

    For the k-th selected frame (k = position in the iteration): ``depth(k)`` (H, W)
    metres at working size, ``poses[k]`` camera-to-world (NaN when invalid, see
    ``pose_valid``), ``intrinsics_of(k)``. ``dataset`` is the selected subset at native size.
    """

    kind = "dataset"

    def __init__(self, dataset: RGBDDataset, selection: Selection = Selection(), width: int | None = None):
        self.path = Path(dataset.root)
        self.selection = selection
        self.full = dataset
        self._fps, times = _dataset_fps(dataset)
        self.selected = selection.apply(times - times[0]) if len(dataset) else np.zeros(0, np.int64)
        self.timestamps = times[self.selected]
        self.dataset = dataset.subset(self.selected)
        self.native_size = (dataset.width, dataset.height)
        self._size = working_size(self.native_size, width, self.path)

    @property
    def description(self) -> str:
        ds = self.full
        return (
            f"{ds.kind} dataset {self.path} ({len(ds)} frames, {ds.width}x{ds.height}, "
            f"depth {'yes' if ds.has_depth else 'no'}, poses {'yes' if ds.has_poses else 'no'}) "
            f"-> {self.count} frames at {self.size[0]}x{self.size[1]}, {self.selection.describe()}"
        )

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        return resize_intrinsics(self.full.intrinsics, self.native_size, self._size)

    def intrinsics_of(self, k: int) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the k-th selected frame at working size."""
        return resize_intrinsics(self.dataset.intrinsics_of(k), self.native_size, self._size)

    @property
    def has_depth(self) -> bool:
        return self.full.has_depth

    @property
    def poses(self) -> np.ndarray | None:
        """(M, 4, 4) camera-to-world poses of the selected frames, or None."""
        return self.dataset.poses

    @property
    def pose_valid(self) -> np.ndarray | None:
        return self.dataset.pose_valid

    def depth(self, k: int) -> np.ndarray | None:
        """Sensor depth (H, W) float32 metres of the k-th selected frame at working size."""
        depth = self.dataset.depth(k)
        return None if depth is None else resize_depth(depth, self._size)

    def load_depth(self) -> np.ndarray | None:
        """(M, H, W) float32 sensor depth of all selected frames at working size, or None."""
        if not self.has_depth:
            return None
        w, h = self._size
        out = np.empty((self.count, h, w), np.float32)
        for k in range(self.count):
            out[k] = self.depth(k)
        return out

    def __iter__(self) -> Iterator[Frame]:
        for k, i in enumerate(self.selected):
            yield Frame(int(i), float(self.timestamps[k]), resize_rgb(self.dataset.rgb(k), self._size))


# --------------------------------------------------------------------------- entry point


def open_source(
    path,
    stride: int = 1,
    max_frames: int | None = None,
    start_time: float | None = None,
    end_time: float | None = None,
    width: int | None = None,
    min_frames: int = 1,
    fps: float | None = None,
) -> FrameSource:
    """Open a video file, an image folder or an RGB-D dataset folder as a FrameSource.

    Args:
        path: a video file (anything OpenCV decodes: mp4, mov, avi, mkv, ...), a folder of
            images (natural order), or a dataset folder recognised by
            :func:`recon.io.datasets.detect_dataset` (TUM, 7-Scenes, ScanNet, ...).
        stride, max_frames, start_time, end_time: frame selection (module docstring).
        width: working width in pixels (aspect kept); None keeps the native size.
        min_frames: fewest selected frames the caller can work with (e.g. 2 for a
            multi-view method); fewer gives a one-line ReconInputError.
        fps: frame rate assumed for an image folder (default 30); ignored otherwise.

    Raises:
        ReconInputError: missing path, unreadable/not-a-video file, no frames, fewer than
            `min_frames` frames, empty folder, mixed image sizes, unreadable image.
    """
    from .video import VideoSource  # video.py builds on this module

    path = Path(path)
    selection = make_selection(stride, max_frames, start_time, end_time)
    if not path.exists():
        raise ReconInputError(f"{path}: no such file or folder")
    if path.is_dir():
        dataset = detect_dataset(path)
        source: FrameSource = (
            DatasetSource(dataset, selection, width) if dataset is not None else ImageFolderSource(path, selection, width, fps)
        )
    elif path.suffix.lower() in IMAGE_SUFFIXES:
        raise ReconInputError(f"{path}: a single image; give a video file or a folder of images")
    else:
        source = VideoSource(path, selection, width)
    found = source.count_at_least(max(1, int(min_frames)))
    if found == 0:
        raise ReconInputError(f"{path}: no frames selected ({selection.describe()})")
    if found < min_frames:
        raise ReconInputError(
            f"{path}: needs at least {min_frames} frames, got {found} ({selection.describe()})"
        )
    return source


__all__ = [
    "DatasetSource",
    "Frame",
    "FrameBatch",
    "FrameSource",
    "IMAGE_SUFFIXES",
    "ImageFolderSource",
    "Selection",
    "image_header_size",
    "list_image_files",
    "make_selection",
    "natural_key",
    "open_source",
    "resize_depth",
    "resize_intrinsics",
    "resize_rgb",
    "scale_intrinsics",
    "working_size",
]
