"""Video files: a streaming frame source (anything OpenCV's FFmpeg backend decodes) and
writing frames to an mp4.

This module owns :class:`VideoSource`: opening a video with OpenCV, honouring the rotation
stored in its metadata (phones record portrait video as landscape pixels plus a display
matrix), frame timestamps, the selection of :class:`recon.io.source.Selection` and the frame
count estimate. Frames are decoded one at a time, so a long video never sits in memory; the
yielded index is the frame's 0-based position in the whole video. It also owns
:func:`write_video`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from recon.errors import ReconInputError
from recon.io.source import Frame, FrameSource, Selection, resize_rgb, size_at_width, wxh

# FFmpeg prints its own complaints about a file on stderr ("moov atom not found" for a file
# that is not a video, "header damaged" while decoding a damaged one); recon says what
# matters in its own one-line error, so FFmpeg is quiet (AV_LOG_QUIET). OpenCV reads this
# once, at its first use of FFmpeg in the process (a capture or a writer), which is after
# this module is imported. A value set by the user is kept: OPENCV_FFMPEG_LOGLEVEL=16 shows
# FFmpeg's errors again (OpenCV then prints them on stdout, prefixed "[OPENCV:FFMPEG:16]").
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

VIDEO_SUFFIXES = (
    ".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp", ".mts", ".ts",
)
DEFAULT_FPS = 30.0  # assumed when the container reports no usable frame rate

# Display rotation (degrees, as OpenCV reports CAP_PROP_ORIENTATION_META) -> cv2.rotate code,
# the same mapping OpenCV's FFmpeg backend applies when it rotates frames itself.
_ROTATE_CODES = {90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}


def _capture(path: Path) -> cv2.VideoCapture:
    """An opened VideoCapture of `path`, or a one-line error.

    The FFmpeg backend is asked for explicitly when it exists: CAP_ANY would also try the
    image-sequence backend, which reads printf patterns such as ``%03d`` in file names.
    """
    api = cv2.CAP_FFMPEG if cv2.videoio_registry.hasBackend(cv2.CAP_FFMPEG) else cv2.CAP_ANY
    # OpenCV logs a warning of its own when a file is not a video; our error says it in one line.
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        cap = cv2.VideoCapture(str(path), api)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if not cap.isOpened():
        cap.release()
        raise ReconInputError(f"{path}: not a video OpenCV can decode (unknown format or corrupt file)")
    # Ask OpenCV to apply the rotation itself; _manual_rotation covers backends that ignore this.
    cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    return cap


def _rotation_degrees(cap: cv2.VideoCapture) -> int:
    """Display rotation in the metadata, normalised to 0, 90, 180 or 270."""
    meta = cap.get(cv2.CAP_PROP_ORIENTATION_META)
    if not np.isfinite(meta):
        return 0
    return int(round(meta / 90.0)) % 4 * 90


def _manual_rotation(cap: cv2.VideoCapture, rotation: int) -> int | None:
    """cv2.rotate code we must apply ourselves, None when OpenCV already rotates (or no rotation)."""
    if rotation == 0 or cap.get(cv2.CAP_PROP_ORIENTATION_AUTO) == 1:
        return None
    return _ROTATE_CODES[rotation]


def _usable_fps(value: float) -> float | None:
    return float(value) if np.isfinite(value) and 0.0 < value < 1000.0 else None


class VideoSource(FrameSource):
    """Frames of a video file, decoded lazily, rotation metadata applied.

    Attributes (besides FrameSource's): ``rotation`` (0/90/180/270 degrees of display
    rotation found in the metadata), ``frame_count_meta`` (frames the container claims,
    0 when unknown).
    """

    kind = "video"

    def __init__(self, path, selection: Selection = Selection(), width: int | None = None):
        self.path = Path(path)
        self.selection = selection
        cap = _capture(self.path)
        try:
            self.rotation = _rotation_degrees(cap)
            self._rotate_code = _manual_rotation(cap, self.rotation)
            fps = _usable_fps(cap.get(cv2.CAP_PROP_FPS))
            self.fps_known = fps is not None
            self._fps = fps or DEFAULT_FPS
            count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            self.frame_count_meta = int(count) if np.isfinite(count) and count > 0 else 0
            # The size comes from a decoded frame: it is the size after rotation whatever
            # the backend reports in CAP_PROP_FRAME_WIDTH/HEIGHT.
            ok, frame = cap.read()
        finally:
            cap.release()
        if not ok or frame is None:
            raise ReconInputError(f"{self.path}: video contains no decodable frames")
        frame = self._orient(frame)
        self.native_shape = frame.shape[:2]
        self._shape = size_at_width(*self.native_shape, width, self.path)

    # ------------------------------------------------------------------ facts

    @property
    def count_is_exact(self) -> bool:
        return False

    @property
    def count(self) -> int:
        """Estimated number of selected frames, from the container's frame count and fps."""
        total = self.frame_count_meta
        sel = self.selection
        if total == 0:
            return 0
        first = 0 if sel.start_time is None else min(total, math.ceil(sel.start_time * self._fps - 1e-6))
        stop = total if sel.end_time is None else min(total, math.ceil(sel.end_time * self._fps - 1e-6))
        n = max(0, math.ceil((stop - first) / sel.stride))
        return n if sel.max_frames is None else min(n, sel.max_frames)

    @property
    def description(self) -> str:
        rot = f", rotated {self.rotation} deg" if self.rotation else ""
        fps = f"{self._fps:g} fps" if self.fps_known else f"{self._fps:g} fps (assumed)"
        return (
            f"video {self.path} ({wxh(self.native_shape)}{rot}, {fps}, "
            f"~{self.frame_count_meta} frames) -> {wxh(self.shape)}, {self.selection.describe()}"
        )

    # ------------------------------------------------------------------ decoding

    def _orient(self, bgr: np.ndarray) -> np.ndarray:
        return bgr if self._rotate_code is None else cv2.rotate(bgr, self._rotate_code)

    def _selected(self, cap: cv2.VideoCapture) -> Iterator[tuple[int, float]]:
        """(video index, timestamp) of each selected frame, the capture positioned on it.

        Uses grab() only: frames outside the selection are demuxed/decoded but never
        converted to RGB. Timestamps come from CAP_PROP_POS_MSEC (right for variable
        frame rate phone videos) unless the backend's values do not increase, then from
        the previous timestamp plus 1 / fps.
        """
        sel = self.selection
        index, previous, in_range, taken = -1, None, 0, 0
        while sel.max_frames is None or taken < sel.max_frames:
            if not cap.grab():
                return
            index += 1
            t = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            if previous is not None and not (np.isfinite(t) and t > previous):
                t = previous + 1.0 / self._fps
            elif previous is None and not (np.isfinite(t) and t >= 0.0):
                t = 0.0
            previous = t
            if sel.start_time is not None and t < sel.start_time - 1e-6:
                continue
            if sel.end_time is not None and t >= sel.end_time - 1e-6:
                return
            in_range += 1
            if (in_range - 1) % sel.stride:
                continue
            taken += 1
            yield index, t

    def _frames(self) -> Iterator[Frame]:
        cap = _capture(self.path)
        try:
            for index, t in self._selected(cap):
                ok, bgr = cap.retrieve()
                if not ok or bgr is None:
                    raise ReconInputError(f"{self.path}: cannot decode frame {index} (corrupt video?)")
                bgr = self._orient(bgr)
                if bgr.shape[:2] != self.native_shape:
                    raise ReconInputError(
                        f"{self.path}: frame {index} is {bgr.shape[1]}x{bgr.shape[0]}, "
                        f"expected {wxh(self.native_shape)} like the first frame"
                    )
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                yield Frame(index, t, resize_rgb(rgb, self._shape))
        finally:
            cap.release()

    def count_at_least(self, n: int) -> int:
        """Number of selected frames, counted by grabbing but stopping once `n` are found."""
        cap = _capture(self.path)
        try:
            found = 0
            for _ in self._selected(cap):
                found += 1
                if found >= n:
                    break
            return found
        finally:
            cap.release()


def is_video_file(path) -> bool:
    """True when `path` is a file with a common video suffix (OpenCV may decode others too)."""
    path = Path(path)
    return path.is_file() and path.suffix.lower() in VIDEO_SUFFIXES


def write_video(rgb, path, fps: float = 30.0) -> Path:
    """Write frames (N, H, W, 3) uint8 RGB to an mp4 (mp4v) at `path`; returns the path.

    Writes to a temporary name next to `path` and renames, so a reader never sees a
    half-written file.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.shape[0] < 1:
        raise ReconInputError(f"write_video: frames must be (N, H, W, 3) with N >= 1, got shape {rgb.shape}")
    if rgb.dtype != np.uint8:
        raise ReconInputError(f"write_video: frames must be uint8, got {rgb.dtype}")
    path = Path(path)
    if not path.parent.is_dir():
        raise ReconInputError(f"write_video: directory {path.parent} does not exist")
    # The temporary name keeps the suffix: OpenCV picks the container from it.
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix or '.mp4'}")
    height, width = rgb.shape[1:3]
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (width, height))
    if not writer.isOpened():
        raise ReconInputError(f"write_video: OpenCV cannot open {path} for writing (mp4v)")
    try:
        for frame in rgb:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    os.replace(tmp, path)
    return path
