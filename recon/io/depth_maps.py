"""Depth maps stored as files by other tools: listing a folder of them and reading one.

This module owns the file side of user-supplied depth (or disparity) maps: .npy, .npz,
16-bit PNG (millimetres unless told otherwise; 0 and 65535 invalid) and float EXR/PFM/TIFF
through OpenCV, each read as one (H, W) float32 map, with one-line ReconInputErrors naming
the file. Matching files to frames and checking their values is the folder prior's
business (:mod:`recon.priors.folder`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.io.naming import natural_key

DEPTH_SUFFIXES = (".npy", ".npz", ".png", ".exr", ".pfm", ".tif", ".tiff")
# Metres per unit of 16-bit PNG depth unless told otherwise (millimetres).
PNG_DEPTH_SCALE = 0.001
# 16-bit value some sensors (7-Scenes, Kinect tools) write for "no measurement".
UINT16_INVALID = 65535


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
