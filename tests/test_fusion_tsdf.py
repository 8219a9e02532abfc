"""TSDF fusion (recon.fusion.tsdf) on the synthetic room: accuracy against the ground-truth
mesh, automatic parameters, memory budget, fragment removal, inputs, and real sensor depth.
The room and its fusion (conftest: fusion_room, fused_room) are shared with the export tests."""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d
import pytest

from recon.errors import ReconInputError
from recon.eval.mesh import mesh_metrics, visible_mask
from recon.fusion import FusionOptions, auto_voxel_size, estimate_block_count, fuse, remove_fragments
from recon.synthetic import render_sequence

from helpers import SHARED_DATA

QUIET = dict(progress=False)


def test_fusion_matches_ground_truth(fusion_room, fused_room):
    mesh = fused_room.mesh
    assert len(mesh.triangles) > 10_000 and mesh.has_vertex_colors() and mesh.has_vertex_normals()
    assert fused_room.frames_fused == 20 and fused_room.seconds > 0
    # Evaluate only what the cameras saw (the rest of the room cannot be reconstructed).
    seen = lambda p: visible_mask(p, fusion_room.depth, fusion_room.poses, fusion_room.intrinsics)  # noqa: E731
    m = mesh_metrics(mesh, fusion_room.o3d_mesh(), threshold=0.05, num_points=20_000, point_filter=seen)
    assert m.precision >= 0.95 and m.recall >= 0.95 and m.fscore >= 0.95, m
    assert m.completeness < 0.03
    # Colours are the frames' colours (0..1), not 0..255 and not black.
    colors = np.asarray(mesh.vertex_colors)
    assert colors.max() <= 1.0 + 1e-5
    assert colors.mean(0) == pytest.approx(fusion_room.rgb.reshape(-1, 3).mean(0) / 255, abs=0.06)
    assert fused_room.point_cloud is not None and len(fused_room.point_cloud.points) > 1000


def test_automatic_parameters_follow_the_rule(fusion_room, fused_room):
    valid = fusion_room.depth[fusion_room.depth > 0]
    # The rule, on the sampled depths fuse() uses (every 4th pixel): 1.1 x p99, median / 200.
    sample = fusion_room.depth[:, ::4, ::4].ravel()
    assert fused_room.max_depth == pytest.approx(1.1 * np.percentile(sample, 99), rel=1e-6)
    sampled_median = np.median(sample[sample <= fused_room.max_depth])
    assert fused_room.voxel_size == pytest.approx(sampled_median / 200, rel=1e-6)
    assert fused_room.voxel_size == pytest.approx(np.median(valid) / 200, rel=0.02)
    assert fused_room.trunc == pytest.approx(FusionOptions.trunc_voxels * fused_room.voxel_size)
    assert auto_voxel_size(2.0) == pytest.approx(0.01)
    assert auto_voxel_size(0.3) == 0.005 and auto_voxel_size(40.0) == 0.05
    # A constant 2 m depth: voxel 1 cm, max depth 2.2 m.
    flat = np.full((2, 24, 32), 2.0, np.float32)
    poses = np.stack([np.eye(4)] * 2)
    r = fuse(flat, None, poses, (30.0, 30.0, 15.5, 11.5), FusionOptions(**QUIET))
    assert (r.voxel_size, r.trunc, r.max_depth) == pytest.approx((0.01, 0.08, 2.2))
    # Overrides win.
    r = fuse(flat, None, poses, (30.0, 30.0, 15.5, 11.5),
             FusionOptions(voxel_size=0.02, trunc=0.05, max_depth=3.0, **QUIET))
    assert (r.voxel_size, r.trunc, r.max_depth) == pytest.approx((0.02, 0.05, 3.0))
    # The voxel as another share of the median depth (fusion.voxel_per_depth).
    r = fuse(flat, None, poses, (30.0, 30.0, 15.5, 11.5),
             FusionOptions(voxel_per_depth=1 / 150, trunc_voxels=6, **QUIET))
    assert (r.voxel_size, r.trunc) == pytest.approx((2.0 / 150, 0.08))


def test_block_estimate_and_budget(fusion_room, fused_room, caplog):
    # The estimate predicts what integration allocates.
    assert fused_room.blocks_used == pytest.approx(fused_room.block_estimate, rel=0.2)
    est = estimate_block_count(fusion_room.depth, fusion_room.poses, fusion_room.intrinsics, fused_room.voxel_size,
                               fused_room.trunc, fused_room.max_depth)
    assert est == fused_room.block_estimate
    # A budget 4x too small: the voxel grows (about 2x) with a warning instead of failing.
    budget = fused_room.block_estimate // 4
    frames = slice(0, 20, 4)
    with caplog.at_level(logging.WARNING, logger="recon.fusion.sizing"):
        r = fuse(fusion_room.depth[frames], fusion_room.rgb[frames], fusion_room.poses[frames], fusion_room.intrinsics,
                 FusionOptions(block_count=budget, **QUIET))
    assert any("budget" in rec.message for rec in caplog.records)
    assert r.block_estimate <= budget and r.blocks_used <= 1.2 * budget
    assert r.voxel_size > 1.5 * fused_room.voxel_size
    assert r.trunc == pytest.approx(FusionOptions.trunc_voxels * r.voxel_size)
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

    kept = fuse(depth, seq.rgb, seq.poses, seq.intrinsics,
                FusionOptions(min_fragment_triangles=0, min_fragment_fraction=0, **opts))
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


def test_fusion_inputs(fusion_room):
    poses = fusion_room.poses[:4].copy()
    poses[1] = np.nan  # an untracked frame is skipped, not fused
    r = fuse(fusion_room.depth[:4], fusion_room.rgb[:4], poses, fusion_room.intrinsics, FusionOptions(**QUIET))
    assert r.frames_fused == 3
    # Per-frame intrinsics and an uncoloured fusion.
    k = np.tile(fusion_room.intrinsics, (4, 1))
    r = fuse(fusion_room.depth[:4], None, fusion_room.poses[:4], k, FusionOptions(**QUIET))
    assert len(r.mesh.triangles) > 0 and not r.mesh.has_vertex_colors()
    with pytest.raises(ReconInputError):
        fuse(np.zeros((2, 8, 8), np.float32), None, fusion_room.poses[:2], fusion_room.intrinsics,
             FusionOptions(**QUIET))
    with pytest.raises(ReconInputError):
        fuse(fusion_room.depth[:2], None, fusion_room.poses[:2], fusion_room.intrinsics,
             FusionOptions(voxel_size=-1.0, **QUIET))
    with pytest.raises(ReconInputError):
        fuse(fusion_room.depth[:2], None, fusion_room.poses[:2], fusion_room.intrinsics,
             FusionOptions(device="tpu", **QUIET))


def test_depth_all_beyond_max_depth_gives_an_empty_mesh_and_says_so(fusion_room, caplog):
    """Open3D raises when a frame touches no block and when an empty volume is meshed; a
    fusion that keeps nothing returns empty geometry and warns instead."""
    options = FusionOptions(max_depth=0.05, point_cloud=True, **QUIET)
    with caplog.at_level(logging.WARNING):
        r = fuse(fusion_room.depth[:3], fusion_room.rgb[:3], fusion_room.poses[:3], fusion_room.intrinsics, options)
    assert r.frames_fused == 0 and r.blocks_used == 0
    assert len(r.mesh.triangles) == 0 and len(r.point_cloud.points) == 0
    assert any("mesh is empty" in rec.message and "--max-depth 0.05" in rec.message for rec in caplog.records)


@pytest.mark.skipif(not (SHARED_DATA / "7scenes-redkitchen").is_dir(), reason="../shared is not present")
def test_fuse_real_sensor_depth(tmp_path):
    """7-Scenes sensor depth with its ground-truth poses gives a clean kitchen surface."""
    from recon.io.frames import open_source

    src = open_source(SHARED_DATA / "7scenes-redkitchen", width=160, stride=20, max_frames=10)
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


def test_cuda_without_open3d_cuda_falls_back_to_the_cpu(monkeypatch, caplog):
    """--device cuda where only torch has CUDA (pip's Open3D may not): fusion runs on the
    CPU with one warning instead of failing after the GPU stages; a bad name still fails."""
    import open3d.core as o3c

    from recon.fusion import fusion_device

    monkeypatch.setattr(o3c.cuda, "is_available", lambda: False)
    with caplog.at_level(logging.WARNING):
        assert fusion_device("cuda") == o3c.Device("CPU:0")
        assert fusion_device("cuda:1") == o3c.Device("CPU:0")
    assert sum("no CUDA support" in r.getMessage() for r in caplog.records) == 2
    assert fusion_device("cpu") == o3c.Device("CPU:0")
    with pytest.raises(ReconInputError):
        fusion_device("tpu")


def test_rendered_depth_is_the_fused_surface(fusion_room):
    from recon.fusion.volume import TsdfVolume

    room = fusion_room
    h, w = room.depth.shape[1:]
    volume = TsdfVolume(0.02, 0.08, 8.0, 4096, colored=False)
    assert not volume.render_depth(room.poses[0], room.intrinsics, (h, w)).any()  # nothing fused: no surface
    for k in range(10):
        volume.integrate(room.depth[k], room.poses[k], room.intrinsics)
    for k in (5, 14):  # a fused frame, and one the fused frames only partly saw
        rendered = volume.render_depth(room.poses[k], room.intrinsics, (h, w))
        both = (rendered > 0) & (room.depth[k] > 0)
        assert both.mean() > 0.4
        error = np.abs(rendered[both] - room.depth[k][both]) / room.depth[k][both]
        assert np.median(error) < 0.01 and np.percentile(error, 90) < 0.03


def test_rendered_depth_is_the_same_every_time(fusion_room):
    # Open3D's ray cast with a coarse range map (down factor 8) left a different 2-10 % of
    # the pixels empty or on another surface from one call to the next, so the streamed
    # run's anchors, and everything after them, changed between identical runs.
    from recon.fusion.volume import TsdfVolume

    room = fusion_room
    h, w = room.depth.shape[1:]
    volume = TsdfVolume(0.02, 0.08, 8.0, 4096, colored=False)
    for k in range(10):
        volume.integrate(room.depth[k], room.poses[k], room.intrinsics)
    first = volume.render_depth(room.poses[5], room.intrinsics, (h, w))
    for _ in range(6):
        assert np.array_equal(volume.render_depth(room.poses[5], room.intrinsics, (h, w)), first)


def test_ray_casting_more_blocks_than_open3d_holds_at_once(fusion_room):
    # Open3D's ray cast holds the blocks' screen tiles in a buffer of 65535; cast at once, a
    # phone video's volume (58540 tiles at 160x285) crashed the process. The blocks in view are
    # cast in passes of fewer tiles, the passes' nearest surface kept: the same surface.
    import open3d.core as o3c

    from recon.fusion.volume import RANGE_TILE_BUDGET, TsdfVolume, blocks_in_view, tile_batches

    room = fusion_room
    h, w = room.depth.shape[1:]
    volume = TsdfVolume(0.004, 0.016, 8.0, 65536, colored=False)
    for k in range(0, 10, 3):
        volume.integrate(room.depth[k], room.poses[k], room.intrinsics)
    scale = 3  # a larger image: each block covers more tiles
    big = np.asarray(room.intrinsics, np.float64) * scale
    hashmap = volume.grid.hashmap()
    keys = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)].cpu().numpy()
    seen, tiles, _ = blocks_in_view(keys, volume.voxel * volume.block_resolution, room.poses[5], big,
                                    (h * scale, w * scale), volume.max_depth)
    assert tiles.sum() > 65535 and len(tile_batches(tiles, RANGE_TILE_BUDGET)) >= 2
    rendered = volume.render_depth(room.poses[5], big, (h * scale, w * scale))[::scale, ::scale]
    both = (rendered > 0) & (room.depth[5] > 0)
    assert both.mean() > 0.4
    error = np.abs(rendered[both] - room.depth[5][both]) / room.depth[5][both]
    assert np.median(error) < 0.01 and np.percentile(error, 90) < 0.03


def test_tile_batches_cover_every_block_once_within_the_budget():
    from recon.fusion.volume import tile_batches

    tiles = np.random.default_rng(0).integers(1, 50, 1000).astype(float)
    runs = tile_batches(tiles, 2000)
    assert np.array_equal(np.concatenate(runs), np.arange(1000))
    assert all(tiles[r].sum() <= 2000 + tiles.max() for r in runs) and len(runs) >= tiles.sum() // 2000


def _signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_canonical_mesh_is_the_same_surface_whatever_the_order():
    from recon.fusion.volume import canonical_mesh

    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    box.vertex_colors = o3d.utility.Vector3dVector(np.asarray(box.vertices) / 3.0)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(box.vertices))
    inverse = np.argsort(perm)
    shuffled = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(box.vertices)[perm]),
        o3d.utility.Vector3iVector(np.roll(inverse[np.asarray(box.triangles)], 1, axis=1)[
            rng.permutation(len(box.triangles))]))
    shuffled.vertex_colors = o3d.utility.Vector3dVector(np.asarray(box.vertex_colors)[perm])
    a, b = canonical_mesh(box), canonical_mesh(shuffled)
    for field in ("vertices", "triangles", "vertex_colors"):
        assert np.array_equal(np.asarray(getattr(a, field)), np.asarray(getattr(b, field))), field
    # Same winding: the closed box keeps its signed volume (6 m^3), outward normals.
    assert _signed_volume(np.asarray(a.vertices), np.asarray(a.triangles)) == pytest.approx(6.0)
    assert np.allclose(np.asarray(a.vertex_colors), np.asarray(a.vertices) / 3.0)


def test_the_same_frames_give_the_same_mesh_file(fusion_room, tmp_path):
    # Open3D's parallel hash map orders extracted vertices differently from run to run.
    from recon.fusion.volume import TsdfVolume

    room = fusion_room
    meshes = []
    for _ in range(3):
        volume = TsdfVolume(0.02, 0.08, 8.0, 4096, colored=True)
        for k in range(8):
            volume.integrate(room.depth[k], room.poses[k], room.intrinsics, room.rgb[k])
        meshes.append(volume.mesh(FusionOptions())[0])
    assert len(meshes[0].triangles) > 1000
    for mesh in meshes[1:]:
        assert np.array_equal(np.asarray(mesh.vertices), np.asarray(meshes[0].vertices))
        assert np.array_equal(np.asarray(mesh.triangles), np.asarray(meshes[0].triangles))


def test_the_voxel_follows_the_depth_alone_where_its_metres_are_not_trusted():
    """A metric scene's voxel is held within 5 mm - 5 cm; where the prior cannot vouch for the
    scale (a close-up 5x too far, a street 25x too near) it follows the depth alone."""
    assert auto_voxel_size(0.3) == 0.005 and auto_voxel_size(0.3, metric=False) == pytest.approx(0.0015)
    assert auto_voxel_size(40.0) == 0.05 and auto_voxel_size(40.0, metric=False) == pytest.approx(0.2)
    assert auto_voxel_size(2.5, metric=False) == auto_voxel_size(2.5)


def test_a_pixel_of_weight_two_counts_as_two_observations(fusion_room):
    """integrate(weight=w) is w integrations of the pixels of weight >= each count: weight 2
    on one frame leaves the same voxels as fusing that frame twice, weight 0 leaves it out."""
    from recon.fusion import TsdfVolume

    room = fusion_room
    once, twice = (TsdfVolume(0.02, 0.08, 6.0, 4096, colored=False) for _ in range(2))
    weight = np.full(room.depth[0].shape, 2, np.uint8)
    weight[:, : weight.shape[1] // 2] = 0
    once.integrate(room.depth[0], room.poses[0], room.intrinsics, weight=weight)
    half = np.where(weight > 0, room.depth[0], 0)
    for _ in range(2):
        twice.integrate(half, room.poses[0], room.intrinsics)
    values = [(v.grid.attribute("tsdf").numpy().ravel(), v.grid.attribute("weight").numpy().ravel())
              for v in (once, twice)]
    assert once.blocks_used == twice.blocks_used and values[0][1].max() == 2
    order = [np.lexsort((t, w)) for t, w in values]
    assert np.allclose(values[0][1][order[0]], values[1][1][order[1]])
    assert np.allclose(values[0][0][order[0]], values[1][0][order[1]], atol=1e-6)


def test_confidence_weights_keep_what_the_gate_drops(fusion_room):
    """Each frame's left half confirmed (confidence 0.5), its right half filled (0.05) and
    1.5 cm too far: the gate at 0.1 loses what only right halves saw, weighing keeps it."""
    room = fusion_room
    confidence = np.full(room.depth.shape, 0.5, np.float32)
    confidence[..., room.depth.shape[2] // 2:] = 0.05
    depth = np.where(confidence < 0.1, room.depth + 0.015, room.depth).astype(np.float32)
    seen = lambda p: visible_mask(p, room.depth, room.poses, room.intrinsics)  # noqa: E731
    scores = {}
    for name, extra in {"gate": dict(min_confidence=0.1, weight_threshold=2),
                        "weighed": dict(min_confidence=0.02, confidence_weights=(0.1, 0.1, 0.1), weight_threshold=5),
                        }.items():
        fused = fuse(depth, room.rgb, room.poses, room.intrinsics,
                     FusionOptions(voxel_size=0.01, **extra, **QUIET), confidence=confidence)
        scores[name] = mesh_metrics(fused.mesh, room.o3d_mesh(), threshold=0.02, num_points=20_000,
                                    point_filter=seen)
    assert scores["weighed"].recall > scores["gate"].recall + 0.1, scores
    assert scores["weighed"].fscore > scores["gate"].fscore + 0.05, scores


def test_a_confirmed_pixel_outweighs_a_filled_one_by_its_levels(fusion_room):
    """One view fused twice, confirmed (0.5) and filled 2 cm too far (0.05): the surface comes
    out at the weighted mean, 1 cm back with equal weights, 4 mm with the confirmed pixel
    counted 4x (confidence_weight), as the weights say."""
    from recon.fusion import TsdfVolume
    from recon.fusion.tsdf import confidence_weight

    assert confidence_weight(np.array([0.0, 0.05, 0.5]), 0.02, (0.1, 0.1, 0.1)).tolist() == [0, 1, 4]
    room, levels = fusion_room, {"alike": (), "weighed": (0.1, 0.1, 0.1)}
    truth = room.depth[0]
    rows, cols = truth.shape
    inner = (slice(rows // 4, 3 * rows // 4), slice(cols // 4, 3 * cols // 4))

    def surface_offset(views, levels) -> float:
        """Median depth of the surface fused from `views` ((depth, confidence) pairs) past the truth."""
        volume = TsdfVolume(0.01, 0.08, 6.0, 4096, colored=False)
        for depth, confidence in views:
            weight = confidence_weight(np.full(truth.shape, confidence), 0.02, levels)
            volume.integrate(depth, room.poses[0], room.intrinsics, weight=weight)
        rendered = volume.render_depth(room.poses[0], room.intrinsics, truth.shape, min_weight=1.0)
        return float(np.median((rendered - truth)[inner][rendered[inner] > 0]))

    # The ray cast's own offset at this voxel, from the confirmed view alone.
    base = surface_offset([(truth, 0.5)], ())
    for name, expected in {"alike": 0.010, "weighed": 0.004}.items():
        offset = surface_offset([(truth, 0.5), (truth + 0.02, 0.05)], levels[name]) - base
        assert offset == pytest.approx(expected, abs=0.0015), name


def test_the_surface_estimate_follows_what_marching_cubes_extracts(fusion_room, caplog):
    """surface_triangles is within 20 % of the triangles extracted at each weight, and a surface
    over EXTRACTION_BUDGET_FACTOR x the budget is meshed at the lowest weight that fits it."""
    from recon.fusion import TsdfVolume
    from recon.fusion.tsdf import finished_mesh
    from recon.fusion.volume import EXTRACTION_BUDGET_FACTOR

    room = fusion_room
    volume = TsdfVolume(0.02, 0.08, 8.0, 4096, colored=False)
    for k in (0, 0, 0, 19):  # weight 1: what frame 19 alone saw; 3: frame 0 alone; 4: both
        volume.integrate(room.depth[k], room.poses[k], room.intrinsics)
    extracted = {}
    for weight in (1, 2, 3):
        options = FusionOptions(weight_threshold=weight, max_triangles=0, min_fragment_triangles=0)
        mesh, removed = volume.mesh(options)
        extracted[weight] = len(mesh.triangles) + removed
        assert volume.surface_triangles(weight) == pytest.approx(extracted[weight], rel=0.2), weight
    assert extracted[1] > 1.1 * extracted[2] > 0
    budget = int(0.5 * (extracted[1] + extracted[2])) // EXTRACTION_BUDGET_FACTOR + 1
    options = FusionOptions(weight_threshold=1, max_triangles=budget, min_fragment_triangles=0)
    assert volume.bounded_weight(options) == 2
    assert volume.bounded_weight(FusionOptions(weight_threshold=1, max_triangles=0)) == 1
    assert volume.bounded_weight(FusionOptions(weight_threshold=1, max_extracted=0)) == 1
    assert volume.bounded_weight(FusionOptions(weight_threshold=1, max_extracted=volume.surface_triangles(3) - 1)) == 4
    with caplog.at_level(logging.WARNING):
        *_, used = finished_mesh(volume, options, confidence_used=False)
    assert used == 2 and "meshing the surface seen by 2 instead" in caplog.text
