"""The writers of recon.export: everything a run exports into its output folder (mesh PLY and
GLB, point cloud, trajectory, intrinsics, depth maps, report) and the GLB's y-up axes."""

from __future__ import annotations

import json
import struct

import numpy as np
import open3d as o3d
import pytest
import trimesh

from recon.export import export_reconstruction, write_mesh_glb
from recon.io.depth_maps import read_depth_png_mm
from recon.io.output_folder import (
    DEPTH_DIR,
    INTRINSICS_JSON,
    MESH_GLB,
    MESH_PLY,
    POINT_CLOUD_PLY,
    REPORT_JSON,
    TRAJECTORY,
    OutputFolder,
)
from recon.io.pose_formats.trajectories import read_poses

from helpers import glb_json, glb_vertex_colors, no_temp_files


def _glb_mesh(path) -> trimesh.Trimesh:
    return trimesh.load(str(path), file_type="glb", force="mesh", process=False)


def test_export_all(tmp_path, fusion_room, fused_room):
    out = OutputFolder(tmp_path / "result")
    timestamps = np.arange(20) / 30.0
    names = [f"frame_{i:06d}" for i in range(3)]
    written = export_reconstruction(
        out,
        mesh=fused_room.mesh,
        poses=fusion_room.poses,
        timestamps=timestamps,
        intrinsics=fusion_room.intrinsics,
        shape=(fusion_room.height, fusion_room.width),
        depth=fusion_room.depth[:3],
        frame_names=names,
        report={"voxel_size": fused_room.voxel_size, "f": np.float32(0.5), "bad": float("nan"), "n": np.int64(3)},
        point_cloud=fused_room.point_cloud,
    )
    root = out.path
    for name in (MESH_PLY, MESH_GLB, TRAJECTORY, INTRINSICS_JSON, REPORT_JSON, POINT_CLOUD_PLY):
        assert (root / name).is_file(), name
    assert written["mesh_ply"] == root / MESH_PLY and written["depth"] == root / DEPTH_DIR
    # PLY and GLB hold the same vertices (GLB in glTF axes).
    ply = o3d.io.read_triangle_mesh(str(root / MESH_PLY))
    glb = _glb_mesh(root / MESH_GLB)
    assert len(ply.vertices) == len(glb.vertices) == len(fused_room.mesh.vertices)
    assert len(ply.triangles) == len(glb.faces) == len(fused_room.mesh.triangles)
    assert np.allclose(glb.vertices, np.asarray(ply.vertices) * [1, -1, -1], atol=1e-5)
    assert np.abs(glb_vertex_colors(root / MESH_GLB)[:, :3] / 255.0 - np.asarray(ply.vertex_colors)).max() < 0.01
    # Trajectory, intrinsics, depth, report.
    traj = read_poses(root / TRAJECTORY, "tum")
    assert np.allclose(traj.poses, fusion_room.poses, atol=1e-6)
    assert np.allclose(traj.timestamps, timestamps, atol=1e-6)
    intr = json.loads((root / INTRINSICS_JSON).read_text())
    assert (intr["width"], intr["height"]) == (320, 240)
    assert [intr[k] for k in ("fx", "fy", "cx", "cy")] == pytest.approx(list(fusion_room.intrinsics))
    for k, name in enumerate(names):
        assert np.abs(read_depth_png_mm(root / DEPTH_DIR / f"{name}.png") - fusion_room.depth[k]).max() <= 0.0005 + 1e-6
        assert np.array_equal(np.load(root / DEPTH_DIR / f"{name}.npy"), fusion_room.depth[k])
    report = json.loads((root / REPORT_JSON).read_text())
    assert report == {"voxel_size": fused_room.voxel_size, "f": 0.5, "bad": None, "n": 3}
    assert no_temp_files(root)


def test_glb_is_y_up(tmp_path):
    # A floor 1.5 m below the cameras: +y in OpenCV world axes (y down).
    floor = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector([[-1, 1.5, 1], [1, 1.5, 1], [1, 1.5, 3], [-1, 1.5, 3]]),
        o3d.utility.Vector3iVector([[0, 2, 1], [0, 3, 2]]),
    )
    floor.vertex_colors = o3d.utility.Vector3dVector(np.tile([0.2, 0.4, 0.6], (4, 1)))
    floor.compute_vertex_normals()
    path = write_mesh_glb(tmp_path / "floor.glb", floor)
    glb = _glb_mesh(path)
    assert len(glb.vertices) == 4
    assert np.allclose(glb.vertices[:, 1], -1.5)  # down in a y-up viewer
    assert np.allclose(glb.vertices[:, 2], -np.asarray(floor.vertices)[:, 2])  # in front = -z
    assert np.allclose(glb_vertex_colors(path)[0, :3], [51, 102, 153])
    # The rotation is proper (det +1): triangle normals turn with the vertices.
    if not floor.has_triangle_normals():
        floor.compute_triangle_normals()
    n_cv = np.asarray(floor.triangle_normals)
    assert np.allclose(glb.face_normals, n_cv * [1, -1, -1], atol=1e-6)


def test_glb_has_a_matte_material(tmp_path):
    """glTF's default material is fully metallic (a scan renders black under ambient light):
    every primitive gets a non-metallic, fully rough one, and the file still loads."""
    box = o3d.geometry.TriangleMesh.create_box()
    box.compute_vertex_normals()
    box.vertex_colors = o3d.utility.Vector3dVector(np.full((8, 3), 0.5))
    path = write_mesh_glb(tmp_path / "box.glb", box)
    data = path.read_bytes()
    assert struct.unpack_from("<I", data, 8)[0] == len(data)
    document = glb_json(data)
    primitives = [p for mesh in document["meshes"] for p in mesh["primitives"]]
    assert primitives
    for primitive in primitives:
        pbr = document["materials"][primitive["material"]]["pbrMetallicRoughness"]
        assert pbr["metallicFactor"] == 0.0 and pbr["roughnessFactor"] == 1.0
    assert len(_glb_mesh(path).faces) == 12
    assert np.allclose(glb_vertex_colors(path)[:, :3], 128, atol=1)
