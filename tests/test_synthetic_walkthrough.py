"""The synthetic walk-through (recon.synthetic.walkthrough, with recon.synthetic.floorplan):
determinism, a closed shell and depth on the mesh, a path through every room and the
corridor at walking pace, a textureless stretch that really has no texture, a fast turn of
the stated angle within the stated frames, motion blur there, and cuts inside the stretches."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from recon.errors import ReconInputError
from recon.synthetic.walkthrough import TEXTURELESS_SHARE, render_walkthrough, walkthrough_plan
from test_synthetic_scene import depth_off_mesh

SIZE = (160, 120)


@pytest.fixture(scope="module")
def plan():
    return walkthrough_plan(seed=0)


@pytest.fixture(scope="module")
def subset(plan):
    """Walk frames to render: every 30th, a run in the textureless stretch and the fast
    turn with a sharp frame on either side."""
    quiet = plan.stretches["textureless"]
    turn = plan.stretches["fast_turn"]
    picked = {*range(0, plan.num_frames, 30), *range(quiet[0] + 10, quiet[0] + 14), *range(turn[0] - 3, turn[1] + 3)}
    return np.array(sorted(picked))


@pytest.fixture(scope="module")
def walk(subset):
    return render_walkthrough(*SIZE, seed=0, frames=subset)


def mesh_scene(plan) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(plan.scene.vertices.astype(np.float32)),
                        o3d.core.Tensor(plan.scene.triangles.astype(np.uint32)))
    return scene


def yaw_degrees(poses: np.ndarray) -> np.ndarray:
    """(N,) unwrapped heading of the optical axis in the floor plane, degrees (0: +z, 90: +x)."""
    return np.degrees(np.unwrap(np.arctan2(poses[:, 0, 2], poses[:, 2, 2])))


def step_angles(poses: np.ndarray) -> np.ndarray:
    """(N-1,) rotation angle in degrees between consecutive poses."""
    rel = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    return np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def planar_texture(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Texture: grey levels (P,) of the image's detail finer than ~2 pixels (the image less
    its Gaussian blur, which keeps smooth shading out) at pixels inside planar surfaces.
    Inverse depth is affine in the pixel coordinates on a plane, so its Laplacian vanishes
    away from edges between faces; those edges, and the blur's reach around them, are left out."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    detail = np.abs(grey - cv2.GaussianBlur(grey, (0, 0), 2.0))
    inv = 1.0 / depth.astype(np.float64)
    curvature = np.abs(cv2.Laplacian(inv, cv2.CV_64F, ksize=3)) / inv
    planar = cv2.erode((curvature < 1e-3).astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    return detail[planar]


def test_metadata_shapes_and_intrinsics(walk, subset):
    n, (w, h) = len(subset), SIZE
    assert walk.rgb.shape == (n, h, w, 3) and walk.rgb.dtype == np.uint8
    assert walk.depth.shape == (n, h, w) and walk.depth.dtype == np.float32
    assert walk.poses.shape == (n, 4, 4) and np.array_equal(walk.frame_ids, subset)
    fx, fy, cx, cy = walk.intrinsics
    assert fx == fy == pytest.approx(525.0 * w / 640) and (cx, cy) == ((w - 1) / 2, (h - 1) / 2)
    assert walk.fps == 30.0 and walk.blur.shape == (n,)
    assert len(walk.textured_share) > 300  # the whole walk's, 300+ frames


def test_deterministic_and_independent_of_the_frames_rendered(walk, subset):
    picked = subset[[0, len(subset) // 2, -1]]
    again = render_walkthrough(*SIZE, seed=0, frames=picked, threads=1)
    where = np.searchsorted(subset, picked)
    np.testing.assert_array_equal(again.rgb, walk.rgb[where])
    np.testing.assert_array_equal(again.depth, walk.depth[where])
    np.testing.assert_array_equal(again.mesh_vertices, walk.mesh_vertices)
    other = walkthrough_plan(seed=1)
    assert not np.array_equal(other.scene.vertices.shape, walk.mesh_vertices.shape) or \
        not np.array_equal(other.scene.vertices, walk.mesh_vertices)
    assert not np.array_equal(other.poses[picked], walk.poses[np.searchsorted(subset, picked)])


def test_shell_is_closed(plan):
    """Rays in every direction from anywhere in the free space hit a face (depth > 0 everywhere)."""
    rng = np.random.default_rng(0)
    scene = mesh_scene(plan)
    for region in plan.scene.regions:
        n = 20000
        lo, hi = np.array(region.lo), np.array(region.hi)
        xz = rng.uniform(lo + 0.07, hi - 0.07, (n, 2))
        origin = np.stack([xz[:, 0], rng.uniform(-2.65, -0.05, n), xz[:, 1]], axis=1)
        direction = rng.standard_normal((n, 3))
        rays = np.hstack([origin, direction / np.linalg.norm(direction, axis=1, keepdims=True)])
        t = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        assert np.isfinite(t).all(), region.name


def test_depth_positive_and_on_the_mesh(walk):
    assert np.isfinite(walk.depth).all() and (walk.depth > 0.1).all()
    lo, hi = walk.room_bounds
    assert walk.depth.max() < np.linalg.norm(hi - lo)
    assert depth_off_mesh(walk, range(0, len(walk.frame_ids), 4), 300) < 1e-3


def test_path_walks_through_every_room_and_the_corridor_at_walking_pace(plan):
    s = plan.stretches
    order = ["room_a", "corridor", "door_b", "room_b", "door_c", "room_c"]
    starts = [s[name][0] for name in order]
    assert starts == sorted(starts) and starts[0] == 0 and s["room_c"][1] == plan.num_frames >= 300
    for name in ("room_a", "corridor", "room_b", "room_c"):
        assert s[name][1] - s[name][0] >= 60, name  # two seconds or more in each
    centres = plan.poses[:, :3, 3]
    # Every camera centre is in the free space, a head's width from walls, jambs and furniture.
    inside = np.zeros(len(centres), bool)
    for region in plan.scene.regions:
        inside |= region.contains(centres[:, 0], centres[:, 2])
    assert inside.all()
    distance = mesh_scene(plan).compute_distance(o3d.core.Tensor(centres.astype(np.float32))).numpy()
    assert distance.min() > 0.25
    # A walk: 3-5 cm per frame, except while turning fast and looking around at the end.
    steps = np.linalg.norm(np.diff(centres[:, [0, 2]], axis=0), axis=1)
    walking = np.ones(len(steps), bool)
    walking[s["fast_turn"][0] - 15 : s["fast_turn"][1] + 15] = False
    walking[-40:] = False
    assert 0.03 <= np.median(steps[walking]) <= 0.05 and np.percentile(steps[walking], 95) < 0.06


def test_textureless_stretch_has_no_texture(plan, walk):
    first, stop = plan.stretches["textureless"]
    assert stop - first >= 45  # 1.5 s or more
    assert (plan.textured_share[first:stop] <= TEXTURELESS_SHARE).all()
    corridor = plan.stretches["corridor"]
    assert max(first, corridor[0]) < min(stop, corridor[1])  # in the corridor (it starts looking into it)
    quiet = (walk.frame_ids >= first) & (walk.frame_ids < stop)
    busy = (plan.textured_share[walk.frame_ids] > 0.95) & (walk.blur == 1)  # sharp views of the rooms
    assert quiet.sum() >= 4 and busy.sum() >= 4
    # Plain surfaces under smooth lighting: a fraction of a grey level of detail (8-bit
    # rounding), where the rooms' textures give several.
    for i in np.flatnonzero(quiet):
        detail = planar_texture(walk.rgb[i], walk.depth[i])
        assert len(detail) > 0.3 * walk.width * walk.height and np.percentile(detail, 99) < 1.0, walk.frame_ids[i]
    for i in np.flatnonzero(busy):
        assert np.median(planar_texture(walk.rgb[i], walk.depth[i])) > 3.0, walk.frame_ids[i]


def test_fast_turn_turns_by_the_stated_angle_within_its_frames(plan):
    first, stop = plan.stretches["fast_turn"]
    degrees, frames = plan.settings["turn_degrees"], plan.settings["turn_frames"]
    assert stop - first == frames + 1
    yaw = yaw_degrees(plan.poses)
    # The head's own shake adds about a degree.
    assert yaw[stop - 1] - yaw[first] == pytest.approx(-degrees, abs=2.0)
    steps = step_angles(plan.poses)
    assert steps[first : stop - 1].max() > 1.2 * degrees / frames  # peaks above the mean rate
    # Around it the head turns at an ordinary pace.
    assert steps[first - 15 : first - 1].max() < 2.0 and steps[stop : stop + 15].max() < 2.0
    assert (plan.blur[first:stop] == plan.settings["turn_blur"]).all()
    assert (np.delete(plan.blur, np.arange(first, stop)) == 1).all()


def test_fast_turn_frames_are_blurred(walk):
    first, stop = walk.stretches["fast_turn"]
    ids = walk.frame_ids

    def sharpness(i):
        grey = cv2.cvtColor(walk.rgb[i], cv2.COLOR_RGB2GRAY).astype(np.float32)
        return np.abs(cv2.Laplacian(grey, cv2.CV_32F)).mean()

    middle = int(np.flatnonzero(ids == (first + stop) // 2)[0])
    before, after = int(np.flatnonzero(ids == first - 3)[0]), int(np.flatnonzero(ids == stop + 2)[0])
    assert walk.blur[middle] > 1 and walk.blur[before] == walk.blur[after] == 1
    assert sharpness(middle) < 0.5 * min(sharpness(before), sharpness(after))


def test_cuts_lie_inside_their_stretches(plan):
    s = plan.stretches
    assert plan.cuts == sorted(plan.cuts) and len(plan.cuts) == 3
    quiet, corner, turn = plan.cuts
    assert quiet == s["textureless"][0] and s["textureless"][0] <= quiet < s["textureless"][1]
    # The corner turns out of the plain corridor: it starts with nothing to track.
    assert corner == s["corner"][0] and s["low_texture"][0] <= corner < s["low_texture"][1]
    assert plan.textured_share[corner] <= TEXTURELESS_SHARE
    assert turn == s["fast_turn"][0] and s["fast_turn"][0] <= turn < s["fast_turn"][1]
    assert s["low_texture"][0] <= s["textureless"][0] < s["textureless"][1] <= s["low_texture"][1]
    assert s["blur"] == s["fast_turn"]


def test_harder_settings_and_argument_checks():
    longer = walkthrough_plan(seed=0, corridor_length=8.0, turn_frames=5)
    base = walkthrough_plan(seed=0)
    span = lambda p: p.stretches["textureless"][1] - p.stretches["textureless"][0]  # noqa: E731
    assert span(longer) > span(base) + 40
    assert longer.stretches["fast_turn"][1] - longer.stretches["fast_turn"][0] == 6
    with pytest.raises(ReconInputError, match="corridor_length"):
        walkthrough_plan(corridor_length=2.0)
    with pytest.raises(ReconInputError, match="turn_frames"):
        walkthrough_plan(turn_frames=0)
    with pytest.raises(ReconInputError, match="8x8"):
        render_walkthrough(4, 4)
