"""Camera pose files: read and write camera-to-world trajectories in common formats.

This module owns pose *files*: format detection, parsing with one-line errors that name the
file and line (or frame) at fault, atomic writing, and the time bookkeeping that goes with
them (associating timestamps, interpolating a trajectory at new timestamps).

Every reader returns :class:`PoseData` whose ``poses`` are camera-to-world (N, 4, 4) float64
with OpenCV camera axes (x right, y down, z forward), whatever the file's own convention.

Formats (the ``fmt`` names):

* ``"tum"``: TUM RGB-D trajectory text, ``timestamp tx ty tz qx qy qz qw`` per line,
  camera-to-world.
* ``"colmap"``: a COLMAP sparse model folder (``cameras``/``images`` as .bin or .txt);
  COLMAP stores world-to-camera (``cam_from_world``). Uses pycolmap when installed; text
  models are also read and written without it.
* ``"nerfstudio"``: ``transforms.json``; ``transform_matrix`` is camera-to-world with
  OpenGL camera axes (x right, y up, z back); intrinsics ``fl_x fl_y cx cy w h``.
* ``"matrices"``: a folder of per-frame 4x4 text files (7-Scenes ``frame-000000.pose.txt``,
  ScanNet ``pose/0.txt``), camera-to-world; rows of -inf/nan mark an invalid pose.
* ``"log"``: Open3D / Redwood trajectory ``.log``: per pose one line of 3 integers of
  metadata, then the 4 rows of the camera-to-world matrix.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError

FORMATS = ("tum", "colmap", "nerfstudio", "matrices", "log")

# Tolerance on max |R^T R - I| after parsing: text files often carry 6-7 significant digits.
ROTATION_TOL = 1e-3
# Quaternions shorter than this are noise, not a rotation, and cannot be normalised.
MIN_QUAT_NORM = 1e-6
# OpenGL <-> OpenCV camera axes: flip y and z (its own inverse).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

_TUM_COLUMNS = "timestamp tx ty tz qx qy qz qw"
# COLMAP camera models whose first parameters are (f, cx, cy) rather than (fx, fy, cx, cy).
_COLMAP_SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}


@dataclass
class PoseData:
    """Camera-to-world poses read from a pose file, plus what the format carries.

    ``poses``: (N, 4, 4) float64, camera-to-world, OpenCV axes; NaN where ``valid`` is False.
    ``names``: (N,) frame names (image file names, per-frame file stems) or None.
    ``timestamps``: (N,) float64 seconds or None.
    ``intrinsics``: ``{"fx", "fy", "cx", "cy", "width", "height"}`` (first camera) or None.
    ``valid``: (N,) bool, False for poses the file marks invalid.
    """

    poses: np.ndarray
    fmt: str
    path: Path
    names: list[str] | None = None
    timestamps: np.ndarray | None = None
    intrinsics: dict | None = None
    valid: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = np.isfinite(self.poses).all(axis=(1, 2))

    def __len__(self) -> int:
        return len(self.poses)


# --------------------------------------------------------------------------------------
# Small helpers: errors, parsing, validation, rotations
# --------------------------------------------------------------------------------------


def _fail(path, message: str, line: int | None = None) -> ReconInputError:
    """A one-line input error naming the file (and line)."""
    where = f"{path}:{line}" if line is not None else f"{path}"
    return ReconInputError(f"{where}: {message}")


def _read_text(path: Path) -> str:
    """Whole text of `path`, with a one-line error when it is missing or unreadable."""
    if not path.is_file():
        raise _fail(path, "file not found")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(path, f"cannot read ({type(exc).__name__}: {exc})") from None


def _data_lines(path: Path, text: str | None = None) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each non-blank, non-comment line; commas count as spaces."""
    text = _read_text(path) if text is None else text
    out = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            out.append((lineno, line.replace(",", " ").split()))
    return out


def _floats(path: Path, lineno: int, tokens: Sequence[str]) -> list[float]:
    """Tokens as floats, or a one-line error quoting the first non-numeric one."""
    try:
        return [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise _fail(path, f"non-numeric value {bad!r}", lineno) from None


def _is_float(token: str) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def _parse_table(path: Path, ncols: int, columns: str, text: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Numeric table (N, ncols) float64 and its 1-based line numbers (N,) from a text file.

    Every data line must have exactly `ncols` finite numbers (`columns` names them in errors).
    """
    rows, linenos = [], []
    for lineno, tokens in _data_lines(path, text):
        if len(tokens) != ncols:
            raise _fail(path, f"expected {ncols} columns ({columns}), got {len(tokens)}", lineno)
        values = _floats(path, lineno, tokens)
        if not np.isfinite(values).all():
            raise _fail(path, "non-finite value (nan/inf)", lineno)
        rows.append(values)
        linenos.append(lineno)
    if not rows:
        raise _fail(path, f"no data lines ({columns})")
    return np.asarray(rows, dtype=np.float64), np.asarray(linenos)


def rotation_errors(rotations: np.ndarray) -> np.ndarray:
    """Orthonormality error max |R^T R - I| of rotations (N, 3, 3) -> (N,); inf if det <= 0."""
    rotations = np.asarray(rotations, dtype=np.float64)
    gram = np.einsum("nji,njk->nik", rotations, rotations)
    err = np.abs(gram - np.eye(3)).max(axis=(1, 2))
    # A reflection is orthonormal but is not a camera rotation.
    return np.where(np.linalg.det(rotations) > 0, err, np.inf)


def _check_poses(poses: np.ndarray, path, locations: Sequence[str], valid: np.ndarray | None = None) -> None:
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


def quat_to_matrix(quats_xyzw: np.ndarray, path=None, linenos: Sequence[int] | None = None) -> np.ndarray:
    """Rotation matrices (N, 3, 3) from quaternions (N, 4) ``qx qy qz qw``, normalising them.

    Quaternions of near-zero norm raise, naming `path` and the line when given.
    """
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(norm < MIN_QUAT_NORM)
    if bad.size:
        line = None if linenos is None else int(linenos[bad[0]])
        where = path if path is not None else "<quaternions>"
        raise _fail(where, f"quaternion has near-zero norm ({norm[bad[0]]:.2g})", line)
    return Rotation.from_quat(q / norm[:, None]).as_matrix()


def matrix_to_quat(rotations: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) ``qx qy qz qw`` with qw >= 0 from rotation matrices (N, 3, 3)."""
    q = Rotation.from_matrix(np.asarray(rotations, dtype=np.float64)).as_quat()
    # q and -q are the same rotation; a fixed sign makes written files reproducible.
    return np.where(q[:, 3:4] < 0, -q, q)


def make_poses(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """4x4 poses (N, 4, 4) from rotations (N, 3, 3) and translations (N, 3)."""
    n = len(rotations)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = translations
    return poses


def invert_poses(poses: np.ndarray) -> np.ndarray:
    """Inverse of rigid 4x4 transforms (N, 4, 4) (camera-to-world <-> world-to-camera)."""
    rot_t = np.swapaxes(poses[:, :3, :3], 1, 2)
    return make_poses(rot_t, -np.einsum("nij,nj->ni", rot_t, poses[:, :3, 3]))


def opengl_to_opencv(poses: np.ndarray) -> np.ndarray:
    """Camera-to-world (N, 4, 4) with OpenGL camera axes -> OpenCV axes (and back: same op)."""
    return np.asarray(poses, dtype=np.float64) @ GL_TO_CV


opencv_to_opengl = opengl_to_opencv


def _natural_key(name: str) -> list:
    """Sort key that orders 'frame-2' before 'frame-10'."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _intrinsics_dict(intrinsics) -> dict | None:
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


def _atomic_write_text(path: Path, text: str) -> None:
    """Write `text` to a temp name beside `path`, then rename, so readers never see half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _move_files_into(src_dir: Path, dst_dir: Path) -> None:
    """Rename every file of `src_dir` into `dst_dir` (same file system: atomic per file)."""
    dst_dir.mkdir(parents=True, exist_ok=True)
    for f in src_dir.iterdir():
        os.replace(f, dst_dir / f.name)


# --------------------------------------------------------------------------------------
# Timestamps
# --------------------------------------------------------------------------------------


def associate_timestamps(
    query, reference, max_diff: float = 0.02, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matches between two timestamp lists, closest pairs first (TUM's associate.py).

    query: (N,), reference: (M,) seconds; a pair (i, j) is allowed when
    ``|query[i] - (reference[j] + offset)| < max_diff``. Returns index arrays (K,), (K,)
    ordered by query index.
    """
    q = np.asarray(query, dtype=np.float64).ravel()
    r = np.asarray(reference, dtype=np.float64).ravel() + offset
    order = np.argsort(r, kind="stable")
    rs = r[order]
    lo = np.searchsorted(rs, q - max_diff, side="left")
    hi = np.searchsorted(rs, q + max_diff, side="right")
    counts = hi - lo
    qi = np.repeat(np.arange(len(q)), counts)
    # Index of each candidate inside its query's window [lo, hi).
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    rj = np.repeat(lo, counts) + within
    diff = np.abs(q[qi] - rs[rj])
    keep = diff < max_diff
    qi, rj, diff = qi[keep], rj[keep], diff[keep]
    # Greedy one-to-one matching is inherently sequential; the loop runs over the few
    # candidate pairs inside the window, not over all N x M combinations.
    used_q = np.zeros(len(q), bool)
    used_r = np.zeros(len(r), bool)
    pick = []
    for k in np.argsort(diff, kind="stable"):
        if not used_q[qi[k]] and not used_r[rj[k]]:
            used_q[qi[k]] = used_r[rj[k]] = True
            pick.append(k)
    pick = np.asarray(pick, dtype=np.int64)
    out_q, out_r = qi[pick], order[rj[pick]]
    s = np.argsort(out_q, kind="stable")
    return out_q[s], out_r[s]


def interpolate_poses(
    query_ts, ref_ts, ref_poses: np.ndarray, max_gap: float = 0.1, max_diff: float = 0.02, snap: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at `query_ts` (M,) from a trajectory sampled at `ref_ts` (N,) with `ref_poses` (N, 4, 4).

    A sample within `snap` s is taken as is (for timestamps that differ only by rounding).
    Else, between two samples at most `max_gap` s apart: SLERP of rotation, linear
    translation. Otherwise (outside the trajectory or across a gap): the nearest sample when
    within `max_diff` s. Returns poses (M, 4, 4) (NaN where none applies) and valid (M,) bool.
    """
    q = np.asarray(query_ts, dtype=np.float64).ravel()
    order = np.argsort(np.asarray(ref_ts, dtype=np.float64), kind="stable")
    t = np.asarray(ref_ts, dtype=np.float64)[order]
    ref = np.asarray(ref_poses, dtype=np.float64)[order]
    n = len(t)
    out = np.full((len(q), 4, 4), np.nan)
    if n == 0 or len(q) == 0:
        return out, np.zeros(len(q), bool)
    idx = np.searchsorted(t, q, side="right")  # t[idx-1] <= q < t[idx]
    i0 = np.clip(idx - 1, 0, n - 1)
    i1 = np.clip(idx, 0, n - 1)
    gap = t[i1] - t[i0]
    inside = (idx > 0) & (idx < n) & (gap <= max_gap)
    nearest = np.where(np.abs(q - t[i0]) <= np.abs(t[i1] - q), i0, i1)
    near_dist = np.abs(q - t[nearest])
    inside &= ~(near_dist <= snap)
    near_ok = ~inside & (near_dist <= max(max_diff, snap))

    alpha = np.where(gap > 0, (q - t[i0]) / np.where(gap > 0, gap, 1.0), 0.0)[inside]
    a, b = i0[inside], i1[inside]
    if a.size:
        rot_a = Rotation.from_matrix(ref[a, :3, :3])
        delta = (rot_a.inv() * Rotation.from_matrix(ref[b, :3, :3])).as_rotvec()
        rot = (rot_a * Rotation.from_rotvec(alpha[:, None] * delta)).as_matrix()
        trans = (1 - alpha)[:, None] * ref[a, :3, 3] + alpha[:, None] * ref[b, :3, 3]
        out[inside] = make_poses(rot, trans)
    out[near_ok] = ref[nearest[near_ok]]
    return out, inside | near_ok


# --------------------------------------------------------------------------------------
# TUM
# --------------------------------------------------------------------------------------


def read_tum(path) -> PoseData:
    """TUM trajectory ``timestamp tx ty tz qx qy qz qw`` (camera-to-world) -> PoseData."""
    path = Path(path)
    table, linenos = _parse_table(path, 8, _TUM_COLUMNS)
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
    _atomic_write_text(path, "\n".join(lines) + "\n")


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
    for lineno, tokens in _data_lines(path):
        if len(tokens) != 4:
            raise _fail(path, f"expected 4 numbers per row of a 4x4 pose, got {len(tokens)}", lineno)
        rows.append(_floats(path, lineno, tokens))
    if len(rows) == 3:
        rows.append([0.0, 0.0, 0.0, 1.0])
    if len(rows) != 4:
        raise _fail(path, f"expected 4 rows of a 4x4 pose, got {len(rows)}")
    pose = np.asarray(rows, dtype=np.float64)
    if not np.isfinite(pose).all():
        if not allow_invalid:
            raise _fail(path, "pose has non-finite values (invalid pose)")
        return np.full((4, 4), np.nan)
    return pose


def _matrix_files(folder: Path) -> list[Path]:
    """Pose files of a folder, naturally sorted; ``*.pose.txt`` only when there are any."""
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix == ".txt" and not p.name.startswith(".")]
    tagged = [p for p in files if p.name.endswith(".pose.txt")]
    files = tagged or files
    return sorted(files, key=lambda p: _natural_key(p.name))


def read_matrix_folder(path, allow_invalid: bool = True) -> PoseData:
    """Folder of per-frame 4x4 camera-to-world text files -> PoseData; names are file names minus '.txt'."""
    path = Path(path)
    if path.is_file():
        files = [path]
    elif path.is_dir():
        files = _matrix_files(path)
    else:
        raise _fail(path, "folder not found")
    if not files:
        raise _fail(path, "no *.txt pose files in folder")
    poses = np.stack([read_matrix_file(f, allow_invalid) for f in files])
    names = [f.name[: -len(".txt")] for f in files]
    valid = np.isfinite(poses).all(axis=(1, 2))
    _check_poses(poses, path, [f"file {f.name}" for f in files], valid)
    return PoseData(poses, "matrices", path, names=names, valid=valid)


def write_matrix_folder(path, poses: np.ndarray, names: Sequence[str] | None = None) -> None:
    """One ``<name>.txt`` 4x4 file per pose in folder `path`; NaN poses are written as -inf rows (ScanNet)."""
    path = Path(path)
    names = [f"{i:06d}" for i in range(len(poses))] if names is None else list(names)
    for pose, name in zip(poses, names):
        pose = np.where(np.isfinite(pose), pose, -np.inf)
        text = "\n".join(" ".join(f"{v:.10g}" for v in row) for row in pose) + "\n"
        _atomic_write_text(path / f"{name}.txt", text)


# --------------------------------------------------------------------------------------
# Open3D / Redwood .log
# --------------------------------------------------------------------------------------


def read_log(path) -> PoseData:
    """Open3D/Redwood trajectory .log (3 metadata integers, then 4 rows per pose) -> PoseData.

    Names are the first metadata integer (the frame index) as a string.
    """
    path = Path(path)
    lines = _data_lines(path)
    if not lines:
        raise _fail(path, "no poses in trajectory log")
    poses, names, locations = [], [], []
    for k in range(0, len(lines), 5):
        lineno, meta = lines[k]
        if len(meta) != 3:
            raise _fail(path, f"expected 3 metadata integers before a pose, got {len(meta)} values", lineno)
        meta_vals = _floats(path, lineno, meta)
        block = lines[k + 1 : k + 5]
        if len(block) < 4:
            raise _fail(path, f"truncated pose: expected 4 matrix rows after metadata, got {len(block)}", lineno)
        rows = []
        for row_lineno, tokens in block:
            if len(tokens) != 4:
                raise _fail(path, f"expected 4 numbers per matrix row, got {len(tokens)}", row_lineno)
            values = _floats(path, row_lineno, tokens)
            if not np.isfinite(values).all():
                raise _fail(path, "non-finite value (nan/inf)", row_lineno)
            rows.append(values)
        poses.append(rows)
        names.append(str(int(meta_vals[0])))
        locations.append(f"line {block[0][0]}")
    poses = np.asarray(poses, dtype=np.float64)
    _check_poses(poses, path, locations)
    return PoseData(poses, "log", path, names=names)


def write_log(path, poses: np.ndarray) -> None:
    """Write (N, 4, 4) camera-to-world poses as an Open3D .log (metadata ``i i i+1`` like Open3D)."""
    out = []
    for i, pose in enumerate(poses):
        out.append(f"{i} {i} {i + 1}")
        out.extend(" ".join(f"{v:.10f}" for v in row) for row in pose)
    _atomic_write_text(Path(path), "\n".join(out) + "\n")


# --------------------------------------------------------------------------------------
# nerfstudio transforms.json
# --------------------------------------------------------------------------------------


def _json_intrinsics(block: Mapping) -> dict | None:
    """Intrinsics dict from nerfstudio keys (fl_x fl_y cx cy w h) when all four are there."""
    if not all(k in block for k in ("fl_x", "cx", "cy")):
        return None
    out = {
        "fx": float(block["fl_x"]),
        "fy": float(block.get("fl_y", block["fl_x"])),
        "cx": float(block["cx"]),
        "cy": float(block["cy"]),
    }
    if "w" in block and "h" in block:
        out["width"], out["height"] = int(block["w"]), int(block["h"])
    return out


def read_nerfstudio(path) -> PoseData:
    """nerfstudio ``transforms.json`` (OpenGL camera axes) -> PoseData with OpenCV axes."""
    path = Path(path)
    if path.is_dir():
        path = path / "transforms.json"
    text = _read_text(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise _fail(path, f"invalid JSON ({exc.msg}, column {exc.colno})", exc.lineno) from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise _fail(path, "no 'frames' list")
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
    _check_poses(poses, path, [f"frame {i} ({n!r})" for i, n in enumerate(names)])
    intrinsics = _json_intrinsics(data) or _json_intrinsics(frames[0])
    return PoseData(opengl_to_opencv(poses), "nerfstudio", path, names=names, intrinsics=intrinsics)


def write_nerfstudio(path, poses: np.ndarray, names: Sequence[str] | None = None, intrinsics=None) -> None:
    """Write camera-to-world OpenCV poses (N, 4, 4) as nerfstudio ``transforms.json`` (OpenGL axes)."""
    path = Path(path)
    if path.suffix != ".json":
        path = path / "transforms.json"
    names = [f"images/frame_{i + 1:05d}.png" for i in range(len(poses))] if names is None else list(names)
    data: dict = {"camera_model": "OPENCV"}
    intr = _intrinsics_dict(intrinsics)
    if intr is not None:
        data.update(fl_x=intr["fx"], fl_y=intr["fy"], cx=intr["cx"], cy=intr["cy"])
        if "width" in intr:
            data.update(w=intr["width"], h=intr["height"])
    gl = opencv_to_opengl(poses)
    data["frames"] = [{"file_path": n, "transform_matrix": m.tolist()} for n, m in zip(names, gl)]
    _atomic_write_text(path, json.dumps(data, indent=2) + "\n")


# --------------------------------------------------------------------------------------
# COLMAP
# --------------------------------------------------------------------------------------


def _import_pycolmap(required: bool):
    """pycolmap module, or None (or a one-line error when `required`)."""
    try:
        import pycolmap
    except ImportError:
        if required:
            raise ReconInputError(
                "binary COLMAP models need pycolmap (optional dependency): pip install pycolmap"
            ) from None
        return None
    return pycolmap


def colmap_model_dir(path) -> Path | None:
    """The folder holding cameras.* and images.* for a COLMAP path (model, project or file)."""
    path = Path(path)
    if path.is_file():
        path = path.parent
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        for ext in (".bin", ".txt"):
            if (cand / f"cameras{ext}").is_file() and (cand / f"images{ext}").is_file():
                return cand
    return None


def _colmap_intrinsics(model: str, width: int, height: int, params) -> dict:
    """fx fy cx cy width height of a COLMAP camera (distortion parameters are dropped)."""
    p = [float(v) for v in params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model in _COLMAP_SINGLE_FOCAL else (p[0], p[1], p[2], p[3])
    return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": int(width), "height": int(height), "model": model}


def _read_colmap_pycolmap(pycolmap, model_dir: Path):
    """(names, world-to-camera (N, 3, 4), camera ids, {id: intrinsics}) via pycolmap."""
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises bare RuntimeError/ValueError for corrupt models
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise _fail(model_dir, f"cannot read COLMAP model ({first})") from None
    names, w2c, cam_ids = [], [], []
    for _, img in sorted(rec.images.items(), key=lambda kv: _natural_key(kv[1].name)):
        has_pose = getattr(img, "has_pose", getattr(img, "registered", True))
        cfw = img.cam_from_world
        # pycolmap >= 3.12 turned cam_from_world into a method (poses live on frames).
        cfw = cfw() if callable(cfw) and has_pose else cfw
        w2c.append(np.asarray(cfw.matrix(), np.float64) if has_pose else np.full((3, 4), np.nan))
        names.append(img.name)
        cam_ids.append(img.camera_id)
    cams = {}
    for cid, cam in rec.cameras.items():
        model = cam.model_name if hasattr(cam, "model_name") else str(cam.model).split(".")[-1]
        cams[cid] = _colmap_intrinsics(model, cam.width, cam.height, cam.params)
    return names, w2c, cam_ids, cams


def _read_colmap_text(model_dir: Path):
    """(names, world-to-camera (N, 3, 4), camera ids, {id: intrinsics}) from a text model."""
    cams = {}
    cam_path = model_dir / "cameras.txt"
    for lineno, tokens in _data_lines(cam_path):
        if len(tokens) < 5:
            raise _fail(cam_path, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]", lineno)
        vals = _floats(cam_path, lineno, [tokens[0], *tokens[2:]])
        cams[int(vals[0])] = _colmap_intrinsics(tokens[1], vals[1], vals[2], vals[3:])
    img_path = model_dir / "images.txt"
    lines = _read_text(img_path).splitlines()
    names, w2c, cam_ids = [], [], []
    k = 0
    while k < len(lines):
        line = lines[k].strip()
        if not line or line.startswith("#"):
            k += 1
            continue
        tokens = line.split()
        if len(tokens) < 10:
            raise _fail(img_path, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", k + 1)
        vals = _floats(img_path, k + 1, tokens[1:9])
        rot = quat_to_matrix(np.array([vals[1], vals[2], vals[3], vals[0]]), img_path, [k + 1])[0]
        w2c.append(np.column_stack([rot, vals[4:7]]))
        cam_ids.append(int(vals[7]))
        names.append(" ".join(tokens[9:]))
        k += 2  # the POINTS2D line follows, possibly empty
    return names, w2c, cam_ids, cams


def read_colmap(path) -> PoseData:
    """COLMAP sparse model (binary or text; project, sparse/ or sparse/0 folder) -> PoseData.

    Images are sorted by name; intrinsics are those of the first image's camera.
    """
    path = Path(path)
    model_dir = colmap_model_dir(path)
    if model_dir is None:
        raise _fail(path, "no COLMAP model (cameras.bin/.txt and images.bin/.txt) found")
    binary = (model_dir / "images.bin").is_file()
    pycolmap = _import_pycolmap(required=binary)
    if pycolmap is not None:
        names, w2c, cam_ids, cams = _read_colmap_pycolmap(pycolmap, model_dir)
    else:
        names, w2c, cam_ids, cams = _read_colmap_text(model_dir)
    if not names:
        raise _fail(model_dir, "COLMAP model has no images")
    if pycolmap is None:
        order = sorted(range(len(names)), key=lambda i: _natural_key(names[i]))
        names, w2c, cam_ids = [names[i] for i in order], [w2c[i] for i in order], [cam_ids[i] for i in order]
    w2c = np.stack([np.vstack([m, [0.0, 0.0, 0.0, 1.0]]) for m in w2c])
    valid = np.isfinite(w2c).all(axis=(1, 2))
    _check_poses(w2c, model_dir, [f"image {n!r}" for n in names], valid)
    poses = np.full_like(w2c, np.nan)
    poses[valid] = invert_poses(w2c[valid])
    missing = [c for c in cam_ids if c not in cams]
    if missing:
        raise _fail(model_dir, f"image refers to camera {missing[0]} missing from cameras file")
    return PoseData(poses, "colmap", model_dir, names=names, intrinsics=dict(cams[cam_ids[0]]), valid=valid)


def _colmap_text_model(poses: np.ndarray, names: Sequence[str], intr: dict) -> dict[str, str]:
    """File name -> text of a single-PINHOLE-camera COLMAP text model."""
    w2c = invert_poses(poses)
    q = matrix_to_quat(w2c[:, :3, :3])
    params = " ".join(f"{intr[k]:.17g}" for k in ("fx", "fy", "cx", "cy"))
    cameras = f"# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 PINHOLE {intr['width']} {intr['height']} {params}\n"
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, qi, t) in enumerate(zip(names, q, w2c[:, :3, 3]), start=1):
        nums = " ".join(f"{v:.17g}" for v in (qi[3], qi[0], qi[1], qi[2], *t))
        lines.append(f"{i} {nums} 1 {name}")
        lines.append("")
    points = "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
    return {"cameras.txt": cameras, "images.txt": "\n".join(lines) + "\n", "points3D.txt": points}


def _colmap_reconstruction(pycolmap, poses: np.ndarray, names: Sequence[str], intr: dict):
    """pycolmap.Reconstruction with one PINHOLE camera and one posed image per frame."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="PINHOLE",
        width=intr["width"],
        height=intr["height"],
        params=[intr["fx"], intr["fy"], intr["cx"], intr["cy"]],
        camera_id=1,
    )
    w2c = invert_poses(poses)
    with_rigs = hasattr(rec, "add_camera_with_trivial_rig")  # pycolmap >= 3.12 (rigs and frames)
    if with_rigs:
        rec.add_camera_with_trivial_rig(cam)
    else:
        rec.add_camera(cam)
    for i, (name, m) in enumerate(zip(names, w2c), start=1):
        rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(m[:3, :3]), m[:3, 3])
        img = pycolmap.Image(name=str(name), camera_id=1, image_id=i)
        if with_rigs:
            rec.add_image_with_trivial_frame(img, rigid)
        else:
            img.cam_from_world = rigid
            rec.add_image(img)
            rec.register_image(i)
    return rec


def write_colmap(
    path, poses: np.ndarray, names: Sequence[str] | None = None, intrinsics=None, binary: bool = False
) -> None:
    """Write a COLMAP model (one PINHOLE camera, no points) into folder `path`.

    Text by default (readable without pycolmap); binary needs pycolmap. Files are written to
    a temp folder beside `path` and renamed in.
    """
    path = Path(path)
    intr = _intrinsics_dict(intrinsics)
    if intr is None or "width" not in intr:
        raise ValueError("writing a COLMAP model needs intrinsics (fx, fy, cx, cy, width, height)")
    names = [f"frame_{i:06d}.png" for i in range(len(poses))] if names is None else [str(n) for n in names]
    pycolmap = _import_pycolmap(required=binary)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp", dir=path.parent))
    try:
        if pycolmap is not None:
            rec = _colmap_reconstruction(pycolmap, poses, names, intr)
            (rec.write_binary if binary else rec.write_text)(str(tmp))
        else:
            for fname, text in _colmap_text_model(poses, names, intr).items():
                (tmp / fname).write_text(text, encoding="utf-8")
        _move_files_into(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# --------------------------------------------------------------------------------------
# Detection and the two entry points
# --------------------------------------------------------------------------------------


def detect_pose_format(path) -> str:
    """Format name of a pose file or folder (one of FORMATS); one-line error when unknown."""
    path = Path(path)
    if not path.exists():
        raise _fail(path, "no such file or folder")
    if path.is_dir():
        if colmap_model_dir(path) is not None:
            return "colmap"
        if (path / "transforms.json").is_file():
            return "nerfstudio"
        if _matrix_files(path):
            return "matrices"
        raise _fail(path, "folder holds no recognised poses (COLMAP model, transforms.json, *.txt 4x4 files)")
    if path.suffix == ".json":
        return "nerfstudio"
    if path.suffix == ".log":
        return "log"
    if path.name in ("cameras.bin", "images.bin", "points3D.bin", "cameras.txt", "images.txt", "points3D.txt"):
        return "colmap"
    lines = _data_lines(path)
    widths = [len(t) for _, t in lines[:5]]
    if widths and widths[0] == 8:
        return "tum"
    if widths and widths[0] == 3 and all(w == 4 for w in widths[1:5]):
        return "log"
    if widths and widths[0] == 4:
        return "matrices"
    raise _fail(path, f"unknown pose file format (first data line has {widths[0] if widths else 0} columns)")


def read_poses(path, fmt: str | None = None) -> PoseData:
    """Read camera-to-world poses (OpenCV axes) from `path`; `fmt` is auto-detected when None."""
    path = Path(path)
    fmt = detect_pose_format(path) if fmt is None else fmt
    readers = {
        "tum": read_tum,
        "colmap": read_colmap,
        "nerfstudio": read_nerfstudio,
        "matrices": read_matrix_folder,
        "log": read_log,
    }
    if fmt not in readers:
        raise ValueError(f"unknown pose format {fmt!r}; expected one of {FORMATS}")
    if not path.exists():
        raise _fail(path, "no such file or folder")
    return readers[fmt](path)


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
    _check_poses(poses, "<poses to write>", [f"pose {i}" for i in range(n)], valid)
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
    else:
        raise ValueError(f"unknown pose format {fmt!r}; expected one of {FORMATS}")
