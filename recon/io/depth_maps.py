"""Depth maps as files: listing a folder of them, reading one, and the 16-bit PNG recon writes.

This module owns the file side of depth (or disparity) maps: reading user-supplied .npy,
.npz, 16-bit PNG (millimetres unless told otherwise; 0 and 65535 invalid) and float
EXR/PFM/TIFF through OpenCV, each as one (H, W) float32 map, with one-line
ReconInputErrors naming the file; and encoding recon's own depth PNGs so that every reader,
this one included, reads back what was written. Matching files to frames and checking their
values is the folder prior's business (:mod:`recon.priors.folder`); where the files go in
an output folder, :mod:`recon.io.output_folder`'s.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from recon.errors import ReconInputError
from recon.io.naming import natural_key

DEPTH_SUFFIXES = (".npy", ".npz", ".png", ".exr", ".pfm", ".tif", ".tiff")
# Metres per unit of 16-bit PNG depth unless told otherwise (millimetres).
PNG_DEPTH_SCALE = 0.001
# 16-bit value some sensors (7-Scenes, Kinect tools) write for "no measurement".
UINT16_INVALID = 65535
# The largest value recon writes (65.534 m): 65535 would read back as no measurement.
PNG_DEPTH_MAX = UINT16_INVALID - 1


def list_depth_files(folder: Path) -> list[Path]:
    """Depth files in ``folder`` in natural order."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in DEPTH_SUFFIXES]
    return sorted(files, key=lambda p: natural_key(p.name))


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
                key = next((k for k in ("depth", "disparity", "arr_0") if k in keys),
                           keys[0] if len(keys) == 1 else None)
                if key is None:
                    raise ReconInputError(f"{path}: .npz holds {keys}; expected one array or one named 'depth'")
                raw = archive[key]
        else:
            raw = _read_depth_image(path)
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


def _read_depth_image(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".exr":
        # OpenCV reads EXR only when this is set before its first use; setting it here is
        # harmless when cv2 was imported earlier and EXR then fails with a clear message.
        os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2

    try:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
    except cv2.error:
        image = None
    if image is None and path.suffix.lower() == ".exr" and path.is_file():
        # Some OpenCV wheels ship without an EXR codec at all (e.g. opencv-python 5.0).
        from recon.io.exr import read_exr

        return read_exr(path)
    if image is None:
        raise ReconInputError(f"{path}: OpenCV cannot read this depth file")
    if image.ndim == 3:
        # Multi-channel float images (EXR/PFM) written from a depth map repeat it per channel.
        if not np.allclose(image[..., 0], image[..., -1], equal_nan=True):
            raise ReconInputError(f"{path}: depth must be single-channel, got {image.shape[2]} different channels")
        image = image[..., 0]
    return image


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """(H, W) metres -> uint16 millimetres: invalid (0, negative, NaN, inf) -> 0, valid depth
    rounded and clipped to [1, PNG_DEPTH_MAX] so a valid pixel never turns into "invalid"."""
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    mm = np.zeros(d.shape, np.uint16)
    mm[valid] = np.clip(np.round(d[valid] / PNG_DEPTH_SCALE), 1, PNG_DEPTH_MAX).astype(np.uint16)
    return mm


def depth_png_bytes(depth: np.ndarray) -> bytes:
    """16-bit PNG (millimetres) of a (H, W) depth map in metres."""
    ok, buf = cv2.imencode(".png", depth_to_mm(depth))
    if not ok:
        raise OSError("OpenCV could not encode a 16-bit PNG")
    return buf.tobytes()


def read_depth_png_mm(path) -> np.ndarray:
    """(H, W) float32 metres from a depth PNG written by :func:`depth_png_bytes`."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise ReconInputError(f"{path}: not a 16-bit single-channel depth PNG")
    return raw.astype(np.float32) / np.float32(1.0 / PNG_DEPTH_SCALE)
