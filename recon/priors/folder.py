"""User-supplied depth (or disparity) maps from a folder, as a prior.

This module owns reading depth files (.npy, .npz, 16-bit PNG, float EXR/PFM/TIFF through
OpenCV), matching them to frames (by file stem, else by natural sorted order), and the
checks that turn a bad file into a one-line ReconInputError naming the frame and file.
Affine-invariant disparity is aligned to metric depth by :mod:`recon.priors.align` when an
``align_to`` reference is given (see DepthPrior).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..errors import ReconInputError
from .base import DepthPrior, PriorOutput, register_prior
from .resample import resize_nearest

DEPTH_SUFFIXES = (".npy", ".npz", ".png", ".exr", ".pfm", ".tif", ".tiff")
# Metres per unit of 16-bit PNG depth unless told otherwise (millimetres).
PNG_DEPTH_SCALE = 0.001
# 16-bit value some sensors (7-Scenes, Kinect tools) write for "no measurement".
UINT16_INVALID = 65535
# Role words that name the same frame differently in colour and depth files
# ("frame-000001.color.jpg" <-> "frame-000001.depth.png").
_ROLE_SUFFIX = re.compile(r"[._-](colou?r|rgb|image|img|depth|disp|disparity|pred|prediction)$", re.IGNORECASE)


def natural_key(name: str) -> list:
    """Sort key with numbers compared as numbers ("f2" < "f10")."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def stem_keys(name: str) -> tuple[str, ...]:
    """Keys a file is matched by: its stem, and the stem without a role word."""
    stem = Path(name).stem
    bare = _ROLE_SUFFIX.sub("", stem)
    return (stem,) if bare == stem else (stem, bare)


def list_depth_files(folder: Path) -> list[Path]:
    """Depth files in ``folder`` in natural order."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in DEPTH_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


def match_depth_files(files: list[Path], frame_names: list[str] | None, count: int, folder: Path) -> list[Path]:
    """One depth file per frame: by stem when frame names are known, else in sorted order.

    Raises:
        ReconInputError: a frame without a depth file, or (by order) a count mismatch.
    """
    if frame_names is None:
        if len(files) != count:
            raise ReconInputError(
                f"{folder}: {len(files)} depth files for {count} frames (matching by sorted order needs one per"
                " frame; pass frame names to match by file stem)"
            )
        return list(files)
    index: dict[str, Path] = {}
    for path in files:
        for key in stem_keys(path.name):
            index.setdefault(key, path)
    matched = []
    for k, name in enumerate(frame_names):
        path = next((index[key] for key in stem_keys(name) if key in index), None)
        if path is None:
            raise ReconInputError(f"{folder}: no depth file for frame {k} ({name}); expected e.g. {Path(name).stem}.npy")
        matched.append(path)
    return matched


def read_depth_file(path: Path, depth_scale: float | None = None) -> np.ndarray:
    """Read one map (H, W) float32, scaled by ``depth_scale`` (metres per stored unit).

    Defaults: 16-bit PNG in millimetres (0 and 65535 invalid -> 0); float files as stored.
    NaN/inf are kept for the caller to judge.

    Raises:
        ReconInputError: unreadable file or not a single-channel 2-D map.
    """
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            raw = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                keys = list(archive.keys())
                key = next((k for k in ("depth", "disparity", "arr_0") if k in keys), keys[0] if len(keys) == 1 else None)
                if key is None:
                    raise ReconInputError(f"{path}: .npz holds {keys}; expected one array or one named 'depth'")
                raw = archive[key]
        else:
            raw = _read_image(path)
    except ReconInputError:
        raise
    except (OSError, ValueError, EOFError) as exc:
        raise ReconInputError(f"{path}: cannot read depth ({type(exc).__name__}: {exc})") from None
    raw = np.squeeze(np.asarray(raw))
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.number):
        raise ReconInputError(f"{path}: depth must be a single-channel 2-D map, got {raw.dtype} {raw.shape}")
    if raw.dtype == np.uint16:
        invalid = (raw == 0) | (raw == UINT16_INVALID)
        depth = raw.astype(np.float32) * np.float32(PNG_DEPTH_SCALE if depth_scale is None else depth_scale)
        depth[invalid] = 0.0
        return depth
    return raw.astype(np.float32) * np.float32(1.0 if depth_scale is None else depth_scale)


def _read_image(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".exr":
        # OpenCV reads EXR only when this is set before its first use; setting it here is
        # harmless when cv2 was imported earlier and EXR then fails with a clear message.
        os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        image = None
    if image is None:
        hint = ""
        if path.suffix.lower() == ".exr":
            # Some OpenCV wheels ship without an EXR codec at all (e.g. opencv-python 5.0).
            hint = (" (this OpenCV build has no EXR reader, or OPENCV_IO_ENABLE_OPENEXR=1 was not set before cv2"
                    " was imported; convert to .npy, .pfm or float .tiff)")
        raise ReconInputError(f"{path}: OpenCV cannot read this depth file{hint}")
    if image.ndim == 3:
        # Multi-channel float images (EXR/PFM) written from a depth map repeat it per channel.
        if not np.allclose(image[..., 0], image[..., -1], equal_nan=True):
            raise ReconInputError(f"{path}: depth must be single-channel, got {image.shape[2]} different channels")
        image = image[..., 0]
    return image


def check_map(values: np.ndarray, kind: str, frame: int, path: Path, allow_nan: bool) -> np.ndarray:
    """Validate one map and mark invalid pixels 0 (depth: also non-positive ones).

    Raises:
        ReconInputError: NaN present (unless allowed) or no valid pixel at all.
    """
    finite = np.isfinite(values)
    if np.isnan(values).any() and not allow_nan:
        raise ReconInputError(
            f"{path}: {kind} of frame {frame} contains NaN ({int(np.isnan(values).sum())} pixels);"
            " use 0 for invalid pixels or allow_nan=True"
        )
    valid = finite & (values > 0) if kind == "depth" else finite & (values != 0)
    if not valid.any():
        raise ReconInputError(f"{path}: {kind} of frame {frame} has no valid pixel (all zero, NaN or inf)")
    return np.where(valid, values, 0.0).astype(np.float32)


@register_prior("folder")
class FolderDepthPrior(DepthPrior):
    """Depth or disparity maps the user computed elsewhere.

    Args:
        path: folder of depth files.
        frame_names: names of the frames (e.g. their image file names), to match depth files
            by stem (role words like ".color"/".depth" ignored); None: sorted natural order,
            one file per frame.
        kind: "depth" (metric, metres after ``depth_scale``) or "disparity" (affine-invariant;
            output kind "affine_disparity", or "metric" when ``align_to`` is given).
        depth_scale: metres per stored unit; default 0.001 for 16-bit PNG, 1 otherwise.
        resize: resize maps of another size (same aspect) to the frame size with nearest
            neighbours; False makes a size mismatch an error.
        allow_nan: treat NaN as invalid instead of rejecting the file.
    """

    name = "folder"

    def __init__(self, path, frame_names=None, kind: str = "depth", depth_scale: float | None = None,
                 resize: bool = True, allow_nan: bool = False, batch_size: int = 16, device: str = "cpu",
                 progress: bool = True, align_to=None):
        super().__init__(batch_size=batch_size, device=device, progress=progress, align_to=align_to)
        if kind not in ("depth", "disparity"):
            raise ValueError(f"folder prior kind must be 'depth' or 'disparity', got {kind!r}")
        self.folder = Path(path)
        if not self.folder.is_dir():
            raise ReconInputError(f"{self.folder}: depth folder does not exist")
        self.files = list_depth_files(self.folder)
        if not self.files:
            raise ReconInputError(f"{self.folder}: no depth files ({', '.join(DEPTH_SUFFIXES)})")
        self.frame_names = None if frame_names is None else [str(n) for n in frame_names]
        self.kind = kind
        self.depth_scale = depth_scale
        self.resize = resize
        self.allow_nan = allow_nan

    def plan(self, frames, intrinsics) -> list[Path]:
        if self.frame_names is not None and len(self.frame_names) != len(frames):
            raise ReconInputError(f"{self.folder}: {len(self.frame_names)} frame names for {len(frames)} frames")
        return match_depth_files(self.files, self.frame_names, len(frames), self.folder)

    def load(self, frame: int, path: Path, size: tuple[int, int]) -> np.ndarray:
        """One checked map (H, W) float32 at the frame size."""
        values = check_map(read_depth_file(path, self.depth_scale), self.kind, frame, path, self.allow_nan)
        if values.shape != size:
            if not self.resize:
                raise ReconInputError(
                    f"{path}: depth of frame {frame} is {values.shape[0]}x{values.shape[1]},"
                    f" the frame is {size[0]}x{size[1]} (resizing disabled)"
                )
            try:
                values = resize_nearest(values, size)
            except ValueError as exc:
                raise ReconInputError(f"{path}: frame {frame}: {exc}") from None
        return values

    def predict_batch(self, frames, intrinsics, indices, plan=None) -> PriorOutput:
        files = plan if plan is not None else self.plan(frames, intrinsics)
        size = tuple(frames.shape[1:3])
        maps = np.stack([self.load(k, files[k], size) for k in indices])
        kind = "metric" if self.kind == "depth" else "affine_disparity"
        return PriorOutput(depth=maps, kind=kind, info={"model": "folder", "folder": str(self.folder),
                                                        "stored": self.kind})
