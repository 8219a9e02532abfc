"""TSDF fusion on the synthetic room (accuracy against the ground-truth mesh, automatic
parameters, memory budget, fragment removal) and the export of its results."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import trimesh

from recon.errors import ReconInputError
from recon.eval.mesh import mesh_metrics, visible_mask
from recon.export import OutputFolder, export_reconstruction, read_depth_png_mm, write_mesh_glb, write_mesh_ply
from recon.export.writers import (
    DEPTH_DIR,
    INTRINSICS_JSON,
    MESH_GLB,
    MESH_PLY,
    REPORT_JSON,
    TRAJECTORY,
    atomic_write_bytes,
    depth_to_mm,
    glb_bytes,
)
from recon.fusion import FusionOptions, auto_voxel_size, estimate_block_count, fuse, remove_fragments
from recon.poses.formats import read_poses
from recon.synthetic import render_sequence

QUIET = dict(progress=False)


@pytest.fixture(scope="module")
def room():
    return render_sequence(20, 320, 240, seed=0)


@pytest.fixture(scope="module")
def fused(room):
    return fuse(room.depth, room.rgb, room.poses, room.intrinsics, FusionOptions(point_cloud=True, **QUIET))


def _glb_mesh(path) -> trimesh.Trimesh:
    return trimesh.load(str(path), file_type="glb", force="mesh", process=False)


def _no_temp_files(folder: Path) -> bool:
    return not any(p.name.startswith(".") for p in folder.rglob("*"))


# --------------------------------------------------------------------------- fusion


def test_fusion_matches_ground_truth(room, fused):
    mesh = fused.mesh
    assert len(mesh.triangles) > 10_000 and mesh.has_vertex_colors() and mesh.has_vertex_normals()
    assert fused.frames_fused == 20 and fused.seconds > 0
    # Evaluate only what the cameras saw (the rest of the room cannot be reconstructed).
    seen = lambda p: visible_mask(p, room.depth, room.poses, room.intrinsics)  # noqa: E731
    m = mesh_metrics(mesh, room.o3d_mesh(), threshold=0.05, num_points=20_000, point_filter=seen)
    assert m.precision >= 0.95 and m.recall >= 0.95 and m.fscore >= 0.95, m
    assert m.completeness < 0.03
    # Colours are the frames' colours (0..1), not 0..255 and not black.
    colors = np.asarray(mesh.vertex_colors)
    assert colors.max() <= 1.0 + 1e-5
    assert colors.mean(0) == pytest.approx(room.rgb.reshape(-1, 3).mean(0) / 255, abs=0.06)
    assert fused.point_cloud is not None and len(fused.point_cloud.points) > 1000


def test_automatic_parameters_follow_the_rule(room, fused):
    valid = room.depth[room.depth > 0]
    # The rule, on the sampled depths fuse() uses (every 4th pixel): 1.1 x p99, median / 200.
    sample = room.depth[:, ::4, ::4].ravel()
    assert fused.max_depth == pytest.approx(1.1 * np.percentile(sample, 99), rel=1e-6)
    assert fused.voxel_size == pytest.approx(np.median(sample[sample <= fused.max_depth]) / 200, rel=1e-6)
    assert fused.voxel_size == pytest.approx(np.median(valid) / 200, rel=0.02)
    assert fused.trunc == pytest.approx(FusionOptions.trunc_voxels * fused.voxel_size)
    assert auto_voxel_size(2.0) == pytest.approx(0.01)
    assert auto_voxel_size(0.3) == 0.005 and auto_voxel_size(40.0) == 0.05
    # A constant 2 m depth: voxel 1 cm, max depth 2.2 m.
    flat = np.full((2, 24, 32), 2.0, np.float32)
    poses = np.stack([np.eye(4)] * 2)
    r = fuse(flat, None, poses, (30.0, 30.0, 15.5, 11.5), FusionOptions(**QUIET))
    assert (r.voxel_size, r.trunc, r.max_depth) == pytest.approx((0.01, 0.08, 2.2))
    # Overrides win.
    r = fuse(flat, None, poses, (30.0, 30.0, 15.5, 11.5), FusionOptions(voxel_size=0.02, trunc=0.05, max_depth=3.0, **QUIET))
    assert (r.voxel_size, r.trunc, r.max_depth) == pytest.approx((0.02, 0.05, 3.0))


def test_block_estimate_and_budget(room, fused, caplog):
    # The estimate predicts what integration allocates.
    assert fused.blocks_used == pytest.approx(fused.block_estimate, rel=0.2)
    est = estimate_block_count(room.depth, room.poses, room.intrinsics, fused.voxel_size, fused.trunc, fused.max_depth)
    assert est == fused.block_estimate
    # A budget 4x too small: the voxel grows (about 2x) with a warning instead of failing.
    budget = fused.block_estimate // 4
    frames = slice(0, 20, 4)
    with caplog.at_level(logging.WARNING, logger="recon.fusion.tsdf"):
        r = fuse(room.depth[frames], room.rgb[frames], room.poses[frames], room.intrinsics, FusionOptions(block_count=budget, **QUIET))
    assert any("budget" in rec.message for rec in caplog.records)
    assert r.block_estimate <= budget and r.blocks_used <= 1.2 * budget
    assert r.voxel_size > 1.5 * fused.voxel_size and r.trunc == pytest.approx(FusionOptions.trunc_voxels * r.voxel_size)
    assert len(r.mesh.triangles) > 1000


def test_fragment_removal_drops_floating_blob():
    seq = render_sequence(6, 160, 120, seed=1)
    depth = seq.depth.copy()
    # A 5x5 pixel speck floating 1 m in front of every camera: a tiny disconnected blob.
    depth[:, 60:65, 80:85] = 1.0
    blob = np.stack([(p[:3, :3] @ np.array([0.0, 0.0, 1.0]) + p[:3, 3]) for p in seq.poses])
    opts = dict(weight_threshold=1.0, **QUIET)

    def near_blob(mesh):
        v = np.asarray(mesh.vertices)
        return int((np.linalg.norm(v[:, None] - blob[None], axis=2).min(1) < 0.05).sum())

    kept = fuse(depth, seq.rgb, seq.poses, seq.intrinsics, FusionOptions(min_fragment_triangles=0, min_fragment_fraction=0, **opts))
    assert near_blob(kept.mesh) > 0 and kept.fragments_removed == 0
    cleaned = fuse(depth, seq.rgb, seq.poses, seq.intrinsics, FusionOptions(**opts))
    assert near_blob(cleaned.mesh) == 0 and cleaned.fragments_removed > 0
    # Only the blob went: the room surface is essentially unchanged.
    assert len(cleaned.mesh.triangles) > 0.98 * len(kept.mesh.triangles)


def test_remove_fragments_unit():
    big = o3d.geometry.TriangleMesh.create_box(1, 1, 1).subdivide_midpoint(3)  # 768 triangles
    small = o3d.geometry.TriangleMesh.create_tetrahedron(0.05).translate((3, 0, 0))  # 4 triangles
    mesh, removed = remove_fragments(big + small, min_triangles=10, min_fraction=0.0)
    assert removed == 4 and len(mesh.triangles) == len(big.triangles)
    assert np.asarray(mesh.vertices)[:, 0].max() <= 1.0 + 1e-9
    # The fraction rule alone: 4 < 1 % of 768 -> dropped; 0 triangles and 0 fraction keep all.
    assert remove_fragments(big + small, min_triangles=0, min_fraction=0.01)[1] == 4
    assert remove_fragments(big + small, min_triangles=0, min_fraction=0.0)[1] == 0


def test_fusion_inputs(room):
    poses = room.poses[:4].copy()
    poses[1] = np.nan  # an untracked frame is skipped, not fused
    r = fuse(room.depth[:4], room.rgb[:4], poses, room.intrinsics, FusionOptions(**QUIET))
    assert r.frames_fused == 3
    # Per-frame intrinsics and an uncoloured fusion.
    k = np.tile(room.intrinsics, (4, 1))
    r = fuse(room.depth[:4], None, room.poses[:4], k, FusionOptions(**QUIET))
    assert len(r.mesh.triangles) > 0 and not r.mesh.has_vertex_colors()
    with pytest.raises(ReconInputError):
        fuse(np.zeros((2, 8, 8), np.float32), None, room.poses[:2], room.intrinsics, FusionOptions(**QUIET))
    with pytest.raises(ReconInputError):
        fuse(room.depth[:2], None, room.poses[:2], room.intrinsics, FusionOptions(voxel_size=-1.0, **QUIET))
    with pytest.raises(ReconInputError):
        fuse(room.depth[:2], None, room.poses[:2], room.intrinsics, FusionOptions(device="tpu", **QUIET))


# --------------------------------------------------------------------------- export


def test_export_all(tmp_path, room, fused):
    out = OutputFolder(tmp_path / "result")
    timestamps = np.arange(20) / 30.0
    names = [f"frame_{i:06d}" for i in range(3)]
    written = export_reconstruction(
        out,
        mesh=fused.mesh,
        poses=room.poses,
        timestamps=timestamps,
        intrinsics=room.intrinsics,
        size=(room.width, room.height),
        depth=room.depth[:3],
        frame_names=names,
        report={"voxel_size": fused.voxel_size, "f": np.float32(0.5), "bad": float("nan"), "n": np.int64(3)},
        point_cloud=fused.point_cloud,
    )
    root = out.path
    for name in (MESH_PLY, MESH_GLB, TRAJECTORY, INTRINSICS_JSON, REPORT_JSON, "point_cloud.ply"):
        assert (root / name).is_file(), name
    assert written["mesh_ply"] == root / MESH_PLY and written["depth"] == root / DEPTH_DIR
    # PLY and GLB hold the same vertices (GLB in glTF axes).
    ply = o3d.io.read_triangle_mesh(str(root / MESH_PLY))
    glb = _glb_mesh(root / MESH_GLB)
    assert len(ply.vertices) == len(glb.vertices) == len(fused.mesh.vertices)
    assert len(ply.triangles) == len(glb.faces) == len(fused.mesh.triangles)
    assert np.allclose(glb.vertices, np.asarray(ply.vertices) * [1, -1, -1], atol=1e-5)
    assert np.abs(glb.visual.vertex_colors[:, :3] / 255.0 - np.asarray(ply.vertex_colors)).max() < 0.01
    # Trajectory, intrinsics, depth, report.
    traj = read_poses(root / TRAJECTORY, "tum")
    assert np.allclose(traj.poses, room.poses, atol=1e-6) and np.allclose(traj.timestamps, timestamps, atol=1e-6)
    intr = json.loads((root / INTRINSICS_JSON).read_text())
    assert (intr["width"], intr["height"]) == (320, 240)
    assert [intr[k] for k in ("fx", "fy", "cx", "cy")] == pytest.approx(list(room.intrinsics))
    for k, name in enumerate(names):
        assert np.abs(read_depth_png_mm(root / DEPTH_DIR / f"{name}.png") - room.depth[k]).max() <= 0.0005 + 1e-6
        assert np.array_equal(np.load(root / DEPTH_DIR / f"{name}.npy"), room.depth[k])
    report = json.loads((root / REPORT_JSON).read_text())
    assert report == {"voxel_size": fused.voxel_size, "f": 0.5, "bad": None, "n": 3}
    assert _no_temp_files(root)


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
    assert np.allclose(glb.visual.vertex_colors[0, :3], [51, 102, 153])
    # The rotation is proper (det +1): triangle normals turn with the vertices.
    n_cv = np.asarray(floor.triangle_normals if floor.has_triangle_normals() else floor.compute_triangle_normals().triangle_normals)
    assert np.allclose(glb.face_normals, n_cv * [1, -1, -1], atol=1e-6)


def test_depth_png_round_trip(tmp_path):
    depth = np.array([[0.0, 1.2344, 0.0004], [np.nan, 70.0, -1.0], [np.inf, 65.535, 2.5]], np.float32)
    mm = depth_to_mm(depth)
    assert mm.tolist() == [[0, 1234, 1], [0, 65535, 0], [0, 65535, 2500]]
    out = OutputFolder(tmp_path / "o")
    from recon.export import write_depth_frame

    png, npy = write_depth_frame(out, "f", depth)
    back = read_depth_png_mm(png)
    assert back.dtype == np.float32 and back[0, 1] == pytest.approx(1.234) and back[1, 1] == pytest.approx(65.535)
    assert np.array_equal(back > 0, np.isfinite(depth) & (depth > 0))
    stored = np.load(npy)
    assert stored.dtype == np.float32 and stored[1, 0] == 0 and stored[1, 1] == 70.0 and stored[2, 0] == 0


def test_output_folder_refuses_non_empty(tmp_path):
    target = tmp_path / "busy"
    target.mkdir()
    (target / "keep.txt").write_text("precious")
    with pytest.raises(ReconInputError) as exc:
        OutputFolder(target)
    assert str(target) in str(exc.value) and "\n" not in str(exc.value)
    assert (target / "keep.txt").read_text() == "precious"
    # With overwrite: same names replaced, other files left alone.
    out = OutputFolder(target, overwrite=True)
    out.write_text("keep2.txt", "new")
    assert (target / "keep.txt").read_text() == "precious"
    # An empty existing folder and a new nested one are fine; a file is not.
    (tmp_path / "empty").mkdir()
    OutputFolder(tmp_path / "empty")
    assert OutputFolder(tmp_path / "a" / "b").path.is_dir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ReconInputError):
        OutputFolder(tmp_path / "file")


def test_atomic_writes(tmp_path):
    out = OutputFolder(tmp_path / "o")
    out.write_json("r.json", {"a": 1})
    out.write_json("r.json", {"a": 2})  # this run's own file may be rewritten
    assert json.loads((out.path / "r.json").read_text()) == {"a": 2}
    # A writer that fails leaves neither a temp file nor a partial result.
    with pytest.raises(RuntimeError):
        with out.atomic("broken.bin") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer crashed")
    assert not (out.path / "broken.bin").exists()
    # Standalone writers never replace an existing file without overwrite.
    target = tmp_path / "o" / "existing.ply"
    target.write_text("old")
    mesh = o3d.geometry.TriangleMesh.create_tetrahedron()
    with pytest.raises(ReconInputError):
        write_mesh_ply(target, mesh)
    assert target.read_text() == "old"
    with pytest.raises(ReconInputError):
        atomic_write_bytes(target, b"new")
    assert target.read_text() == "old"
    write_mesh_ply(target, mesh, overwrite=True)
    assert len(o3d.io.read_triangle_mesh(str(target)).triangles) == 4
    assert glb_bytes(mesh)[:4] == b"glTF"
    assert _no_temp_files(out.path)
    with pytest.raises(ValueError):
        out.path_for("../escape.txt")


@pytest.mark.skipif(
    not (Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes-redkitchen").is_dir(),
    reason="../shared is not present",
)
def test_fuse_real_sensor_depth(tmp_path):
    """7-Scenes sensor depth with its ground-truth poses gives a clean kitchen surface."""
    from recon.io.frames import open_source

    src = open_source(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes-redkitchen", width=160, stride=20, max_frames=10)
    depth, rgb = src.load_depth(), src.read_all().rgb
    r = fuse(depth, rgb, src.poses, src.intrinsics, FusionOptions(**QUIET))
    assert len(r.mesh.triangles) > 5000 and 0.005 <= r.voxel_size <= 0.03
    # Self-consistency: the mesh lies where the sensor saw surfaces.
    seen = lambda p: visible_mask(p, depth, src.poses, src.intrinsics)  # noqa: E731
    from recon.eval.mesh import sample_surface

    pts = sample_surface(r.mesh, 20_000)
    pts = pts[seen(pts)]
    fx, fy, cx, cy = src.intrinsics
    k = 0
    cam = (pts - src.poses[k][:3, 3]) @ src.poses[k][:3, :3]
    u = np.round(fx * cam[:, 0] / cam[:, 2] + cx).astype(int)
    v = np.round(fy * cam[:, 1] / cam[:, 2] + cy).astype(int)
    inside = (cam[:, 2] > 0) & (u >= 0) & (u < depth.shape[2]) & (v >= 0) & (v < depth.shape[1])
    d = depth[k][v[inside], u[inside]]
    ok = d > 0
    assert ok.sum() > 1000 and np.median(np.abs(cam[inside, 2][ok] - d[ok])) < 0.02
