"""TUM RGB-D sequences (``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``).

Owns: timestamp association of colour, depth and ground truth, and the choice of
intrinsics. Colour frames are paired with depth frames (closest first, within
``max_diff`` s); ground-truth poses are interpolated (SLERP + linear) to the colour
timestamps, or taken from the nearest sample within ``max_diff`` s at the ends and across
tracking gaps. Frames without a pose stay in with ``pose_valid`` False.

Depth PNGs are uint16, metres = value / 5000, 0 invalid. Colour images are returned as
stored; TUM's are not undistorted, so ``distortion`` carries the published coefficients.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import associate_timestamps, interpolate_poses
from recon.io.pose_formats.trajectories import read_tum

from .base import RGBDDataset, check_exist, image_shape, require_file

DEPTH_SCALE = 5000.0
# Published calibrated colour intrinsics (fx, fy, cx, cy) and distortion (k1, k2, p1, p2, k3).
PUBLISHED = {
    "fr1": ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}
# What the ROS driver used to register depth to colour; the fallback for unknown sequences.
ROS_DEFAULT = (525.0, 525.0, 319.5, 239.5)


def is_tum(root: Path) -> bool:
    """True when `root` looks like a TUM sequence."""
    return (root / "rgb.txt").is_file() or ((root / "rgbd_assoc.txt").is_file() and (root / "rgb").is_dir())


def read_list(path: Path) -> tuple[np.ndarray, list[str], list[int]]:
    """``timestamp filename`` list (rgb.txt, depth.txt) -> timestamps (N,), names, line numbers."""
    require_file(path)
    stamps, names, lines = [], [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != 2:
            raise ReconInputError(f"{path}:{lineno}: expected 2 columns (timestamp filename), got {len(tokens)}")
        try:
            stamps.append(float(tokens[0]))
        except ValueError:
            raise ReconInputError(f"{path}:{lineno}: non-numeric timestamp {tokens[0]!r}") from None
        names.append(tokens[1])
        lines.append(lineno)
    if not names:
        raise ReconInputError(f"{path}: no frames listed")
    return np.asarray(stamps), names, lines


def read_assoc(path: Path) -> tuple[np.ndarray, list[str], list[str]]:
    """Pre-associated ``t_rgb rgb_file t_depth depth_file`` list -> rgb timestamps, rgb names, depth names."""
    stamps, rgb, depth = [], [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != 4:
            raise ReconInputError(f"{path}:{lineno}: expected 4 columns (t_rgb rgb t_depth depth), got {len(tokens)}")
        try:
            stamps.append(float(tokens[0]))
        except ValueError:
            raise ReconInputError(f"{path}:{lineno}: non-numeric timestamp {tokens[0]!r}") from None
        rgb.append(tokens[1])
        depth.append(tokens[3])
    if not rgb:
        raise ReconInputError(f"{path}: no frames listed")
    return np.asarray(stamps), rgb, depth


def parse_intrinsics_txt(path: Path) -> tuple[tuple[float, ...], tuple[float, ...] | None]:
    """(fx, fy, cx, cy) and distortion (or None) from an intrinsics text file.

    Accepts ``fx=.. fy=.. cx=.. cy=.. [d=k1,k2,p1,p2,k3]`` lines, a line of 4 numbers or a
    3x3 matrix. With several ``key=value`` lines the one carrying distortion wins: that is
    the calibrated colour camera (TUM's published values), not the registered-depth default.
    """
    candidates = []
    numeric_rows = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if "=" in line:
            fields = dict(tok.split("=", 1) for tok in line.split() if "=" in tok)
            try:
                intr = tuple(float(fields[k]) for k in ("fx", "fy", "cx", "cy"))
                dist = tuple(float(v) for v in fields["d"].split(",")) if "d" in fields else None
            except (KeyError, ValueError):
                raise ReconInputError(f"{path}:{lineno}: expected fx= fy= cx= cy= [d=k1,k2,p1,p2,k3]") from None
            candidates.append((intr, dist))
        else:
            try:
                numeric_rows.append([float(t) for t in line.replace(",", " ").split()])
            except ValueError:
                raise ReconInputError(f"{path}:{lineno}: non-numeric value in intrinsics") from None
    if candidates:
        with_dist = [c for c in candidates if c[1] is not None]
        return (with_dist or candidates)[0]
    if len(numeric_rows) == 1 and len(numeric_rows[0]) == 4:
        return tuple(numeric_rows[0]), None
    if len(numeric_rows) == 3 and all(len(r) == 3 for r in numeric_rows):
        k = numeric_rows
        return (k[0][0], k[1][1], k[0][2], k[1][2]), None
    raise ReconInputError(
        f"{path}: no intrinsics found (expected 'fx=.. fy=.. cx=.. cy=..', 4 numbers or a 3x3 matrix)"
    )


def sequence_intrinsics(root: Path) -> tuple[tuple[float, ...], tuple[float, ...] | None]:
    """Intrinsics of a TUM sequence: intrinsics.txt, else by freiburg number in the name, else ROS default."""
    if (root / "intrinsics.txt").is_file():
        return parse_intrinsics_txt(root / "intrinsics.txt")
    match = re.search(r"(?:freiburg|fr)([123])", root.resolve().name.lower())
    if match:
        return PUBLISHED[f"fr{match.group(1)}"]
    return ROS_DEFAULT, None


def open_tum(root, max_diff: float = 0.02, max_gap: float = 0.1) -> RGBDDataset:
    """Open a TUM RGB-D sequence folder.

    max_diff: largest colour/depth/ground-truth time difference accepted (s);
    max_gap: largest gap between ground-truth samples interpolated across (s).
    """
    root = Path(root)
    if (root / "rgb.txt").is_file():
        rgb_ts, rgb_names, _ = read_list(root / "rgb.txt")
        depth_names = None
        if (root / "depth.txt").is_file():
            depth_ts, d_names, _ = read_list(root / "depth.txt")
            qi, ri = associate_timestamps(rgb_ts, depth_ts, max_diff)
            if qi.size == 0:
                raise ReconInputError(f"{root / 'depth.txt'}: no depth timestamp within {max_diff} s of any in rgb.txt")
            rgb_ts, rgb_names = rgb_ts[qi], [rgb_names[i] for i in qi]
            depth_names = [d_names[j] for j in ri]
    elif (root / "rgbd_assoc.txt").is_file():
        rgb_ts, rgb_names, depth_names = read_assoc(root / "rgbd_assoc.txt")
    else:
        raise ReconInputError(f"{root}: not a TUM sequence (no rgb.txt or rgbd_assoc.txt)")

    rgb_paths = [root / n for n in rgb_names]
    depth_paths = None if depth_names is None else [root / n for n in depth_names]
    check_exist(rgb_paths, root / "rgb.txt")
    if depth_paths is not None:
        check_exist(depth_paths, root / "depth.txt")

    poses = valid = None
    gt_path = root / "groundtruth.txt"
    if gt_path.is_file():
        gt = read_tum(gt_path)
        poses, valid = interpolate_poses(rgb_ts, gt.timestamps, gt.poses, max_gap=max_gap, max_diff=max_diff)
        if not valid.any():
            raise ReconInputError(f"{gt_path}: no ground-truth timestamp within {max_diff} s of the colour frames")

    intrinsics, distortion = sequence_intrinsics(root)
    height, width = image_shape(rgb_paths[0])
    return RGBDDataset(
        kind="tum",
        name=root.resolve().name,
        root=root,
        frame_ids=[f"{t:.6f}" for t in rgb_ts],
        intrinsics=tuple(float(v) for v in intrinsics),
        width=width,
        height=height,
        rgb_paths=rgb_paths,
        depth_paths=depth_paths,
        poses=poses,
        pose_valid=valid,
        timestamps=np.asarray(rgb_ts, dtype=np.float64),
        depth_scale=DEPTH_SCALE,
        distortion=distortion,
    )
