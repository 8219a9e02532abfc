"""Writing results into an output folder: meshes (PLY, GLB), trajectory, intrinsics, depth maps.

The folder's layout, file names and atomic-write rule belong to
:mod:`recon.io.output_folder`; this module holds the writers that need Open3D, trimesh or a
pose format, and :func:`export_reconstruction`, which puts everything under its standard
name. The standalone ``write_*`` functions refuse to replace an existing file unless
``overwrite=True``. The GLB applies diag(1, -1, -1) to vertices and normals (OpenCV axes to
glTF's, winding kept), after the world's upright rotation (:mod:`recon.fusion.upright`).
More: docs/fusion.md#upright-output
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import open3d as o3d

from recon.io.depth_maps import depth_png_bytes
from recon.io.output_folder import (
    DEPTH_DIR,
    DEPTH_NPY,
    DEPTH_PNG,
    INTRINSICS_JSON,
    MESH_GLB,
    MESH_PLY,
    POINT_CLOUD_PLY,
    REPORT_JSON,
    TRAJECTORY,
    OutputFolder,
    atomic_path,
    atomic_write_bytes,
    depth_name,
    frame_name,
    intrinsics_dict,
    json_bytes,
    npy_bytes,
)
from recon.io.pose_formats.trajectories import write_poses

# OpenCV (x right, y down, z forward) -> glTF (x right, y up, camera looks down -z).
GLTF_FROM_OPENCV = np.diag([1.0, -1.0, -1.0])


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


def _legacy_cloud(cloud) -> o3d.geometry.PointCloud:
    if isinstance(cloud, o3d.t.geometry.PointCloud):
        return cloud.cpu().to_legacy()
    return cloud


def write_point_cloud_ply(path, cloud, overwrite: bool = False) -> Path:
    """Binary PLY of an Open3D point cloud (legacy or tensor)."""
    cloud = _legacy_cloud(cloud)
    return _write_with_open3d(Path(path), overwrite, lambda p: o3d.io.write_point_cloud(p, cloud, write_ascii=False))


def to_gltf_axes(points: np.ndarray, rotation: np.ndarray | None = None) -> np.ndarray:
    """(M, 3) points or normals from OpenCV world axes to glTF's: (x, -y, -z), after
    `rotation` (3, 3), the world's upright rotation (:mod:`recon.fusion.upright`), if given."""
    turn = GLTF_FROM_OPENCV if rotation is None else GLTF_FROM_OPENCV @ np.asarray(rotation, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ turn.T


def glb_bytes(mesh, rotation: np.ndarray | None = None) -> bytes:
    """GLB (binary glTF) of a mesh: vertices and normals turned upright by `rotation` (3, 3;
    None: as they are) and then to glTF axes, vertex colours.

    Vertices are written as they are (trimesh with process=False: no merging or
    splitting), so the GLB has exactly the vertex and triangle counts of the PLY.
    """
    import trimesh

    mesh = _legacy_mesh(mesh)
    vertices = to_gltf_axes(np.asarray(mesh.vertices), rotation)
    kwargs = {}
    if mesh.has_vertex_colors():
        rgb = np.clip(np.round(np.asarray(mesh.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
        kwargs["vertex_colors"] = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    if mesh.has_vertex_normals():
        kwargs["vertex_normals"] = to_gltf_axes(np.asarray(mesh.vertex_normals), rotation)
    tm = trimesh.Trimesh(vertices=vertices, faces=np.asarray(mesh.triangles), process=False, **kwargs)
    return with_matte_material(tm.export(file_type="glb"))


# Without a material glTF's default applies, which is fully metallic: under ambient light
# (three.js's MeshStandardMaterial) a scan then renders black. Scans are matte: no metal,
# full roughness, the vertex colours as the base colour.
MATTE_MATERIAL = {"name": "recon scan", "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                                                 "metallicFactor": 0.0, "roughnessFactor": 1.0}}


def with_matte_material(glb: bytes) -> bytes:
    """The GLB with MATTE_MATERIAL given to every primitive that has no material (the JSON
    chunk rewritten, padded with spaces to 4 bytes as the GLB container requires)."""
    import json
    import struct

    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    json_length, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or json_type != b"JSON":
        raise ValueError("not a GLB with a JSON chunk first")
    document = json.loads(glb[20:20 + json_length])
    materials = document.setdefault("materials", [])
    materials.append(MATTE_MATERIAL)
    for mesh in document.get("meshes", []):
        for primitive in mesh.get("primitives", []):
            primitive.setdefault("material", len(materials) - 1)
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    rest = glb[20 + json_length:]
    header = struct.pack("<4sII", magic, version, 12 + 8 + len(text) + len(rest))
    return header + struct.pack("<I4s", len(text), b"JSON") + text + rest


def write_mesh_glb(path, mesh, overwrite: bool = False, rotation: np.ndarray | None = None) -> Path:
    """GLB of a mesh in glTF's y-up axes (module docstring), written atomically."""
    return atomic_write_bytes(path, glb_bytes(mesh, rotation), overwrite)


# --------------------------------------------------------------------------- cameras


def write_trajectory_tum(path, poses, timestamps=None, overwrite: bool = False) -> Path:
    """Camera-to-world poses (N, 4, 4) as a TUM trajectory ``t tx ty tz qx qy qz qw``.

    timestamps: (N,) seconds (default: the frame numbers 0..N-1). Frames with a
    non-finite pose are left out (TUM trajectories may have gaps).
    """
    poses = np.asarray(poses, dtype=np.float64)
    stamps = np.arange(len(poses), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    if len(stamps) != len(poses):
        raise ValueError(f"{len(stamps)} timestamps for {len(poses)} poses")
    valid = np.isfinite(poses).all(axis=(1, 2))
    path = Path(path)
    with atomic_path(path, overwrite) as tmp:
        write_poses(tmp, poses[valid], "tum", timestamps=stamps[valid])
    return path


def write_intrinsics_json(path, intrinsics, width: int, height: int, per_frame=None, overwrite: bool = False) -> Path:
    """intrinsics.json (see :func:`recon.io.output_folder.intrinsics_dict`), written atomically."""
    return atomic_write_bytes(path, json_bytes(intrinsics_dict(intrinsics, width, height, per_frame)), overwrite)


# --------------------------------------------------------------------------- depth maps


def write_depth_frame(out: OutputFolder, name: str, depth: np.ndarray, npy: bool = True) -> list[Path]:
    """depth/<name>.png (uint16 mm) and, with `npy`, depth/<name>.npy (float32 metres)."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    written = [out.write_bytes(depth_name(name, DEPTH_PNG), depth_png_bytes(depth))]
    if npy:
        clean = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        written.append(out.write_bytes(depth_name(name, DEPTH_NPY), npy_bytes(clean)))
    return written


def write_depth_maps(
    out: OutputFolder, depth: Iterable[np.ndarray], names: Sequence[str] | None = None, npy: bool = True
) -> int:
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
    shape: tuple[int, int] | None = None,
    depth=None,
    frame_names: Sequence[str] | None = None,
    report: Mapping | None = None,
    point_cloud=None,
    glb: bool = True,
    depth_npy: bool = True,
    glb_rotation: np.ndarray | None = None,
) -> dict[str, Path]:
    """Write whatever is given into `out` under its standard name (:mod:`recon.io.output_folder`).
    A mesh without triangles or a point cloud without points is not written (and the file an
    earlier run left in `out` is removed).

    mesh: Open3D mesh; poses: (N, 4, 4) camera-to-world; timestamps: (N,) seconds;
    intrinsics: (fx, fy, cx, cy) or (N, 4) per frame, with shape = (H, W) of the
    depth maps; depth: (N, H, W) metres or an iterable of (H, W); frame_names: depth file
    stems (default frame_000000, ...); report: JSON-able mapping, written last;
    glb_rotation: (3, 3) the upright rotation the GLB is turned by (the PLY is not).
    Returns {label: path} of the files written.
    """
    written: dict[str, Path] = {}
    # Converted once here: the PLY and GLB writers then get the legacy geometry as it is.
    mesh = None if mesh is None else _legacy_mesh(mesh)
    point_cloud = None if point_cloud is None else _legacy_cloud(point_cloud)
    # Nothing to write (fusion said why); a mesh of an earlier run must not pass for this one's.
    if mesh is not None and len(mesh.triangles) == 0:
        for name in (MESH_PLY, MESH_GLB):
            out.remove_stale(name)
        mesh = None
    if point_cloud is not None and len(point_cloud.points) == 0:
        out.remove_stale(POINT_CLOUD_PLY)
        point_cloud = None
    if mesh is not None:
        with out.atomic(MESH_PLY) as tmp:
            write_mesh_ply(tmp, mesh, overwrite=True)
        written["mesh_ply"] = out.path_for(MESH_PLY)
        if glb:
            written["mesh_glb"] = out.write_bytes(MESH_GLB, glb_bytes(mesh, glb_rotation))
    if point_cloud is not None:
        with out.atomic(POINT_CLOUD_PLY) as tmp:
            write_point_cloud_ply(tmp, point_cloud, overwrite=True)
        written["point_cloud"] = out.path_for(POINT_CLOUD_PLY)
    if poses is not None:
        with out.atomic(TRAJECTORY) as tmp:
            write_trajectory_tum(tmp, poses, timestamps, overwrite=True)
        written["trajectory"] = out.path_for(TRAJECTORY)
    if intrinsics is not None:
        if shape is None:
            raise ValueError("shape=(height, width) is needed with intrinsics")
        k = np.asarray(intrinsics, dtype=np.float64)
        shared, per_frame = (k, None) if k.shape == (4,) else (k[0], k)
        written["intrinsics"] = out.write_json(INTRINSICS_JSON, intrinsics_dict(shared, shape[1], shape[0], per_frame))
    if depth is not None:
        write_depth_maps(out, depth, frame_names, depth_npy)
        written["depth"] = out.path / DEPTH_DIR
    if report is not None:
        written["report"] = out.write_json(REPORT_JSON, report)
    return written


__all__ = [
    "GLTF_FROM_OPENCV",
    "export_reconstruction",
    "glb_bytes",
    "to_gltf_axes",
    "write_depth_frame",
    "write_depth_maps",
    "write_intrinsics_json",
    "write_mesh_glb",
    "write_mesh_ply",
    "write_point_cloud_ply",
    "write_trajectory_tum",
]
