"""Record3D exports ("EXR + JPG"): ``rgb/N.jpg``, ``depth/N.exr``, ``metadata.json``.

Owns the Record3D layout and its conventions: frames are the colour files present, in
numeric order; ``metadata.json`` gives ``K`` (column-major), ARKit's camera-to-world poses
(OpenGL camera axes, turned into OpenCV's) and timestamps. The LiDAR depth (half-float
metres on a coarser grid) is scaled up to the colour size by nearest neighbour so that it
agrees with ``K``; non-finite and <= 0 depth is invalid.
More: docs/input.md#record3d
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import MIN_QUAT_NORM, make_poses, opengl_to_opencv, quat_to_matrix

from .base import RGBDDataset, check_exist, image_shape, list_images, require_file

METADATA = "metadata.json"


def is_record3d(root: Path) -> bool:
    """True when `root` looks like a Record3D export."""
    return (root / METADATA).is_file() and (root / "rgb").is_dir()


def read_metadata(path: Path) -> dict:
    """``metadata.json`` as a dict; one-line error on invalid JSON or missing keys."""
    require_file(path)
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ReconInputError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ReconInputError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from None
    if not isinstance(meta, dict):
        raise ReconInputError(f"{path}: expected a JSON object")
    missing = [k for k in ("K", "poses", "w", "h") if k not in meta]
    if missing:
        raise ReconInputError(f"{path}: no {missing[0]!r} entry (not a Record3D metadata file?)")
    return meta


def _numbers(path: Path, meta: dict, key: str, count: int | None = None, what: str = "a number") -> np.ndarray:
    """meta[key] as float64: (M, count) from a list of `count`-number lists, (M,) from a flat list."""
    value = meta[key]
    if not isinstance(value, list) or not value:
        raise ReconInputError(f"{path}: {key!r} must be a non-empty list")
    for i, entry in enumerate(value):
        entries = [entry] if count is None else entry if isinstance(entry, list) and len(entry) == count else [None]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in entries):
            raise ReconInputError(f"{path}: {key}[{i}]: expected {what}, got {entry!r}")
    return np.asarray(value, dtype=np.float64)


def record3d_intrinsics(path: Path, meta: dict) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from metadata's column-major 3x3 ``K``."""
    k = _numbers(path, meta, "K")
    if k.shape != (9,):
        raise ReconInputError(f"{path}: 'K' must hold the 9 numbers of a 3x3 matrix, got {k.size}")
    return float(k[0]), float(k[4]), float(k[6]), float(k[7])


def record3d_poses(path: Path, meta: dict) -> np.ndarray:
    """(M, 4, 4) camera-to-world poses, OpenCV camera axes, from metadata's ARKit ``poses``."""
    table = _numbers(path, meta, "poses", 7, "7 numbers qx qy qz qw tx ty tz")
    norm = np.linalg.norm(table[:, :4], axis=1)
    if (norm < MIN_QUAT_NORM).any():
        i = int(np.argmax(norm < MIN_QUAT_NORM))
        raise ReconInputError(f"{path}: poses[{i}]: quaternion has near-zero norm ({norm[i]:.2g})")
    rot = quat_to_matrix(table[:, :4])
    return opengl_to_opencv(make_poses(rot, table[:, 4:7]))


def _frame_number(path: Path) -> int:
    try:
        return int(path.stem)
    except ValueError:
        raise ReconInputError(f"{path}: file name is not a frame number (expected rgb/N.jpg)") from None


def open_record3d(root) -> RGBDDataset:
    """Open a Record3D export folder (``rgb/``, ``depth/``, ``metadata.json``)."""
    root = Path(root)
    meta_path = root / METADATA
    meta = read_metadata(meta_path)
    rgb_paths = list_images(root / "rgb")
    if not rgb_paths:
        raise ReconInputError(f"{root / 'rgb'}: no colour images")
    numbers = np.asarray([_frame_number(p) for p in rgb_paths], dtype=np.int64)
    order = np.argsort(numbers, kind="stable")
    rgb_paths, numbers = [rgb_paths[i] for i in order], numbers[order]

    all_poses = record3d_poses(meta_path, meta)
    beyond = np.flatnonzero(numbers >= len(all_poses))
    if beyond.size:
        raise ReconInputError(f"{meta_path}: no pose for {rgb_paths[beyond[0]]} ('poses' has {len(all_poses)} "
                              f"entries, frame {numbers[beyond[0]]} needs {numbers[beyond[0]] + 1})")
    poses = all_poses[numbers]

    timestamps = None
    if "frameTimestamps" in meta:
        stamps = _numbers(meta_path, meta, "frameTimestamps")
        if stamps.ndim != 1 or numbers[-1] >= len(stamps):
            raise ReconInputError(f"{meta_path}: 'frameTimestamps' has {stamps.size} entries, frame {numbers[-1]} "
                                  f"({rgb_paths[-1].name}) needs {numbers[-1] + 1}")
        timestamps = stamps[numbers]
    elif isinstance(meta.get("fps"), (int, float)) and meta["fps"] > 0:
        timestamps = numbers / float(meta["fps"])

    depth_paths = None
    if (root / "depth").is_dir():
        depth_paths = [root / "depth" / f"{n}.exr" for n in numbers]
        check_exist(depth_paths)

    height, width = image_shape(rgb_paths[0])
    mw, mh = meta["w"], meta["h"]
    if (mh, mw) != (height, width):
        raise ReconInputError(f"{meta_path}: 'K' is for a {mw}x{mh} image but {rgb_paths[0]} is {width}x{height}")
    return RGBDDataset(
        kind="record3d",
        name=root.resolve().name,
        root=root,
        frame_ids=[str(n) for n in numbers],
        intrinsics=record3d_intrinsics(meta_path, meta),
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        poses=poses,
        timestamps=timestamps,
        depth_scale=1.0,
        depth_resize=True,
    )
