"""Open3D / Redwood RGB-D folders: ``color/`` (or ``image/``, ``rgb/``), ``depth/``, a trajectory
``.log`` and an optional PinholeCameraIntrinsic ``.json``.

Owns this layout: colour and depth paired by sorted order (counts must match), depth
uint16 millimetres with 0 invalid, poses from the ``.log`` (camera-to-world, one per frame
in order), intrinsics from Open3D's json (``intrinsic_matrix`` is column-major) or the
PrimeSense defaults 525, 525, 319.5, 239.5.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.io.pose_formats.trajectories import read_log

from .base import RGBDDataset, image_shape, list_images

PRIMESENSE = (525.0, 525.0, 319.5, 239.5)
COLOR_DIRS = ("color", "image", "rgb")
# Preferred trajectory names when a folder holds several logs.
LOG_NAMES = ("trajectory.log", "traj.log", "odometry.log", "gt.log")


def _color_dir(root: Path) -> Path | None:
    return next((root / d for d in COLOR_DIRS if (root / d).is_dir()), None)


def is_redwood(root: Path) -> bool:
    """True when `root` holds a colour folder and depth/ (the generic Open3D layout)."""
    return _color_dir(root) is not None and (root / "depth").is_dir()


def read_intrinsic_json(path: Path) -> tuple[tuple[float, float, float, float], int | None, int | None]:
    """(fx, fy, cx, cy), width, height from an Open3D PinholeCameraIntrinsic json."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        m = np.asarray(data["intrinsic_matrix"], dtype=np.float64)
    except json.JSONDecodeError as exc:
        raise ReconInputError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg})") from None
    except (KeyError, TypeError, ValueError):
        raise ReconInputError(f"{path}: expected an Open3D intrinsic json with a 9-number 'intrinsic_matrix'") from None
    if m.size != 9:
        raise ReconInputError(f"{path}: 'intrinsic_matrix' must have 9 numbers, got {m.size}")
    k = m.reshape(3, 3).T  # stored column-major
    return (k[0, 0], k[1, 1], k[0, 2], k[1, 2]), data.get("width"), data.get("height")


def _find_log(root: Path) -> Path | None:
    logs = sorted(root.glob("*.log"))
    if not logs:
        return None
    named = [root / n for n in LOG_NAMES if (root / n).is_file()]
    return (named or logs)[0]


def _find_intrinsic_json(root: Path) -> Path | None:
    for p in sorted(root.glob("*.json")):
        try:
            if "intrinsic_matrix" in json.loads(p.read_text(encoding="utf-8")):
                return p
        except (OSError, ValueError, TypeError):
            continue
    return None


def open_redwood(root, log=None, intrinsic=None) -> RGBDDataset:
    """Open an Open3D/Redwood RGB-D folder; `log`/`intrinsic` override the files found in it."""
    root = Path(root)
    cdir = _color_dir(root)
    if cdir is None:
        raise ReconInputError(f"{root / 'color'}: folder not found")
    rgb_paths = list_images(cdir)
    depth_paths = list_images(root / "depth", (".png",))
    if not rgb_paths:
        raise ReconInputError(f"{cdir}: no colour images")
    if len(rgb_paths) != len(depth_paths):
        raise ReconInputError(
            f"{root / 'depth'}: {len(depth_paths)} depth images but {len(rgb_paths)} colour images in {cdir.name}/"
        )

    poses = None
    log_path = Path(log) if log is not None else _find_log(root)
    if log_path is not None:
        data = read_log(log_path)
        if len(data) != len(rgb_paths):
            raise ReconInputError(f"{log_path}: {len(data)} poses for {len(rgb_paths)} frames")
        poses = data.poses

    height, width = image_shape(rgb_paths[0])
    json_path = Path(intrinsic) if intrinsic is not None else _find_intrinsic_json(root)
    intrinsics = PRIMESENSE
    if json_path is not None:
        intrinsics, jw, jh = read_intrinsic_json(json_path)
        if jw is not None and jh is not None and (int(jh), int(jw)) != (height, width):
            raise ReconInputError(f"{json_path}: intrinsics for {jw}x{jh} but images are {width}x{height}")
    return RGBDDataset(
        kind="redwood",
        name=root.resolve().name,
        root=root,
        frame_ids=[p.stem for p in rgb_paths],
        intrinsics=tuple(float(v) for v in intrinsics),
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        poses=poses,
        depth_scale=1000.0,
    )
