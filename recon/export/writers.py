"""Writing results: the output folder, meshes (PLY, GLB), trajectory, intrinsics, depth maps, report.

This module owns the output layout and the rule that nothing previously written is lost:

* every file is written under a hidden temporary name in its destination folder, then
  moved into place (``os.link`` when the name must not exist yet, ``os.replace`` when
  overwriting is allowed), so a reader never sees half a file and a crash leaves the old
  file intact;
* :class:`OutputFolder` refuses an existing non-empty folder unless ``overwrite=True``;
  with it, files of the same name are replaced and other files are left alone;
* the standalone ``write_*`` functions refuse to replace an existing file unless
  ``overwrite=True``.

Output layout (:func:`export_reconstruction`)::

    mesh.ply          binary PLY, world coordinates (OpenCV axes, metres), vertex colours
    mesh.glb          the same vertices in glTF axes (see below), vertex colours
    point_cloud.ply   optional surface points with colours
    trajectory.txt    camera-to-world poses, TUM format (t tx ty tz qx qy qz qw), OpenCV camera axes
    intrinsics.json   fx, fy, cx, cy, width, height of the depth maps (+ per-frame values)
    depth/<name>.png  16-bit PNG, millimetres, 0 = invalid, valid depth clipped to [1 mm, 65.535 m]
    depth/<name>.npy  float32 metres, 0 = invalid (lossless; one file per frame so frames
                      stream to disk and can be memory-mapped back: ``np.load(p, mmap_mode="r")``)
    report.json       whatever the pipeline reports (options, timings, metrics)

glTF is y-up with the camera looking down -z, OpenCV is y-down looking down +z. The GLB
applies the rotation diag(1, -1, -1) (x, -y, -z) to vertices and normals: a proper rotation
(det = +1), so triangle winding is kept. When the world frame is gravity-aligned like an
OpenCV camera held level (y pointing down, as in the synthetic scene and most SLAM outputs
started from a level camera), the floor is at the bottom in a glTF viewer.
"""

from __future__ import annotations

import json
import math
import os
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, Mapping, Sequence

import cv2
import numpy as np
import open3d as o3d

from recon.errors import ReconInputError

MESH_PLY = "mesh.ply"
MESH_GLB = "mesh.glb"
POINT_CLOUD_PLY = "point_cloud.ply"
TRAJECTORY = "trajectory.txt"
INTRINSICS_JSON = "intrinsics.json"
DEPTH_DIR = "depth"
REPORT_JSON = "report.json"

# OpenCV (x right, y down, z forward) -> glTF (x right, y up, camera looks down -z).
GLTF_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])
DEPTH_PNG_SCALE = 1000.0  # PNG units per metre (millimetres)
DEPTH_PNG_MAX = 65535


# --------------------------------------------------------------------------- atomic writes


def _temp_name(path: Path) -> Path:
    # Same folder (so the final rename stays on one file system), hidden, suffix kept
    # because some writers (Open3D) choose the format from it.
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")


def _exists_error(path: Path) -> ReconInputError:
    return ReconInputError(f"{path}: already exists (pass overwrite to replace it)")


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


# --------------------------------------------------------------------------- output folder


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
            raise ReconInputError(f"{self.path}: output folder is not empty (pass overwrite to write into it)")
        self.path.mkdir(parents=True, exist_ok=True)

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

    def __repr__(self) -> str:
        return f"OutputFolder({str(self.path)!r}, overwrite={self.overwrite})"


# --------------------------------------------------------------------------- meshes


def _legacy_mesh(mesh) -> o3d.geometry.TriangleMesh:
    if isinstance(mesh, o3d.t.geometry.TriangleMesh):
        return mesh.cpu().to_legacy()
    return mesh


def _write_with_open3d(path: Path, overwrite: bool, write) -> Path:
    with atomic_path(path, overwrite) as tmp:
        if not write(str(tmp)):
            raise OSError(f"{path}: Open3D could not write the file")
    return path


def write_mesh_ply(path, mesh, overwrite: bool = False) -> Path:
    """Binary PLY of a mesh (legacy or tensor Open3D) with its vertex colours and normals."""
    mesh = _legacy_mesh(mesh)
    return _write_with_open3d(
        Path(path), overwrite, lambda p: o3d.io.write_triangle_mesh(p, mesh, write_ascii=False, compressed=False)
    )


def write_point_cloud_ply(path, cloud, overwrite: bool = False) -> Path:
    """Binary PLY of an Open3D point cloud (legacy or tensor)."""
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        cloud = cloud.cpu().to_legacy()
    return _write_with_open3d(Path(path), overwrite, lambda p: o3d.io.write_point_cloud(p, cloud, write_ascii=False))


def to_gltf_axes(points: np.ndarray) -> np.ndarray:
    """(M, 3) points or normals from OpenCV world axes to glTF's: (x, -y, -z)."""
    return np.asarray(points, dtype=np.float64) @ GLTF_FROM_OPENCV.T


def glb_bytes(mesh) -> bytes:
    """GLB (binary glTF) of a mesh: vertices and normals rotated to glTF axes, vertex colours.

    Vertices are written as they are (trimesh with process=False: no merging or
    splitting), so the GLB has exactly the vertex and triangle counts of the PLY.
    """
    import trimesh

    mesh = _legacy_mesh(mesh)
    vertices = to_gltf_axes(np.asarray(mesh.vertices))
    kwargs = {}
    if mesh.has_vertex_colors():
        rgb = np.clip(np.round(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
        kwargs["vertex_colors"] = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    if mesh.has_vertex_normals():
        kwargs["vertex_normals"] = to_gltf_axes(np.asarray(mesh.vertex_normals))
    tm = trimesh.Trimesh(vertices=vertices, faces=np.asarray(mesh.triangles), process=False, **kwargs)
    return tm.export(file_type="glb")


def write_mesh_glb(path, mesh, overwrite: bool = False) -> Path:
    """GLB of a mesh in glTF's y-up axes (module docstring), written atomically."""
    return atomic_write_bytes(path, glb_bytes(mesh), overwrite)


# --------------------------------------------------------------------------- cameras


def write_trajectory_tum(path, poses, timestamps=None, overwrite: bool = False) -> Path:
    """Camera-to-world poses (N, 4, 4) as a TUM trajectory ``t tx ty tz qx qy qz qw``.

    timestamps: (N,) seconds (default: the frame numbers 0..N-1). Frames with a
    non-finite pose are left out (TUM trajectories may have gaps).
    """
    from recon.poses.formats import write_poses

    poses = np.asarray(poses, dtype=np.float64)
    stamps = np.arange(len(poses), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    if len(stamps) != len(poses):
        raise ValueError(f"{len(stamps)} timestamps for {len(poses)} poses")
    valid = np.isfinite(poses).all(axis=(1, 2))
    path = Path(path)
    with atomic_path(path, overwrite) as tmp:
        write_poses(tmp, poses[valid], "tum", timestamps=stamps[valid])
    return path


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
        "convention": "pixels of the depth maps; pixel centres at integer coordinates; camera x right, y down, z forward",
    }
    if per_frame is not None:
        out["frames"] = [dict(zip(("fx", "fy", "cx", "cy"), map(float, k))) for k in np.asarray(per_frame)]
    return out


def write_intrinsics_json(path, intrinsics, width: int, height: int, per_frame=None, overwrite: bool = False) -> Path:
    """intrinsics.json (see :func:`intrinsics_dict`), written atomically."""
    return atomic_write_bytes(path, json_bytes(intrinsics_dict(intrinsics, width, height, per_frame)), overwrite)


# --------------------------------------------------------------------------- depth maps


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """(H, W) metres -> uint16 millimetres: invalid (0, negative, NaN, inf) -> 0, valid depth
    rounded and clipped to [1, 65535] so a valid pixel never turns into "invalid"."""
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    mm = np.zeros(d.shape, np.uint16)
    mm[valid] = np.clip(np.round(d[valid] * DEPTH_PNG_SCALE), 1, DEPTH_PNG_MAX).astype(np.uint16)
    return mm


def depth_png_bytes(depth: np.ndarray) -> bytes:
    """16-bit PNG (millimetres) of a (H, W) depth map in metres."""
    ok, buf = cv2.imencode(".png", depth_to_mm(depth))
    if not ok:
        raise OSError("OpenCV could not encode a 16-bit PNG")
    return buf.tobytes()


def npy_bytes(array: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def read_depth_png_mm(path) -> np.ndarray:
    """(H, W) float32 metres from a depth PNG written by :func:`depth_png_bytes`."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
        raise ReconInputError(f"{path}: not a 16-bit single-channel depth PNG")
    return raw.astype(np.float32) / np.float32(DEPTH_PNG_SCALE)


def frame_name(index: int) -> str:
    """Default per-frame file stem: frame_000123 (the source frame index)."""
    return f"frame_{int(index):06d}"


def write_depth_frame(out: OutputFolder, name: str, depth: np.ndarray, npy: bool = True) -> list[Path]:
    """depth/<name>.png (uint16 mm) and, with `npy`, depth/<name>.npy (float32 metres)."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    written = [out.write_bytes(f"{DEPTH_DIR}/{name}.png", depth_png_bytes(depth))]
    if npy:
        clean = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        written.append(out.write_bytes(f"{DEPTH_DIR}/{name}.npy", npy_bytes(clean)))
    return written


def write_depth_maps(out: OutputFolder, depth: Iterable[np.ndarray], names: Sequence[str] | None = None, npy: bool = True) -> int:
    """Every depth map (iterable of (H, W), streamed) under depth/; returns how many were written."""
    count = 0
    for k, d in enumerate(depth):
        write_depth_frame(out, names[k] if names is not None else frame_name(k), d, npy)
        count += 1
    return count


# --------------------------------------------------------------------------- everything


def export_reconstruction(
    out: OutputFolder,
    mesh=None,
    poses=None,
    timestamps=None,
    intrinsics=None,
    size: tuple[int, int] | None = None,
    depth=None,
    frame_names: Sequence[str] | None = None,
    report: Mapping | None = None,
    point_cloud=None,
    glb: bool = True,
    depth_npy: bool = True,
) -> dict[str, Path]:
    """Write whatever is given into `out` with the standard names (module docstring).

    mesh: Open3D mesh; poses: (N, 4, 4) camera-to-world; timestamps: (N,) seconds;
    intrinsics: (fx, fy, cx, cy) or (N, 4) per frame, with size = (width, height) of the
    depth maps; depth: (N, H, W) metres or an iterable of (H, W); frame_names: depth file
    stems (default frame_000000, ...); report: JSON-able mapping, written last.
    Returns {label: path} of the files written.
    """
    written: dict[str, Path] = {}
    if mesh is not None:
        with out.atomic(MESH_PLY) as tmp:
            write_mesh_ply(tmp, mesh, overwrite=True)
        written["mesh_ply"] = out.path_for(MESH_PLY)
        if glb:
            written["mesh_glb"] = out.write_bytes(MESH_GLB, glb_bytes(mesh))
    if point_cloud is not None:
        with out.atomic(POINT_CLOUD_PLY) as tmp:
            write_point_cloud_ply(tmp, point_cloud, overwrite=True)
        written["point_cloud"] = out.path_for(POINT_CLOUD_PLY)
    if poses is not None:
        with out.atomic(TRAJECTORY) as tmp:
            write_trajectory_tum(tmp, poses, timestamps, overwrite=True)
        written["trajectory"] = out.path_for(TRAJECTORY)
    if intrinsics is not None:
        if size is None:
            raise ValueError("size=(width, height) is needed with intrinsics")
        k = np.asarray(intrinsics, dtype=np.float64)
        shared, per_frame = (k, None) if k.shape == (4,) else (k[0], k)
        written["intrinsics"] = out.write_json(INTRINSICS_JSON, intrinsics_dict(shared, size[0], size[1], per_frame))
    if depth is not None:
        write_depth_maps(out, depth, frame_names, depth_npy)
        written["depth"] = out.path / DEPTH_DIR
    if report is not None:
        written["report"] = out.write_json(REPORT_JSON, report)
    return written


__all__ = [
    "DEPTH_DIR",
    "GLTF_FROM_OPENCV",
    "INTRINSICS_JSON",
    "MESH_GLB",
    "MESH_PLY",
    "OutputFolder",
    "POINT_CLOUD_PLY",
    "REPORT_JSON",
    "TRAJECTORY",
    "atomic_path",
    "atomic_write_bytes",
    "depth_png_bytes",
    "depth_to_mm",
    "export_reconstruction",
    "frame_name",
    "glb_bytes",
    "intrinsics_dict",
    "json_bytes",
    "read_depth_png_mm",
    "to_gltf_axes",
    "write_depth_frame",
    "write_depth_maps",
    "write_intrinsics_json",
    "write_mesh_glb",
    "write_mesh_ply",
    "write_point_cloud_ply",
    "write_trajectory_tum",
]
