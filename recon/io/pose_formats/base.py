"""What every pose-file reader and writer shares: :class:`PoseData`, one-line errors that
name the file and line at fault, the text-parsing helpers, the check of parsed poses, and
atomic writes (a reader never sees half a file).

The formats themselves live in :mod:`recon.io.pose_formats.trajectories` (TUM, per-frame matrices,
Open3D log, nerfstudio, and the ``read_poses`` / ``write_poses`` entry points) and
:mod:`recon.io.pose_formats.colmap` (COLMAP models).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import rotation_errors

# Tolerance on max |R^T R - I| after parsing: text files often carry 6-7 significant digits.
ROTATION_TOL = 1e-3
# COLMAP and nerfstudio put the centre of an image's first pixel at (0.5, 0.5), the project
# (like OpenCV) at (0, 0): their principal point is this much larger than ours.
PIXEL_CENTRE = 0.5


@dataclass
class PoseData:
    """Camera-to-world poses read from a pose file, plus what the format carries.

    ``poses``: (N, 4, 4) float64, camera-to-world, OpenCV axes; NaN where ``valid`` is False.
    ``names``: (N,) frame names (image file names, per-frame file stems) or None.
    ``timestamps``: (N,) float64 seconds or None.
    ``intrinsics``: ``{"fx", "fy", "cx", "cy", "width", "height"}`` (first camera) or None;
    COLMAP adds ``"model"`` and ``"distortion"`` (OpenCV's (k1, k2, p1, p2, k3), zeros for a
    pinhole camera, None for a lens model OpenCV's cannot express, e.g. a fisheye).
    ``valid``: (N,) bool, False for poses the file marks invalid.
    ``frame_intrinsics``: (N, 4) per-frame (fx, fy, cx, cy) when the frames have different
    cameras (a COLMAP model with a camera per image), else None.
    ``frame_distortion``: (N, 5) per-frame distortion as ``intrinsics["distortion"]``, with
    ``frame_intrinsics``; NaN rows for cameras whose distortion is None.
    """

    poses: np.ndarray
    fmt: str
    path: Path
    names: list[str] | None = None
    timestamps: np.ndarray | None = None
    intrinsics: dict | None = None
    valid: np.ndarray | None = field(default=None)
    frame_intrinsics: np.ndarray | None = None
    frame_distortion: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = np.isfinite(self.poses).all(axis=(1, 2))

    def __len__(self) -> int:
        return len(self.poses)


# --------------------------------------------------------------------------------------
# Parsing and checking
# --------------------------------------------------------------------------------------


def input_error(path, message: str, line: int | None = None) -> ReconInputError:
    """A one-line input error naming the file (and line)."""
    where = f"{path}:{line}" if line is not None else f"{path}"
    return ReconInputError(f"{where}: {message}")


def read_text(path: Path) -> str:
    """Whole text of `path`, with a one-line error when it is missing or unreadable."""
    if not path.is_file():
        raise input_error(path, "file not found")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise input_error(path, f"cannot read ({type(exc).__name__}: {exc})") from None


def data_lines(path: Path, text: str | None = None) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each non-blank, non-comment line; commas count as spaces."""
    text = read_text(path) if text is None else text
    out = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            out.append((lineno, line.replace(",", " ").split()))
    return out


def parse_floats(path: Path, lineno: int, tokens: Sequence[str]) -> list[float]:
    """Tokens as floats, or a one-line error quoting the first non-numeric one."""
    try:
        return [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise input_error(path, f"non-numeric value {bad!r}", lineno) from None


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def parse_row(path, lineno: int, tokens: list[str], ncols: int, what: str) -> np.ndarray:
    """The numbers of one data line, checked: exactly `ncols` of them (`what` names them in
    the message), all finite."""
    if len(tokens) != ncols:
        raise input_error(path, f"expected {ncols} {what}, got {len(tokens)}", lineno)
    values = parse_floats(path, lineno, tokens)
    if not np.isfinite(values).all():
        raise input_error(path, "non-finite value (nan/inf)", lineno)
    return values


def parse_table(path: Path, ncols: int, columns: str, text: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Numeric table (N, ncols) float64 and its 1-based line numbers (N,) from a text file.

    Every data line must have exactly `ncols` finite numbers (`columns` names them in errors).
    """
    rows, linenos = [], []
    for lineno, tokens in data_lines(path, text):
        rows.append(parse_row(path, lineno, tokens, ncols, f"columns ({columns})"))
        linenos.append(lineno)
    if not rows:
        raise input_error(path, f"no data lines ({columns})")
    return np.asarray(rows, dtype=np.float64), np.asarray(linenos)


def check_poses(poses: np.ndarray, path, locations: Sequence[str], valid: np.ndarray | None = None) -> None:
    """Raise naming the first pose whose rotation is not orthonormal or whose last row is off.

    `locations[i]` says where pose i came from ("line 12", "frame 3 ('a.png')").
    """
    valid = np.ones(len(poses), bool) if valid is None else valid
    err = rotation_errors(np.where(valid[:, None, None], poses[:, :3, :3], np.eye(3)))
    bad = np.flatnonzero(~(err <= ROTATION_TOL))
    if bad.size:
        i = bad[0]
        detail = "det <= 0 (reflection)" if np.isinf(err[i]) else f"max |R^T R - I| = {err[i]:.2g}"
        raise ReconInputError(f"{path}: {locations[i]}: rotation is not orthonormal ({detail} > {ROTATION_TOL:g})")
    last = np.abs(poses[:, 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    bad = np.flatnonzero(valid & ~(last <= 1e-6))
    if bad.size:
        raise ReconInputError(f"{path}: {locations[bad[0]]}: last row of the 4x4 pose must be 0 0 0 1")


def normalise_intrinsics(intrinsics) -> dict | None:
    """Normalise intrinsics given as a mapping or a (fx, fy, cx, cy[, width, height]) sequence."""
    if intrinsics is None:
        return None
    if isinstance(intrinsics, Mapping):
        out = {k: float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy")}
        for k in ("width", "height"):
            if intrinsics.get(k) is not None:
                out[k] = int(intrinsics[k])
        return out
    values = list(intrinsics)
    if len(values) not in (4, 6):
        raise ValueError("intrinsics must be (fx, fy, cx, cy) or (fx, fy, cx, cy, width, height)")
    out = dict(zip(("fx", "fy", "cx", "cy"), map(float, values[:4])))
    if len(values) == 6:
        out["width"], out["height"] = int(values[4]), int(values[5])
    return out


# --------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------


def atomic_write_text(path: Path, text: str) -> None:
    """Write `text` to a temp name beside `path`, then rename, so readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def move_files_into(src_dir: Path, dst_dir: Path) -> None:
    """Rename every file of `src_dir` into `dst_dir` (same file system: atomic per file)."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    for f in src_dir.iterdir():
        os.replace(f, dst_dir / f.name)

