"""COLMAP project folders: ``images/`` and a sparse model in ``sparse/0/`` (or ``sparse/``).

Owns reading a COLMAP project as a dataset (kind ``colmap``), the model read by
:func:`recon.io.pose_formats.colmap.read_colmap`. Frames are the registered images whose files
exist, in natural name order; per-image cameras give ``frame_intrinsics`` and their median
``intrinsics``; ``distortion`` is OpenCV's (k1, k2, p1, p2, k3), None for pinhole cameras, and
fisheye or FOV models are refused. No depth; poses up to scale. An image folder alone (no
model beside it) stays a plain image folder.
More: docs/input.md#colmap-projects
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.io.pose_formats.colmap import colmap_model_dir, read_colmap

from .base import RGBDDataset, image_shape, require_dir


def is_colmap(root: Path) -> bool:
    """True when `root` is a COLMAP project: images/ and a sparse model."""
    return (root / "images").is_dir() and colmap_model_dir(root) is not None


def open_colmap(root) -> RGBDDataset:
    """Open a COLMAP project folder (``images/`` + ``sparse/0/`` or ``sparse/``)."""
    root = Path(root)
    image_dir = require_dir(root / "images")
    model_dir = colmap_model_dir(root)
    if model_dir is None:
        where = next((c for c in (root / "sparse" / "0", root / "sparse") if c.is_dir()), root / "sparse" / "0")
        lacking = next(n for n in ("cameras", "images")
                       if not (where / f"{n}.bin").is_file() and not (where / f"{n}.txt").is_file())
        raise ReconInputError(f"{where}: no COLMAP model ({lacking}.bin or {lacking}.txt not found)")
    data = read_colmap(model_dir)
    # read_colmap sorts the images by natural_key of their names.
    keep = [i for i, name in enumerate(data.names) if data.valid[i] and (image_dir / name).is_file()]
    if not keep:
        raise ReconInputError(f"{model_dir}: none of the model's {len(data)} registered images is in {image_dir}")
    names = [data.names[i] for i in keep]
    rgb_paths = [image_dir / n for n in names]
    where = model_dir / ("cameras.bin" if (model_dir / "cameras.bin").is_file() else "cameras.txt")

    if data.frame_intrinsics is not None:
        frame_intrinsics = data.frame_intrinsics[keep]
        distortions = data.frame_distortion[keep]
    else:
        first = data.intrinsics
        frame_intrinsics = None
        distortions = np.array([first["distortion"] or (np.nan,) * 5], dtype=np.float64)
    unexpressed = np.flatnonzero(np.isnan(distortions).any(axis=1))
    if unexpressed.size:
        raise ReconInputError(f"{where}: the camera of {names[unexpressed[0]]} has a lens model (fisheye, FOV) that "
                              "OpenCV's (k1, k2, p1, p2, k3) cannot express; use PINHOLE, SIMPLE_RADIAL, RADIAL or "
                              "OPENCV cameras")
    intrinsics = (tuple(float(v) for v in np.median(frame_intrinsics, axis=0)) if frame_intrinsics is not None
                  else tuple(float(data.intrinsics[k]) for k in ("fx", "fy", "cx", "cy")))
    median = np.median(distortions, axis=0)
    distortion = tuple(float(v) for v in median) if median.any() else None

    height, width = image_shape(rgb_paths[0])
    mw, mh = data.intrinsics.get("width"), data.intrinsics.get("height")
    if (mh, mw) != (height, width):
        raise ReconInputError(f"{where}: the model's camera is {mw}x{mh} but {rgb_paths[0]} is {width}x{height}")
    return RGBDDataset(
        kind="colmap",
        name=root.resolve().name,
        root=root,
        frame_ids=[str(Path(n).with_suffix("")) for n in names],
        intrinsics=intrinsics,
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        poses=data.poses[keep],
        pose_valid=np.ones(len(keep), bool),
        frame_intrinsics=frame_intrinsics,
        distortion=distortion,
    )
