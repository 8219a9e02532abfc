"""KITTI odometry sequences: an image folder, ``calib.txt``, ``poses.txt``, optional ``times.txt``.

Owns the KITTI odometry layout: rectified images in ``image_0/``, ``image_l/`` or
``image_2/`` (tried in that order; greyscale returned as RGB), intrinsics from the matching
projection matrix of ``calib.txt``, ground truth of camera 0 (``poses.txt`` or the official
``poses/<sequence>.txt``, read by :func:`recon.io.pose_formats.trajectories.read_kitti`)
moved to camera 2 by its offset, timestamps from ``times.txt`` else 10 Hz. No depth.
More: docs/input.md#kitti-odometry
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.io.pose_formats.base import data_lines, parse_floats, parse_table
from recon.io.pose_formats.trajectories import read_kitti

from .base import RGBDDataset, image_shape, list_images, require_file

# (image folder, the camera whose projection matrix calib.txt gives as P<n>)
IMAGE_DIRS = (("image_0", 0), ("image_l", 0), ("image_2", 2))
# KITTI's published frame rate (the odometry devkit: "10 frames per second").
FRAME_RATE = 10.0


def _image_dir(root: Path) -> tuple[Path, int] | None:
    return next(((root / d, cam) for d, cam in IMAGE_DIRS if (root / d).is_dir()), None)


def is_kitti(root: Path) -> bool:
    """True when `root` looks like a KITTI odometry sequence."""
    return (root / "calib.txt").is_file() and _image_dir(root) is not None


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """``calib.txt`` -> {"P0": (3, 4), ...}; unnamed lines are P0, P1, ... in order."""
    require_file(path)
    out: dict[str, np.ndarray] = {}
    for lineno, tokens in data_lines(path):
        name = f"P{len(out)}"
        if tokens[0].endswith(":"):
            name, tokens = tokens[0][:-1], tokens[1:]
        if len(tokens) != 12:
            raise ReconInputError(f"{path}:{lineno}: expected 12 numbers (a 3x4 matrix, row-major), got {len(tokens)}")
        out[name] = np.asarray(parse_floats(path, lineno, tokens), dtype=np.float64).reshape(3, 4)
    return out


def _pose_file(root: Path) -> Path | None:
    for cand in (root / "poses.txt", root.resolve().parent.parent / "poses" / f"{root.resolve().name}.txt"):
        if cand.is_file():
            return cand
    return None


def _frame_numbers(paths: list[Path]) -> np.ndarray:
    try:
        return np.asarray([int(p.stem) for p in paths], dtype=np.int64)
    except ValueError:
        bad = next(p for p in paths if not p.stem.isdigit())
        raise ReconInputError(f"{bad}: file name is not a frame number (expected e.g. 000000.png)") from None


def _per_frame(path: Path, count: int, numbers: np.ndarray, paths: list[Path], what: str) -> None:
    """One-line error when a frame number has no line in a per-frame file of `count` lines."""
    if numbers[-1] >= count:
        last = int(np.argmax(numbers >= count))
        raise ReconInputError(f"{path}: {count} {what}, but {paths[last].name} is frame {numbers[last]}")


def open_kitti(root) -> RGBDDataset:
    """Open a KITTI odometry sequence folder (e.g. ``sequences/00``)."""
    root = Path(root)
    found = _image_dir(root)
    if found is None:
        raise ReconInputError(f"{root / 'image_0'}: folder not found (nor image_l/ or image_2/)")
    image_dir, camera = found
    rgb_paths = list_images(image_dir)
    if not rgb_paths:
        raise ReconInputError(f"{image_dir}: no images")
    numbers = _frame_numbers(rgb_paths)  # list_images sorted them naturally: numeric order

    calib_path = root / "calib.txt"
    calib = read_calib(calib_path)
    key = f"P{camera}"
    if key not in calib:
        raise ReconInputError(f"{calib_path}: no {key} line (the projection matrix of {image_dir.name}/)")
    proj = calib[key]
    k = proj[:, :3]
    intrinsics = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))

    poses = None
    pose_path = _pose_file(root)
    if pose_path is not None:
        data = read_kitti(pose_path)
        _per_frame(pose_path, len(data), numbers, rgb_paths, "poses")
        poses = data.poses[numbers]
        if camera != 0:
            # P = K [I | t]: camera n's centre is at -t in camera 0's frame.
            offset = np.eye(4)
            offset[:3, 3] = -np.linalg.solve(k, proj[:, 3])
            poses = poses @ offset

    times_path = root / "times.txt"
    if times_path.is_file():
        times = parse_table(times_path, 1, "timestamp")[0][:, 0]
        _per_frame(times_path, len(times), numbers, rgb_paths, "timestamps")
        timestamps = times[numbers]
    else:
        timestamps = numbers / FRAME_RATE

    height, width = image_shape(rgb_paths[0])
    return RGBDDataset(
        kind="kitti",
        name=root.resolve().name,
        root=root,
        frame_ids=[p.stem for p in rgb_paths],
        intrinsics=intrinsics,
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        poses=poses,
        timestamps=np.asarray(timestamps, dtype=np.float64),
    )
