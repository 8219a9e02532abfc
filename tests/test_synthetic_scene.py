"""The synthetic room (recon.synthetic): determinism, depth/pose/intrinsics/mesh
consistency, the camera path, textures, motion blur and argument checks."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from recon.errors import ReconInputError
from recon.synthetic import render_sequence


@pytest.fixture(scope="module")
def long_seq():
    """Enough frames for a 64-frame gap, at a tiny size."""
    return render_sequence(num_frames=70, width=80, height=60, seed=1)


def backproject(depth: np.ndarray, pose: np.ndarray, intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World points (P, 3) of pixels (u, v) (P,) with z-depth (P,) seen from a camera-to-world pose."""
    fx, fy, cx, cy = intrinsics
    cam = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], axis=-1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def depth_off_mesh(seq, frames, samples: int) -> float:
    """Largest distance (m) from the mesh of `samples` random pixels of each of `frames` of a
    SyntheticSequence, back-projected with their rendered depth: 0 when depth is the mesh's."""
    scene = seq.raycasting_scene()
    rng = np.random.default_rng(0)
    worst = 0.0
    for i in frames:
        u = rng.integers(0, seq.width, samples).astype(np.float64)
        v = rng.integers(0, seq.height, samples).astype(np.float64)
        depth = seq.depth[i, v.astype(int), u.astype(int)].astype(np.float64)
        points = backproject(depth, seq.poses[i], seq.intrinsics, u, v)
        worst = max(worst, float(scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().max()))
    return worst


def project(points: np.ndarray, pose: np.ndarray, intrinsics):
    """Pixel coordinates u, v and z-depth (P,) of world points (P, 3) in a camera-to-world pose."""
    fx, fy, cx, cy = intrinsics
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    z = cam[:, 2]
    return fx * cam[:, 0] / z + cx, fy * cam[:, 1] / z + cy, z


def bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    du, dv = u - u0, v - v0
    return (
        image[v0, u0] * (1 - du) * (1 - dv)
        + image[v0, u0 + 1] * du * (1 - dv)
        + image[v0 + 1, u0] * (1 - du) * dv
        + image[v0 + 1, u0 + 1] * du * dv
    )


def test_shapes_and_types(small_room):
    n, h, w = 12, 120, 160
    assert small_room.rgb.shape == (n, h, w, 3) and small_room.rgb.dtype == np.uint8
    assert small_room.depth.shape == (n, h, w) and small_room.depth.dtype == np.float32
    assert small_room.poses.shape == (n, 4, 4) and small_room.poses.dtype == np.float64
    fx, fy, cx, cy = small_room.intrinsics
    assert fx == fy == pytest.approx(525.0 * w / 640)
    assert (cx, cy) == ((w - 1) / 2, (h - 1) / 2)
    np.testing.assert_allclose(small_room.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    rotations = small_room.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (n, 3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-12)
    mesh = small_room.o3d_mesh()
    assert isinstance(mesh, o3d.geometry.TriangleMesh)
    assert len(mesh.triangles) == len(small_room.mesh_triangles) > 100
    assert small_room.mesh_colors.shape == small_room.mesh_vertices.shape


def test_deterministic():
    a = render_sequence(num_frames=3, width=64, height=48, seed=3)
    b = render_sequence(num_frames=3, width=64, height=48, seed=3)
    for name in ("rgb", "depth", "poses", "mesh_vertices", "mesh_triangles"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = render_sequence(num_frames=3, width=64, height=48, seed=4)
    assert not np.array_equal(a.rgb, c.rgb)
    assert (not np.array_equal(a.mesh_vertices.shape, c.mesh_vertices.shape)
            or not np.array_equal(a.mesh_vertices, c.mesh_vertices))


def test_depth_positive_and_finite(small_room):
    assert np.isfinite(small_room.depth).all()
    assert (small_room.depth > 0.1).all()
    # The room is 6 x 5 x 2.7 m: nothing is farther than its diagonal.
    assert small_room.depth.max() < np.sqrt(6**2 + 5**2 + 2.7**2)


def test_depth_lies_on_the_mesh(small_room):
    assert depth_off_mesh(small_room, (0, 5, 11), 400) < 1e-3


def test_reprojection_between_frames_agrees(small_room):
    """Pixels of frame i moved into frame j with GT depth and poses land where frame j's
    own depth sees the same point (inverse depth is exactly bilinear on planes)."""
    h, w = small_room.height, small_room.width
    for i, j in ((0, 4), (3, 11)):
        v, u = np.mgrid[0:h, 0:w].reshape(2, -1).astype(np.float64)
        depth = small_room.depth[i].reshape(-1).astype(np.float64)
        points = backproject(depth, small_room.poses[i], small_room.intrinsics, u, v)
        uj, vj, zj = project(points, small_room.poses[j], small_room.intrinsics)
        inside = (uj >= 0) & (uj <= w - 1.001) & (vj >= 0) & (vj <= h - 1.001) & (zj > 0)
        assert inside.mean() > 0.5
        seen = 1.0 / bilinear(1.0 / small_room.depth[j].astype(np.float64), uj[inside], vj[inside])
        rel = np.abs(seen - zj[inside]) / zj[inside]
        # Occlusion boundaries and box edges break bilinear interpolation; the rest is exact.
        assert np.median(rel) < 1e-5
        assert (rel < 1e-3).mean() > 0.85


def test_camera_path_is_smooth_and_inside_free_space(long_seq):
    centres = long_seq.poses[:, :3, 3]
    lo, hi = long_seq.room_bounds
    assert ((centres > lo + 0.5) & (centres < hi - 0.5)).all()
    for box_lo, box_hi in long_seq.boxes:
        assert not ((centres > box_lo - 0.3) & (centres < box_hi + 0.3)).all(axis=1).any()
    distance = long_seq.raycasting_scene().compute_distance(o3d.core.Tensor(centres.astype(np.float32))).numpy()
    assert distance.min() > 0.5
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert 0.01 < steps.mean() < 0.04 and steps.max() < 0.05
    forward = long_seq.poses[:, :3, 2]
    turn = np.degrees(np.arccos(np.clip((forward[1:] * forward[:-1]).sum(1), -1, 1)))
    assert turn.max() < 2.0
    # The camera looks slightly down (world y is down) and turns through the room.
    assert (forward[:, 1] > 0).all()
    assert np.degrees(np.arccos(np.clip(forward[0] @ forward[-1], -1, 1))) > 15


@pytest.mark.parametrize("gap", [32, 64])
def test_distant_frames_overlap(long_seq, gap):
    h, w = long_seq.height, long_seq.width
    v, u = np.mgrid[0:h, 0:w].reshape(2, -1).astype(np.float64)
    shares = []
    for i in range(0, len(long_seq.poses) - gap, 3):
        depth = long_seq.depth[i].reshape(-1).astype(np.float64)
        points = backproject(depth, long_seq.poses[i], long_seq.intrinsics, u, v)
        uj, vj, zj = project(points, long_seq.poses[i + gap], long_seq.intrinsics)
        inside = (uj >= 0) & (uj <= w - 1) & (vj >= 0) & (vj <= h - 1) & (zj > 0)
        seen = long_seq.depth[i + gap][np.round(vj[inside]).astype(int), np.round(uj[inside]).astype(int)]
        visible = np.abs(seen - zj[inside]) < 0.05 * zj[inside]
        shares.append(visible.sum() / (h * w))
    assert min(shares) > 0.3


def test_textures_are_not_flat(small_room):
    gray = small_room.rgb.mean(axis=-1).astype(np.float32)
    for frame in gray[::4]:
        gx = cv2.Sobel(frame, cv2.CV_32F, 1, 0, ksize=3) / 8
        gy = cv2.Sobel(frame, cv2.CV_32F, 0, 1, ksize=3) / 8
        magnitude = cv2.blur(np.hypot(gx, gy), (5, 5))
        # Mean intensity change of over 2 grey levels per pixel in nearly every 5x5 window.
        assert (magnitude > 2.0).mean() > 0.95
    assert small_room.rgb.std() > 20


def test_blur_is_rendered_and_ground_truth_is_the_frame_time():
    sharp = render_sequence(4, 160, 120, seed=2, speed=6)
    blurred = render_sequence(4, 160, 120, seed=2, speed=6, blur=4)
    assert np.array_equal(sharp.poses, blurred.poses) and np.array_equal(sharp.depth, blurred.depth)
    difference = np.abs(sharp.rgb.astype(float) - blurred.rgb).mean()
    assert difference > 1.0  # grey levels: a blurred image, not the sharp one
    # Sharp frames at 6x speed are every 6th frame of the default path.
    assert np.allclose(render_sequence(19, 160, 120, seed=2).poses[::6], sharp.poses)


def test_bad_render_arguments():
    with pytest.raises(ReconInputError):
        render_sequence(num_frames=0)
    with pytest.raises(ReconInputError):
        render_sequence(num_frames=2, width=4, height=4)
