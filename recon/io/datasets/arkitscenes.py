"""ARKitScenes low-resolution frames (``<video_id>_frames/``: ``lowres_wide/``, ``lowres_depth/``,
``lowres_wide_intrinsics/``, ``lowres_wide.traj``).

Owns the ARKitScenes layout and its pose convention: ``lowres_wide.traj`` holds axis-angle
world-to-camera transforms already in OpenCV camera axes, so camera-to-world is their
inverse, interpolated (SLERP + linear) to frames between samples at most ``max_gap`` apart
and taken as is within ``max_diff``. Depth is uint16 millimetres, 0 invalid.
More: docs/input.md#arkitscenes
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.geometry.rigid import interpolate_poses, make_poses
from recon.poses.result import invert_poses

from .base import RGBDDataset, check_exist, image_shape, list_images


def frames_dir(root: Path) -> Path | None:
    """The folder holding lowres_wide/ for `root` (itself or ``<video_id>_frames``)."""
    if (root / "lowres_wide").is_dir():
        return root
    cands = sorted(p for p in root.glob("*_frames") if (p / "lowres_wide").is_dir())
    return cands[0] if cands else None


def is_arkitscenes(root: Path) -> bool:
    """True when `root` looks like an ARKitScenes scene."""
    return frames_dir(root) is not None


def read_traj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``lowres_wide.traj`` -> timestamps (N,) and camera-to-world poses (N, 4, 4), OpenCV axes."""
    rows = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != 7:
            raise ReconInputError(
                f"{path}:{lineno}: expected 7 columns (timestamp rx ry rz tx ty tz), got {len(tokens)}"
            )
        try:
            rows.append([float(t) for t in tokens])
        except ValueError:
            raise ReconInputError(f"{path}:{lineno}: non-numeric value") from None
        if not np.isfinite(rows[-1]).all():
            raise ReconInputError(f"{path}:{lineno}: non-finite value")
    if not rows:
        raise ReconInputError(f"{path}: no poses")
    table = np.asarray(rows)
    world_to_cam = make_poses(Rotation.from_rotvec(table[:, 1:4]).as_matrix(), table[:, 4:7])
    return table[:, 0], invert_poses(world_to_cam)


def _timestamp(path: Path) -> float:
    """Timestamp in a ``<video_id>_<timestamp>.<ext>`` file name."""
    try:
        return float(path.stem.rsplit("_", 1)[1])
    except (IndexError, ValueError):
        raise ReconInputError(f"{path}: file name is not <video_id>_<timestamp>.{path.suffix.lstrip('.')}") from None


def read_pincam(path: Path) -> np.ndarray:
    """``w h fx fy cx cy`` -> (6,) float64."""
    try:
        values = np.asarray(path.read_text(encoding="utf-8").split(), dtype=np.float64)
    except (OSError, ValueError):
        raise ReconInputError(f"{path}: expected 'w h fx fy cx cy'") from None
    if values.shape != (6,):
        raise ReconInputError(f"{path}: expected 6 numbers (w h fx fy cx cy), got {values.size}")
    return values


def _pincam_for(intr_dir: Path, stem: str, ts: float) -> Path:
    """The .pincam of a frame; ARKitScenes' names sometimes differ by 1 ms in rounding."""
    video = stem.rsplit("_", 1)[0]
    for cand in (f"{stem}.pincam", f"{video}_{ts - 0.001:.3f}.pincam", f"{video}_{ts + 0.001:.3f}.pincam"):
        if (intr_dir / cand).is_file():
            return intr_dir / cand
    raise ReconInputError(f"{intr_dir / (stem + '.pincam')}: file not found")


def open_arkitscenes(root, max_diff: float = 0.005, max_gap: float = 0.2) -> RGBDDataset:
    """Open an ARKitScenes scene folder (``<video_id>`` or ``<video_id>_frames``)."""
    root = Path(root)
    base = frames_dir(root)
    if base is None:
        raise ReconInputError(f"{root}: no lowres_wide/ folder (not an ARKitScenes scene)")
    rgb_paths = list_images(base / "lowres_wide", (".png", ".jpg"))
    if not rgb_paths:
        raise ReconInputError(f"{base / 'lowres_wide'}: no images")
    stamps = np.asarray([_timestamp(p) for p in rgb_paths])
    order = np.argsort(stamps, kind="stable")
    rgb_paths, stamps = [rgb_paths[i] for i in order], stamps[order]

    depth_paths = None
    if (base / "lowres_depth").is_dir():
        depth_paths = [base / "lowres_depth" / f"{p.stem}.png" for p in rgb_paths]
        check_exist(depth_paths)

    intr_dir = base / "lowres_wide_intrinsics"
    if not intr_dir.is_dir():
        raise ReconInputError(f"{intr_dir}: folder not found")
    pincams = np.stack([read_pincam(_pincam_for(intr_dir, p.stem, t)) for p, t in zip(rgb_paths, stamps)])
    frame_intrinsics = pincams[:, 2:6]

    poses = valid = None
    traj = base / "lowres_wide.traj"
    if traj.is_file():
        traj_ts, traj_poses = read_traj(traj)
        poses, valid = interpolate_poses(stamps, traj_ts, traj_poses, max_gap=max_gap, max_diff=max_diff, snap=max_diff)
        if not valid.any():
            raise ReconInputError(f"{traj}: no trajectory timestamp within {max_diff} s of the frames")

    height, width = image_shape(rgb_paths[0])
    pw, ph = int(pincams[0, 0]), int(pincams[0, 1])
    if (ph, pw) != (height, width):
        pincam = _pincam_for(intr_dir, rgb_paths[0].stem, stamps[0])
        raise ReconInputError(f"{pincam}: size {pw}x{ph} but image is {width}x{height}")
    return RGBDDataset(
        kind="arkitscenes",
        name=base.name.removesuffix("_frames"),
        root=root,
        frame_ids=[p.stem for p in rgb_paths],
        intrinsics=tuple(float(v) for v in frame_intrinsics[0]),
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        poses=poses,
        pose_valid=valid,
        timestamps=stamps,
        depth_scale=1000.0,
        frame_intrinsics=frame_intrinsics,
    )
