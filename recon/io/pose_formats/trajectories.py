"""Camera pose files: read and write camera-to-world trajectories in common formats.

This module owns the pose-file formats (``fmt``: ``tum``, ``colmap``, ``nerfstudio``,
``matrices``, ``log``, ``kitti``) and their two entry points, :func:`read_poses` (format
detection included) and :func:`write_poses`. Every reader returns
:class:`~recon.io.pose_formats.base.PoseData` whose ``poses`` are camera-to-world (N, 4, 4)
float64 with OpenCV camera axes, whatever the file's convention. Errors are one line naming
the file and line (or frame); files are written atomically. What the formats share is in
:mod:`recon.io.pose_formats.base`, COLMAP models in :mod:`recon.io.pose_formats.colmap`.
More: docs/input.md#pose-files
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import make_poses, matrix_to_quat, opencv_to_opengl, opengl_to_opencv, quat_to_matrix
from recon.io.naming import natural_key
from recon.io.pose_formats.base import (
    PIXEL_CENTRE,
    PoseData,
    atomic_write_text,
    check_poses,
    data_lines,
    input_error,
    normalise_intrinsics,
    parse_floats,
    parse_row,
    parse_table,
    read_text,
)
from recon.io.pose_formats.colmap import colmap_model_dir, read_colmap, write_colmap

FORMATS = ("tum", "colmap", "nerfstudio", "matrices", "log", "kitti")
FORMAT_NAMES = {"tum": "a TUM trajectory", "matrices": "a 4x4 matrix file", "log": "an Open3D .log trajectory",
                "kitti": "a KITTI pose file"}

_TUM_COLUMNS = "timestamp tx ty tz qx qy qz qw"


# --------------------------------------------------------------------------------------
# TUM
# --------------------------------------------------------------------------------------


def read_tum(path) -> PoseData:
    """TUM trajectory ``timestamp tx ty tz qx qy qz qw`` (camera-to-world) -> PoseData."""
    path = Path(path)
    table, linenos = parse_table(path, 8, _TUM_COLUMNS)
    rot = quat_to_matrix(table[:, 4:8], path, linenos)
    return PoseData(make_poses(rot, table[:, 1:4]), "tum", path, timestamps=table[:, 0].copy())


def write_tum(path, poses: np.ndarray, timestamps=None) -> None:
    """Write (N, 4, 4) camera-to-world poses as a TUM trajectory; timestamps default to 0..N-1."""
    path = Path(path)
    ts = np.arange(len(poses), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    quat = matrix_to_quat(poses[:, :3, :3])
    table = np.column_stack([ts, poses[:, :3, 3], quat])
    lines = ["# " + _TUM_COLUMNS] + [
        f"{r[0]:.6f} " + " ".join(f"{v:.9f}" for v in r[1:]) for r in table
    ]
    atomic_write_text(path, "\n".join(lines) + "\n")


# --------------------------------------------------------------------------------------
# Per-frame 4x4 matrix files
# --------------------------------------------------------------------------------------


def read_matrix_file(path, allow_invalid: bool = False) -> np.ndarray:
    """One 4x4 (or 3x4) pose from a text file -> (4, 4) float64.

    Non-finite entries (ScanNet writes -inf rows for lost tracking) raise unless
    `allow_invalid`, in which case the pose comes back all NaN.
    """
    path = Path(path)
    rows = []
    for lineno, tokens in data_lines(path):
        if len(tokens) != 4:
            raise input_error(path, f"expected 4 numbers per row of a 4x4 pose, got {len(tokens)}", lineno)
        rows.append(parse_floats(path, lineno, tokens))
    if len(rows) == 3:
        rows.append([0.0, 0.0, 0.0, 1.0])
    if len(rows) != 4:
        raise input_error(path, f"expected 4 rows of a 4x4 pose, got {len(rows)}")
    pose = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(pose).all():
        if not allow_invalid:
            raise input_error(path, "pose has non-finite values (invalid pose)")
        return np.full((4, 4), np.nan)
    return pose


def _matrix_files(folder: Path) -> list[Path]:
    """Pose files of a folder, naturally sorted; ``*.pose.txt`` only when there are any."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix == ".txt" and not p.name.startswith(".")]
    tagged = [p for p in files if p.name.endswith(".pose.txt")]
    files = tagged or files
    return sorted(files, key=lambda p: natural_key(p.name))


def read_matrix_folder(path, allow_invalid: bool = True) -> PoseData:
    """Folder of per-frame 4x4 camera-to-world text files -> PoseData; names are file names minus '.txt'."""
    path = Path(path)
    if path.is_file():
        files = [path]
    elif path.is_dir():
        files = _matrix_files(path)
    else:
        raise input_error(path, "folder not found")
    if not files:
        raise input_error(path, "no *.txt pose files in folder")
    poses = np.stack([read_matrix_file(f, allow_invalid) for f in files])
    names = [f.name[: -len(".txt")] for f in files]
    valid = np.isfinite(poses).all(axis=(1, 2))
    check_poses(poses, path, [f"file {f.name}" for f in files], valid)
    return PoseData(poses, "matrices", path, names=names, valid=valid)


def write_matrix_folder(path, poses: np.ndarray, names: Sequence[str] | None = None) -> None:
    """One ``<name>.txt`` 4x4 file per pose in folder `path`; NaN poses are written as -inf rows (ScanNet)."""
    path = Path(path)
    names = [f"{i:06d}" for i in range(len(poses))] if names is None else list(names)
    for pose, name in zip(poses, names):
        pose = np.where(np.isfinite(pose), pose, -np.inf)
        text = "\n".join(" ".join(f"{v:.10g}" for v in row) for row in pose) + "\n"
        atomic_write_text(path / f"{name}.txt", text)


# --------------------------------------------------------------------------------------
# Open3D / Redwood .log
# --------------------------------------------------------------------------------------


def read_log(path) -> PoseData:
    """Open3D/Redwood trajectory .log (3 metadata integers, then 4 rows per pose) -> PoseData.

    Names are the first metadata integer (the frame index) as a string.
    """
    path = Path(path)
    lines = data_lines(path)
    if not lines:
        raise input_error(path, "no poses in trajectory log")
    poses, names, locations = [], [], []
    for k in range(0, len(lines), 5):
        lineno, meta = lines[k]
        if len(meta) != 3:
            raise input_error(path, f"expected 3 metadata integers before a pose, got {len(meta)} values", lineno)
        meta_vals = parse_floats(path, lineno, meta)
        block = lines[k + 1 : k + 5]
        if len(block) < 4:
            raise input_error(path, f"truncated pose: expected 4 matrix rows after metadata, got {len(block)}", lineno)
        rows = []
        for row_lineno, tokens in block:
            rows.append(parse_row(path, row_lineno, tokens, 4, "numbers per matrix row"))
        poses.append(rows)
        names.append(str(int(meta_vals[0])))
        locations.append(f"line {block[0][0]}")
    poses = np.asarray(poses, dtype=np.float64)
    check_poses(poses, path, locations)
    return PoseData(poses, "log", path, names=names)


def write_log(path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) camera-to-world poses as an Open3D .log (metadata ``i i i+1`` like Open3D)."""
    out = []
    for i, pose in enumerate(poses):
        out.append(f"{i} {i} {i + 1}")
        out.extend(" ".join(f"{v:.10f}" for v in row) for row in pose)
    atomic_write_text(Path(path), "\n".join(out) + "\n")


# --------------------------------------------------------------------------------------
# KITTI odometry poses
# --------------------------------------------------------------------------------------

_KITTI_COLUMNS = "r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz"


def read_kitti(path) -> PoseData:
    """KITTI pose file (12 numbers a line: 3x4 camera-to-world, row-major) -> PoseData."""
    path = Path(path)
    table, linenos = parse_table(path, 12, _KITTI_COLUMNS)
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :] = table.reshape(-1, 3, 4)
    check_poses(poses, path, [f"line {n}" for n in linenos])
    return PoseData(poses, "kitti", path)


def write_kitti(path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) camera-to-world poses as a KITTI pose file (KITTI's own %e precision is
    not enough for a round trip, so 11 significant digits)."""
    rows = np.asarray(poses, dtype=np.float64)[:, :3, :].reshape(-1, 12)
    atomic_write_text(Path(path), "".join(" ".join(f"{v:.10e}" for v in r) + "\n" for r in rows))


# --------------------------------------------------------------------------------------
# nerfstudio transforms.json
# --------------------------------------------------------------------------------------


def _json_intrinsics(block: Mapping) -> dict | None:
    """Intrinsics dict from nerfstudio keys (fl_x fl_y cx cy w h) when all four are there, the
    principal point in the project's pixel convention (pose_files.PIXEL_CENTRE)."""
    if not all(k in block for k in ("fl_x", "cx", "cy")):
        return None
    out = {
        "fx": float(block["fl_x"]),
        "fy": float(block.get("fl_y", block["fl_x"])),
        "cx": float(block["cx"]) - PIXEL_CENTRE,
        "cy": float(block["cy"]) - PIXEL_CENTRE,
    }
    if "w" in block and "h" in block:
        out["width"], out["height"] = int(block["w"]), int(block["h"])
    return out


def read_nerfstudio(path) -> PoseData:
    """nerfstudio ``transforms.json`` (OpenGL camera axes) -> PoseData with OpenCV axes."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    text = read_text(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise input_error(path, f"invalid JSON ({exc.msg}, column {exc.colno})", exc.lineno) from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise input_error(path, "no 'frames' list")
    poses, names = [], []
    for i, frame in enumerate(frames):
        named = isinstance(frame, dict) and "file_path" in frame
        label = f"frame {i}" + (f" ({frame['file_path']!r})" if named else "")
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            raise ReconInputError(f"{path}: {label}: missing 'transform_matrix'")
        try:
            m = np.asarray(frame["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ReconInputError(f"{path}: {label}: transform_matrix is not numeric") from None
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise ReconInputError(f"{path}: {label}: transform_matrix must be 4x4, got shape {m.shape}")
        if not np.isfinite(m).all():
            raise ReconInputError(f"{path}: {label}: transform_matrix has non-finite values")
        poses.append(m)
        names.append(str(frame.get("file_path", f"{i}")))
    poses = np.stack(poses)
    check_poses(poses, path, [f"frame {i} ({n!r})" for i, n in enumerate(names)])
    intrinsics = _json_intrinsics(data) or _json_intrinsics(frames[0])
    return PoseData(opengl_to_opencv(poses), "nerfstudio", path, names=names, intrinsics=intrinsics)


def write_nerfstudio(path, poses: np.ndarray, names: Sequence[str] | None = None, intrinsics=None) -> None:
    """Write camera-to-world OpenCV poses (N, 4, 4) as nerfstudio ``transforms.json`` (OpenGL axes)."""
    path = Path(path)
    if path.suffix != ".json":
        path = path / "transforms.json"
    names = [f"images/frame_{i + 1:05d}.png" for i in range(len(poses))] if names is None else list(names)
    data: dict = {"camera_model": "OPENCV"}
    intr = normalise_intrinsics(intrinsics)
    if intr is not None:
        data.update(fl_x=intr["fx"], fl_y=intr["fy"], cx=intr["cx"] + PIXEL_CENTRE, cy=intr["cy"] + PIXEL_CENTRE)
        if "width" in intr:
            data.update(w=intr["width"], h=intr["height"])
    gl = opencv_to_opengl(poses)
    data["frames"] = [{"file_path": n, "transform_matrix": m.tolist()} for n, m in zip(names, gl)]
    atomic_write_text(path, json.dumps(data, indent=2) + "\n")


# --------------------------------------------------------------------------------------
# Detection and the two entry points
# --------------------------------------------------------------------------------------


def detect_pose_format(path) -> str:
    """Format name of a pose file or folder (one of FORMATS); one-line error when unknown."""
    return _detect(Path(path))[0]


def _detect(path: Path) -> tuple[str, str | None]:
    """(format, why): why is the evidence for a text file's format (None for formats told by
    name or layout), so that a file which then does not parse can say what was assumed."""
    if not path.exists():
        raise input_error(path, "no such file or folder")
    if path.is_dir():
        if colmap_model_dir(path) is not None:
            return "colmap", None
        if (path / "transforms.json").is_file():
            return "nerfstudio", None
        if _matrix_files(path):
            return "matrices", None
        raise input_error(path, "folder holds no recognised poses (COLMAP model, transforms.json, *.txt 4x4 files)")
    if path.suffix == ".json":
        return "nerfstudio", None
    if path.suffix == ".log":
        return "log", None
    if path.name in ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt"):
        return "colmap", None
    return _text_format(path)


def _text_format(path: Path) -> tuple[str, str]:
    """(format, why) of a text pose file from the column counts of all its data lines (one
    odd line, such as a first line with 4 numbers in a TUM file, does not decide it)."""
    widths = [len(t) for _, t in data_lines(path)]
    if not widths:
        raise input_error(path, "unknown pose file format (no data lines)")
    eights = sum(w == 8 for w in widths)
    if eights * 2 >= len(widths):
        return "tum", f"{eights} of {len(widths)} lines have 8 numbers"
    twelves = sum(w == 12 for w in widths)
    if twelves * 2 >= len(widths):
        return "kitti", f"{twelves} of {len(widths)} lines have 12 numbers"
    if widths[0] == 3 and len(widths) % 5 == 0 and all(w == 4 for k, w in enumerate(widths) if k % 5):
        return "log", "blocks of a 3-number line and four 4-number lines"
    fours = sum(w == 4 for w in widths)
    if len(widths) <= 5 and fours * 2 >= len(widths):
        return "matrices", f"{fours} of {len(widths)} lines have 4 numbers"
    counts = ", ".join(f"{widths.count(w)} lines of {w}" for w in sorted(set(widths)))
    raise input_error(path, f"unknown pose file format ({counts} numbers; TUM has 8 per line, KITTI 12, a 4x4 "
                            "matrix file 4 lines of 4, an Open3D .log blocks of 3 + 4x4)")


def read_poses(path, fmt: str | None = None) -> PoseData:
    """Read camera-to-world poses (OpenCV axes) from `path`; `fmt` is auto-detected when None."""
    path = Path(path)
    why = None
    if fmt is None:
        fmt, why = _detect(path)
    readers = {
        "tum": read_tum,
        "colmap": read_colmap,
        "nerfstudio": read_nerfstudio,
        "matrices": read_matrix_folder,
        "log": read_log,
        "kitti": read_kitti,
    }
    if fmt not in readers:
        raise ValueError(f"unknown pose format {fmt!r}; expected one of {FORMATS}")
    if not path.exists():
        raise input_error(path, "no such file or folder")
    try:
        return readers[fmt](path)
    except ReconInputError as error:
        if why is None:
            raise
        raise ReconInputError(f"{error} (read as {FORMAT_NAMES.get(fmt, fmt)}: {why})") from None


def write_poses(path, poses, fmt: str, names=None, timestamps=None, intrinsics=None) -> None:
    """Write camera-to-world poses (N, 4, 4) (OpenCV axes) to `path` in format `fmt`.

    names: (N,) frame names (COLMAP/nerfstudio image names, per-frame file stems);
    timestamps: (N,) seconds (TUM); intrinsics: mapping or (fx, fy, cx, cy[, width, height])
    (COLMAP needs width and height). Only "matrices" can store invalid (NaN) poses.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must be (N, 4, 4), got {poses.shape}")
    n = len(poses)
    for label, seq in (("names", names), ("timestamps", timestamps)):
        if seq is not None and len(seq) != n:
            raise ValueError(f"{label} has {len(seq)} entries for {n} poses")
    valid = np.isfinite(poses).all(axis=(1, 2))
    if fmt != "matrices" and not valid.all():
        first = int(np.flatnonzero(~valid)[0])
        raise ValueError(f"pose {first} is not finite; only 'matrices' can store invalid poses")
    check_poses(poses, "<poses to write>", [f"pose {i}" for i in range(n)], valid)
    if fmt == "tum":
        write_tum(path, poses, timestamps)
    elif fmt == "colmap":
        write_colmap(path, poses, names, intrinsics)
    elif fmt == "nerfstudio":
        write_nerfstudio(path, poses, names, intrinsics)
    elif fmt == "matrices":
        write_matrix_folder(path, poses, names)
    elif fmt == "log":
        write_log(path, poses)
    elif fmt == "kitti":
        write_kitti(path, poses)
    else:
        raise ValueError(f"unknown pose format {fmt!r}; expected one of {FORMATS}")
