"""The upright rotation (recon.fusion.upright) on scenes whose up is known: a box room seen
by cameras pitched down, the whole scene tilted by a known rotation."""

import io

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.fusion.upright import UPRIGHT_UP, camera_up, estimate_upright, refine_with_surfaces, rotation_between


def _angle(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _room_points(rng, with_table: bool = True) -> np.ndarray:
    """(M, 3) points of a 4 x 2.5 x 5 m room in OpenCV world axes (y down: floor at y = 1.2),
    a table top at y = 0.45, and 5 mm noise."""
    n = 6000
    u, v = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    floor = np.stack([2.0 * u, np.full(n, 1.2), 2.5 * v], 1)
    back = np.stack([2.0 * u, 0.0 + 1.2 * v, np.full(n, 2.5)], 1)
    left = np.stack([np.full(n, -2.0), 0.0 + 1.2 * v, 2.5 * u], 1)
    parts = [floor, back, left]
    if with_table:
        parts.append(np.stack([0.5 * u[: n // 3], np.full(n // 3, 0.45), 1.0 + 0.4 * v[: n // 3]], 1))
    return np.concatenate(parts) + rng.normal(0, 0.005, (sum(len(p) for p in parts), 3))


def _cameras(yaws_deg, pitch_down_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """(N, 4, 4) camera-to-world of level-held cameras (OpenCV axes) turned by yaw about the
    world's y, pitched down and rolled by the given angles."""
    poses = []
    for yaw in yaws_deg:
        r = Rotation.from_euler("y", yaw, degrees=True) * Rotation.from_euler("x", -pitch_down_deg, degrees=True) \
            * Rotation.from_euler("z", roll_deg, degrees=True)
        t = np.eye(4)
        t[:3, :3] = r.as_matrix()
        t[:3, 3] = [0.1 * np.sin(np.radians(yaw)), 0.0, 0.0]
        poses.append(t)
    return np.array(poses)


def _tilted(poses, points, rotation):
    turn = np.eye(4)
    turn[:3, :3] = rotation
    return turn @ poses, points @ rotation.T


TILT = Rotation.from_rotvec(np.radians([12.0, 5.0, -9.0])).as_matrix()


def test_cameras_alone_carry_their_pitch():
    """Without a surface the guess is the cameras' mean down axis: off by their pitch."""
    poses, _ = _tilted(_cameras(np.linspace(-30, 30, 20), pitch_down_deg=12.0), np.zeros((1, 3)), TILT)
    result = estimate_upright(poses, None)
    assert result.source == "cameras"
    assert 10.0 < _angle(result.up, TILT @ UPRIGHT_UP) < 12.5  # the pans average a little of it out


@pytest.mark.parametrize("pitch_deg", [18.0, 28.0])
def test_floors_and_walls_correct_the_cameras_pitch(pitch_deg):
    """Cameras pitched down as far as 7-Scenes' kitchen is filmed (25 degrees on average,
    beyond a first cone of 20 around their guess): the vote finds the floor."""
    rng = np.random.default_rng(0)
    poses, points = _tilted(_cameras(np.zeros(20), pitch_down_deg=pitch_deg, roll_deg=4.0), _room_points(rng), TILT)
    truth = TILT @ UPRIGHT_UP
    assert _angle(camera_up(poses), truth) > pitch_deg - 3.0
    result = estimate_upright(poses, points)
    assert result.source == "surfaces"
    assert result.horizontal > 0.2 and result.vertical > 0.2
    assert _angle(result.up, truth) < 1.0
    # The rotation stands the scene upright: the floor's points share one height afterwards.
    floor = points[:6000] @ result.rotation.T
    assert np.std(floor[:, 1]) < 0.02
    assert result.tilt_deg == pytest.approx(_angle(result.up, UPRIGHT_UP), abs=1e-6)


def test_one_slanted_plane_does_not_tip_the_scene():
    """A close-up of one surface at 45 degrees to the cameras' up is neither floor nor wall:
    the cameras' estimate stands."""
    rng = np.random.default_rng(1)
    poses = _cameras(np.linspace(-10, 10, 10), pitch_down_deg=0.0)
    u, v = rng.uniform(-1, 1, (2, 5000))
    normal = np.array([0.0, np.sqrt(0.5), -np.sqrt(0.5)])
    points = np.stack([u, 0.5 * v, 2.0 + 0.5 * v], 1)  # the plane y = z - 2, at 45 degrees
    assert (points @ normal).std() < 1e-9
    result = estimate_upright(poses, points)
    assert result.source == "cameras"
    assert _angle(result.up, UPRIGHT_UP) < 1.0


def test_without_poses_the_world_is_left_as_it_is():
    result = estimate_upright(np.full((3, 4, 4), np.nan), None)
    assert result.source == "none"
    np.testing.assert_array_equal(result.rotation, np.eye(3))


def test_refine_keeps_the_hemisphere_and_rotation_maps_up():
    floor = np.array([0.0, 1.0, 0.05]) / np.hypot(1, 0.05)
    up, horizontal, vertical = refine_with_surfaces(np.array([0.0, -1.0, 0.0]), np.repeat(floor[None], 10, axis=0))
    assert horizontal == 1.0 and vertical == 0.0 and up[1] < 0
    assert _angle(up, -floor) < 0.1
    for a in (np.array([0.3, -0.9, 0.1]), np.array([0.0, 1.0, 0.0]), UPRIGHT_UP):
        r = rotation_between(a, UPRIGHT_UP)
        np.testing.assert_allclose(r @ (a / np.linalg.norm(a)), UPRIGHT_UP, atol=1e-9)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)


def test_glb_of_a_tilted_floor_stands_on_plus_y():
    """The GLB written with the estimated rotation has its floor normal on glTF's +y."""
    import open3d as o3d
    import trimesh

    from recon.export import glb_bytes

    rng = np.random.default_rng(2)
    poses, points = _tilted(_cameras(np.zeros(10), pitch_down_deg=15.0), _room_points(rng), TILT)
    upright = estimate_upright(poses, points)
    floor = o3d.geometry.TriangleMesh()
    floor.vertices = o3d.utility.Vector3dVector(np.array([[-2, 1.2, -2], [2, 1.2, -2], [2, 1.2, 2], [-2, 1.2, 2.0]])
                                                @ TILT.T)
    floor.triangles = o3d.utility.Vector3iVector(np.array([[0, 2, 1], [0, 3, 2]]))
    scene = trimesh.load(io.BytesIO(glb_bytes(floor, upright.rotation)), file_type="glb", force="mesh")
    normal = scene.face_normals.mean(axis=0)
    assert _angle(normal, np.array([0.0, 1.0, 0.0])) < 1.0 or _angle(-normal, np.array([0.0, 1.0, 0.0])) < 1.0
    flat = trimesh.load(io.BytesIO(glb_bytes(floor)), file_type="glb", force="mesh").face_normals.mean(axis=0)
    assert min(_angle(flat, np.array([0.0, 1.0, 0.0])), _angle(-flat, np.array([0.0, 1.0, 0.0]))) > 10.0
