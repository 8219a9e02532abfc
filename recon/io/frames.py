"""Frame sources for image folders and RGB-D dataset folders, and :func:`open_source`,
which opens any input path (video, image folder, dataset) as a frame source.

This module owns :class:`ImageFolderSource` (image files in natural order, checked for
one size), :class:`DatasetSource` (a dataset's frames with its depth, poses and
intrinsics at working size) and the choice of source for a path. The interface and the
selection rule are in :mod:`recon.io.source`, videos in :mod:`recon.io.video`.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from recon.errors import ReconInputError
from recon.geometry.camera import resize_intrinsics
from recon.io.datasets import detect_dataset
from recon.io.datasets.base import RGBDDataset
from recon.io.naming import natural_key
from recon.io.source import Frame, FrameSource, Selection, make_selection, resize_depth, resize_rgb, size_at_width, wxh
from recon.io.video import VideoSource

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
DEFAULT_FOLDER_FPS = 30.0  # assumed frame rate of an image folder (timestamps = index / fps)


# --------------------------------------------------------------------------- image folders


def list_image_files(folder: Path) -> list[Path]:
    """Image files directly in `folder` (hidden files skipped), in natural order."""
    files = [
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    ]
    return sorted(files, key=lambda p: natural_key(p.name))


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _jpeg_shape(f) -> tuple[int, int] | None:
    """(H, W) from a JPEG's start-of-frame marker, reading only the headers before it."""
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
            return h, w
        f.seek(length - 2, 1)


def image_header_shape(path: Path) -> tuple[int, int] | None:
    """(H, W) stored in a PNG/JPEG header without decoding; None for other formats.

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
                is_png = head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
                shape = struct.unpack(">II", head[16:24])[::-1] if is_png else None  # IHDR: width, height
            else:
                shape = _jpeg_shape(f)
    except OSError as exc:
        raise ReconInputError(f"{path}: cannot read image file ({exc.strerror})") from None
    if shape is None:
        raise ReconInputError(f"{path}: cannot read image (not a valid {suffix[1:].upper()} file)")
    return int(shape[0]), int(shape[1])


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file (EXIF orientation applied), or a one-line error."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ReconInputError(f"{path}: cannot read image (unreadable or corrupt file)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _mixed_sizes(path: Path, shape, first: Path, first_shape) -> ReconInputError:
    """The error for an image of `shape` (H, W) in a folder whose first image has `first_shape`."""
    return ReconInputError(
        f"{path}: image is {wxh(shape)} but {first.name} is {wxh(first_shape)} "
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
                f"{self.path}: folder has no images ({', '.join(IMAGE_SUFFIXES)}) "
                "and is not a known RGB-D dataset layout"
            )
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise ReconInputError(f"{self.path}: fps must be > 0, got {fps}")
        self._fps = float(fps) if fps is not None else DEFAULT_FOLDER_FPS
        self._check_header_sizes()
        # Decode the first image: its (EXIF-oriented) size is the reference for all others.
        self.native_shape = read_image(self.files[0]).shape[:2]
        self._shape = size_at_width(*self.native_shape, width, self.path)
        self.selected = selection.apply(np.arange(len(self.files)) / self._fps)

    def _check_header_sizes(self) -> None:
        """Mixed sizes and non-images fail now, from headers alone, not hours into a run."""
        first_shape = None
        for path in self.files:
            shape = image_header_shape(path)
            if shape is None:
                continue
            if first_shape is None:
                first, first_shape = path, shape
            elif shape != first_shape:
                raise _mixed_sizes(path, shape, first, first_shape)

    @property
    def description(self) -> str:
        return (
            f"image folder {self.path} ({len(self.files)} images, {wxh(self.native_shape)}) "
            f"-> {self.count} frames at {wxh(self.shape)}, {self.selection.describe()}"
        )

    def _frames(self) -> Iterator[Frame]:
        for i in self.selected:
            path = self.files[i]
            rgb = read_image(path)
            if rgb.shape[:2] != self.native_shape:
                raise _mixed_sizes(path, rgb.shape[:2], self.files[0], self.native_shape)
            yield Frame(int(i), float(i / self._fps), resize_rgb(rgb, self._shape))


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
        self.native_shape = (dataset.height, dataset.width)
        self._shape = size_at_width(dataset.height, dataset.width, width, self.path)

    @property
    def description(self) -> str:
        ds = self.full
        return (
            f"{ds.kind} dataset {self.path} ({len(ds)} frames, {wxh(ds.shape)}, "
            f"depth {'yes' if ds.has_depth else 'no'}, poses {'yes' if ds.has_poses else 'no'}) "
            f"-> {self.count} frames at {wxh(self.shape)}, {self.selection.describe()}"
        )

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        return resize_intrinsics(self.full.intrinsics, self.native_shape, self.shape)

    @property
    def distortion(self) -> tuple[float, ...] | None:
        """The published lens of the dataset's calibration (None when it has none or it is 0)."""
        from recon.geometry.camera import is_pinhole

        lens = self.full.distortion
        return None if is_pinhole(lens) else tuple(float(v) for v in lens)

    def intrinsics_of(self, k: int) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the k-th selected frame at working size."""
        return resize_intrinsics(self.dataset.intrinsics_of(k), self.native_shape, self.shape)

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
        """Sensor depth (H, W) float32 metres of the k-th selected frame at working size (in
        the pinhole camera after ``to_pinhole``)."""
        depth = self.dataset.depth(k)
        return None if depth is None else self.pinhole(resize_depth(depth, self._shape), nearest=True)

    def load_depth(self) -> np.ndarray | None:
        """(M, H, W) float32 sensor depth of all selected frames at working size, or None."""
        if not self.has_depth:
            return None
        out = np.empty((self.count, *self._shape), np.float32)
        for k in range(self.count):
            out[k] = self.depth(k)
        return out

    def _frames(self) -> Iterator[Frame]:
        for k, i in enumerate(self.selected):
            yield Frame(int(i), float(self.timestamps[k]), resize_rgb(self.dataset.rgb(k), self._shape))


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
        stride, max_frames, start_time, end_time: frame selection (:mod:`recon.io.source`).
        width: working width in pixels (aspect kept); None keeps the native size.
        min_frames: fewest selected frames the caller can work with (e.g. 2 for a
            multi-view method); fewer gives a one-line ReconInputError.
        fps: frame rate assumed for an image folder (default 30); ignored otherwise.

    Raises:
        ReconInputError: missing path, unreadable/not-a-video file, no frames, fewer than
            `min_frames` frames, empty folder, mixed image sizes, unreadable image.
    """
    path = Path(path)
    selection = make_selection(stride, max_frames, start_time, end_time)
    if not path.exists():
        raise ReconInputError(f"{path}: no such file or folder")
    if path.is_dir():
        dataset = detect_dataset(path)
        source: FrameSource = (
            DatasetSource(dataset, selection, width) if dataset is not None
            else ImageFolderSource(path, selection, width, fps)
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
    "DEFAULT_FOLDER_FPS",
    "DatasetSource",
    "IMAGE_SUFFIXES",
    "ImageFolderSource",
    "image_header_shape",
    "list_image_files",
    "open_source",
    "read_image",
]
