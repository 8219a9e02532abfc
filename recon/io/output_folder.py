"""The output folder of `recon run`: its layout, writing into it atomically, reading it back.

This module owns every file name in the folder (and in its ``segment_NN/`` folders) and the
rule that nothing previously written is lost: every file is written under a hidden name and
moved into place; :class:`OutputFolder`, :func:`atomic_path` and :func:`atomic_write_bytes`
replace nothing without ``overwrite=True``; what an earlier run left is removed only when its
own report.json lists it (:mod:`recon.io.earlier_run`), anything else is named
(:func:`stale_results`). Readers (:func:`load_output`, the ``read_*`` functions) take the
same names. UNFINISHED.txt marks a folder whose run has not finished.
More: docs/outputs.md#the-output-folder
"""

from __future__ import annotations

import io
import json
import math
import os
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from recon.errors import ReconInputError
from recon.io.depth_maps import read_depth_png_mm
from recon.io.naming import natural_key
from recon.io.pose_formats.trajectories import read_poses

MESH_PLY = "mesh.ply"
MESH_GLB = "mesh.glb"
POINT_CLOUD_PLY = "point_cloud.ply"
TRAJECTORY = "trajectory.txt"
INTRINSICS_JSON = "intrinsics.json"
UNFINISHED = "UNFINISHED.txt"
DEPTH_DIR = "depth"
DEPTH_PNG = ".png"  # 16-bit millimetres
DEPTH_NPY = ".npy"  # float32 metres
RECORDING = "recording.rrd"
REPORT_JSON = "report.json"
EVAL_JSON = "eval.json"
SEGMENT_PREFIX = "segment_"



# --------------------------------------------------------------------------- names


def frame_name(index: int) -> str:
    """Default per-frame file stem: frame_000123 (the source frame index)."""
    return f"frame_{int(index):06d}"


def depth_name(frame: str, suffix: str) -> str:
    """Name inside the folder of a frame's depth map: depth/<frame><suffix> (DEPTH_PNG or DEPTH_NPY)."""
    return f"{DEPTH_DIR}/{frame}{suffix}"


# --------------------------------------------------------------------------- atomic writes


def _temp_name(path: Path) -> Path:
    # Same folder (so the final rename stays on one file system), hidden, suffix kept
    # because some writers (Open3D) choose the format from it.
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")


def _exists_error(path: Path) -> ReconInputError:
    return ReconInputError(f"{path}: already exists (--overwrite replaces it)")


@contextmanager
def atomic_path(path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path`; when the block succeeds, move it to `path`.

    Without `overwrite`, an existing `path` is never replaced (ReconInputError instead).
    The temporary file is removed whatever happens.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not overwrite and path.exists():
        raise _exists_error(path)
    tmp = _temp_name(path)
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"{path}: the writer produced no file")
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if path appeared meanwhile: no-clobber, atomic
            except FileExistsError:
                raise _exists_error(path) from None
            except OSError:  # file system without hard links
                if path.exists():
                    raise _exists_error(path) from None
                os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path, data: bytes, overwrite: bool = False) -> Path:
    """Write `data` to `path` atomically (see :func:`atomic_path`); returns the path."""
    path = Path(path)
    with atomic_path(path, overwrite) as tmp:
        _write_synced(tmp, data)
    return path


def _write_synced(path: Path, data: bytes) -> None:
    # fsync before the rename: after a power cut the name points at the old or the new
    # content, never at an empty file.
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _jsonable(obj):
    """`obj` with numpy scalars/arrays, paths and tuples made JSON-friendly; NaN/inf -> None."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return _jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None  # strict JSON has no NaN
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "to_dict"):
        return _jsonable(obj.to_dict())
    return obj


def json_bytes(obj) -> bytes:
    """UTF-8 JSON (indented, strict: NaN/inf written as null) of `obj`."""
    return (json.dumps(_jsonable(obj), indent=2, allow_nan=False) + "\n").encode("utf-8")


class OutputFolder:
    """A results folder whose files are all written atomically.

    Creates the folder (and parents). An existing non-empty folder is refused unless
    `overwrite` is True. Names are relative paths inside the folder ("depth/x.png").
    Within one OutputFolder, a name written earlier may be written again (e.g. a report
    updated at the end); anything else already on disk is only replaced with `overwrite`.
    """

    def __init__(self, path, overwrite: bool = False):
        self.path = Path(path)
        self.overwrite = bool(overwrite)
        self._written: set[Path] = set()
        if self.path.exists() and not self.path.is_dir():
            raise ReconInputError(f"{self.path}: output path exists and is not a folder")
        if self.path.is_dir() and any(self.path.iterdir()) and not overwrite:
            raise ReconInputError(f"{self.path}: output folder is not empty (--overwrite writes into it)")
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            # Checked now, before any heavy work: a folder that cannot take a file fails at once.
            probe = self.path / f".recon-write-check-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as error:
            raise ReconInputError(f"{self.path}: cannot write the output folder here "
                                  f"({error.strerror or type(error).__name__})") from None

    def path_for(self, name) -> Path:
        """Absolute path of `name` inside the folder (its parent folders created)."""
        rel = Path(name)
        if rel.is_absolute() or ".." in rel.parts or not rel.parts:
            raise ValueError(f"output name must be a relative path inside the folder, got {name!r}")
        path = self.path / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        return path

    def _may_replace(self, path: Path) -> bool:
        return self.overwrite or path in self._written

    @contextmanager
    def atomic(self, name) -> Iterator[Path]:
        """Temporary path for a third-party writer; moved to `name` when the block succeeds."""
        path = self.path_for(name)
        with atomic_path(path, self._may_replace(path)) as tmp:
            yield tmp
        self._written.add(path)

    def write_bytes(self, name, data: bytes) -> Path:
        with self.atomic(name) as tmp:
            _write_synced(tmp, data)
        return self.path_for(name)

    def write_text(self, name, text: str) -> Path:
        return self.write_bytes(name, text.encode("utf-8"))

    def write_json(self, name, obj) -> Path:
        return self.write_bytes(name, json_bytes(obj))

    def remove_stale(self, name) -> bool:
        """Delete `name` left by an earlier run (the folder was opened with `overwrite`), so
        that it is not taken for this run's result; True when a file was removed."""
        path = self.path / Path(name)
        if not self.overwrite or path in self._written or not path.is_file():
            return False
        path.unlink()
        return True

    def __repr__(self) -> str:
        return f"OutputFolder({str(self.path)!r}, overwrite={self.overwrite})"


def segment_name(k: int) -> str:
    """The folder of the k-th segment of a run written as segments (``segment_00``, ...)."""
    return f"{SEGMENT_PREFIX}{k:02d}"


def stale_results(folder, segments: list[str]) -> list[str]:
    """Results in a run's output folder that this run did not write (sorted names): segment
    folders (:func:`segment_name`) other than `segments`, this run's (empty for a single
    reconstruction), and, for a run written as segments, a single reconstruction's
    top-level mesh, trajectory and depth."""
    folder = Path(folder)
    mine = set(segments)
    stale = [p.name for p in folder.glob(f"{SEGMENT_PREFIX}*")
             if p.is_dir() and p.name.removeprefix(SEGMENT_PREFIX).isdigit() and p.name not in mine]
    if segments:
        stale += [name for name in (MESH_PLY, MESH_GLB, TRAJECTORY, INTRINSICS_JSON, DEPTH_DIR)
                  if (folder / name).exists()]
    return sorted(stale)


# --------------------------------------------------------------------------- file formats


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def intrinsics_dict(intrinsics, width: int, height: int, per_frame=None) -> dict:
    """JSON-ready pinhole intrinsics; `per_frame` (N, 4) adds a "frames" list when they vary."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    out = {
        "model": "PINHOLE",
        "width": int(width),
        "height": int(height),
        "fx": fx,
        "fy": fy,
        "cx": cx,
        "cy": cy,
        "convention": "pixels of the depth maps; pixel centres at integer coordinates; "
                      "camera x right, y down, z forward",
    }
    if per_frame is not None:
        out["frames"] = [dict(zip(("fx", "fy", "cx", "cy"), map(float, k))) for k in np.asarray(per_frame)]
    return out


# --------------------------------------------------------------------------- unfinished runs


def mark_unfinished(out: OutputFolder) -> Path:
    """Say in ``out`` that a run is writing it (UNFINISHED.txt), until mark_finished: a
    native crash cannot clean up after itself, so the folder says so from the start."""
    import time

    return out.write_text(UNFINISHED, (
        f"recon run (process {os.getpid()}) started writing this folder at {time.strftime('%Y-%m-%d %H:%M:%S')} "
        "and has not finished. Until this file is gone the folder is not a result: if no recon run is at work on "
        "it, that run failed or crashed (its stderr says how: a crash in native code leaves a Python stack "
        "there). Run it again with --overwrite.\n"))


def mark_finished(folder) -> None:
    """The run writing `folder` has finished: UNFINISHED.txt goes."""
    (Path(folder) / UNFINISHED).unlink(missing_ok=True)


def check_finished(folder) -> None:
    """ReconInputError when `folder` holds the remains of a run that did not finish."""
    if (Path(folder) / UNFINISHED).is_file():
        raise ReconInputError(f"{folder}: the run that wrote this folder did not finish ({UNFINISHED} is there): "
                              "not a result; run it again with --overwrite")


# --------------------------------------------------------------------------- reading back


def read_report(folder) -> dict | None:
    """report.json of `folder` parsed, or None when there is none; ReconInputError for the
    folder of a run that did not finish (check_finished)."""
    check_finished(folder)
    path = Path(folder) / REPORT_JSON
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError as error:
        raise ReconInputError(f"{path}: unreadable report ({error})") from None


def read_intrinsics(folder) -> tuple[float, float, float, float] | None:
    """(fx, fy, cx, cy) of the depth maps from intrinsics.json, or None when there is none."""
    path = Path(folder) / INTRINSICS_JSON
    if not path.is_file():
        return None
    k = json.loads(path.read_text())
    return (k["fx"], k["fy"], k["cx"], k["cy"])


def read_trajectory(folder) -> np.ndarray | None:
    """Camera-to-world poses (N, 4, 4) from trajectory.txt, or None when there is none."""
    path = Path(folder) / TRAJECTORY
    return read_poses(path, "tum").poses if path.is_file() else None


def read_mesh(folder):
    """The Open3D triangle mesh of mesh.ply, or None when there is none."""
    import open3d as o3d

    path = Path(folder) / MESH_PLY
    return o3d.io.read_triangle_mesh(str(path)) if path.is_file() else None


def depth_files(folder, names: list[str] | None = None) -> list[Path]:
    """The depth maps of an output folder, one per frame ([] without a depth folder).

    names: the frames' file stems (report.json ``frames.names``); each must have a depth
    map. Without names, every map in natural order. The lossless .npy is preferred over
    the PNG.
    """
    depth_dir = Path(folder) / DEPTH_DIR
    if not depth_dir.is_dir():
        return []
    if names is not None:
        files = []
        for name in names:
            npy, png = depth_dir / f"{name}{DEPTH_NPY}", depth_dir / f"{name}{DEPTH_PNG}"
            if not (npy.exists() or png.exists()):
                raise ReconInputError(f"{depth_dir}: no depth map for frame {name!r} (neither .npy nor .png)")
            files.append(npy if npy.exists() else png)
        return files
    return _natural_sorted(depth_dir.glob(f"*{DEPTH_NPY}")) or _natural_sorted(depth_dir.glob(f"*{DEPTH_PNG}"))


def _natural_sorted(paths) -> list[Path]:
    return sorted(paths, key=lambda p: natural_key(p.name))


def read_depth(path, mmap: bool = False) -> np.ndarray:
    """(H, W) depth in metres from a depth map of the folder (.npy or .png).

    mmap: a .npy is memory-mapped read-only as stored instead of loaded as float32.
    """
    path = Path(path)
    if path.suffix != DEPTH_NPY:
        return read_depth_png_mm(path)
    return np.load(path, mmap_mode="r") if mmap else np.load(path).astype(np.float32)


@dataclass
class OutputFolderData:
    """What `recon run` left in a folder: depth (N, H, W) metres, poses (N, 4, 4),
    source frame indices (N,), the mesh (or None) and the parsed report."""

    path: Path
    report: dict
    indices: np.ndarray
    depth: np.ndarray | None
    poses: np.ndarray | None
    mesh: Any


def load_output(path) -> OutputFolderData:
    """Read an output folder of `recon run` whole; report.json is required and every depth
    map and pose must match one of its frames. Of a streamed run, the frames that got depth
    (their poses taken from the trajectory of every tracked frame)."""
    path = Path(path)
    report_path = path / REPORT_JSON
    report = read_report(path)
    if report is None:
        raise ReconInputError(f"{path}: not an output folder of 'recon run' (no {REPORT_JSON})")
    try:
        indices = np.asarray(report["frames"]["indices"], dtype=np.int64)
        # A streamed run tracked every frame (the trajectory) but gave depth to some.
        depth_indices = np.asarray(report["frames"].get("depth_indices", indices), dtype=np.int64)
    except (ValueError, KeyError, TypeError) as error:
        raise ReconInputError(f"{report_path}: unreadable report ({error})") from None
    names = report["frames"].get("depth_names", report["frames"].get("names"))
    depth = None
    if (path / DEPTH_DIR).is_dir():
        files = depth_files(path, names)
        if len(files) != len(depth_indices):
            raise ReconInputError(
                f"{path / DEPTH_DIR}: {len(files)} depth maps for {len(depth_indices)} frames in {REPORT_JSON}"
            )
        depth = np.stack([read_depth(f) for f in files]) if files else None
    poses = read_trajectory(path)
    if poses is not None and len(poses) != len(indices):
        raise ReconInputError(f"{path / TRAJECTORY}: {len(poses)} poses for {len(indices)} frames in {REPORT_JSON}")
    if len(depth_indices) != len(indices) or not np.array_equal(depth_indices, indices):
        row = {int(i): k for k, i in enumerate(indices)}
        if poses is not None:
            poses = poses[[row[int(i)] for i in depth_indices]]
        indices = depth_indices
    return OutputFolderData(path, report, indices, depth, poses, read_mesh(path))


__all__ = [
    "UNFINISHED",
    "check_finished",
    "mark_finished",
    "mark_unfinished",
    "DEPTH_DIR",
    "DEPTH_NPY",
    "DEPTH_PNG",
    "EVAL_JSON",
    "INTRINSICS_JSON",
    "MESH_GLB",
    "MESH_PLY",
    "OutputFolder",
    "OutputFolderData",
    "POINT_CLOUD_PLY",
    "RECORDING",
    "REPORT_JSON",
    "TRAJECTORY",
    "atomic_path",
    "atomic_write_bytes",
    "depth_files",
    "depth_name",
    "frame_name",
    "intrinsics_dict",
    "json_bytes",
    "load_output",
    "read_depth",
    "read_intrinsics",
    "read_mesh",
    "read_report",
    "read_trajectory",
]
