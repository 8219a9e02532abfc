"""The synthetic walk-through: three furnished rooms and a corridor, walked through hand-held,
with a textureless stretch and a fast blurred turn at known frames: the test scene for
trajectories whose scale breaks between stretches.

Why it exists: a hand-held HoloLens walk-through of several rooms made the front end
(recon.poses) return a trajectory whose scale jumped by x0.66 and then x7 between stretches,
with exit code 0. The single synthetic room (recon.synthetic.render) is textured everywhere
and walked slowly, so nothing in the test suite broke that way. This scene has what such a
walk has: a corridor with plain walls, floor and ceiling (uniform albedo, no texture: dense
optical flow has nothing but smooth shading and a few edges to hold on to), a fast turn of
the head (~90 degrees in ~8 frames) rendered with motion blur, and otherwise a normal walk
(about 4.5 cm per frame at 30 fps, ~1.35 m/s) with head bob and shake. Its metadata names
the frame ranges of each stretch and the cuts, the frames where a front end is expected to
break (the start of the textureless stretch, of the turn out of the corridor, which begins
with nothing to track, and of the fast turn), so a benchmark or test can look for a scale
break or a tracking loss there (benchmarks/walkthrough_breaks.py).

This module owns the floor plan (built with recon.synthetic.floorplan), the plain corridor
materials, the lights of every room, the scripted path (:class:`WalkPath`), the stretch
and cut metadata (:func:`walkthrough_plan`) and the rendering with per-frame motion blur
(:func:`render_walkthrough`). The rooms are recon.synthetic.room's room (6 x 5 x 2.7 m),
each furnished from its own seed with its doorways kept free. Plan (metres, y down, floor
y = 0, as in recon.synthetic.room), with corridor length L (default 5):

    room A   x in [-3, 3],        z in [-2.5, 2.5]         (the single room's place)
    corridor x in [-0.65, 0.65],  z in [2.5, 2.5 + L]      (plain; end wall 0.3 m past door B)
    door B   through the corridor's right wall (x = 0.65 .. 0.95), 1 m wide
    room B   x in [0.95, 6.95],   5 m deep, beside the corridor's far end
    door C   through room B's far wall (0.3 m), 1 m wide
    room C   x in [0.95, 6.95],   beyond room B

The walk: room A (looking around) -> corridor (looking along it: the textureless stretch)
-> a normal right turn through door B -> into room B -> the fast left turn -> door C ->
room C, looking around at the end. Everything is deterministic from the seed (furniture,
colours, textures, shake phases).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields

import numpy as np
import open3d as o3d
from scipy.interpolate import PchipInterpolator

from ..errors import ReconInputError
from .camera import camera_rotation, intrinsics_for
from .floorplan import POST_HALF, WALLS, Region, add_shell, find_openings
from .render import Renderer, SyntheticSequence, room_lights
from .room import (
    ROOM_HALF_X,
    ROOM_HALF_Z,
    ROOM_HEIGHT,
    Box,
    Materials,
    MeshBuilder,
    on_room_boundary,
    raycasting_scene,
    scene_layout,
)
from .textures import texture_pyramid

FPS = 30.0
WALK_SPEED = 0.045  # metres per frame of the walk between scripted points: 1.35 m/s at 30 fps
CORRIDOR_WIDTH = 1.3
WALL = 0.3  # thickness of the walls between regions, i.e. the depth of a doorway's passage
DOOR_WIDTH = 1.0
_DOOR_CLEARANCE = 0.2  # furniture and pictures stay this far from a doorway's posts
_EYE_HEIGHT = 1.6  # a head-mounted camera
_PITCH_DOWN = np.deg2rad(12.0)
# A frame is textureless when at most this share of its view falls on textured surfaces
# (counted on a probe image of _PROBE pixels with the same field of view), low in texture
# up to LOW_TEXTURE_SHARE (a sliver of a room through a doorway).
TEXTURELESS_SHARE = 0.005
LOW_TEXTURE_SHARE = 0.05
_PROBE = (64, 48)
_LIGHT_SCALE = 0.7
_CHUNK_PIXELS = 1_250_000  # pixels ray-cast per batch, as in recon.synthetic.render


@dataclass
class WalkthroughScene:
    """The walk-through's geometry and materials.

    regions: the free-space regions (rooms, corridor, doorway passages) of the floor plan.
    vertices (V, 3) float64, triangles (F, 3) int64, triangle_materials (F,) int64: the
    closed mesh (recon.synthetic.room conventions). materials: every material, ids as in
    triangle_materials. plain: (M,) bool, materials of uniform albedo (no texture at all).
    boxes: furniture and jamb posts. lights: positions (L, 3) and powers (L,).
    """

    regions: list[Region]
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_materials: np.ndarray
    materials: Materials
    plain: np.ndarray
    boxes: list[Box]
    lights: tuple[np.ndarray, np.ndarray]

    def bounds(self) -> np.ndarray:
        """(2, 3) float64 min and max corners of the floor plan."""
        lo = np.min([r.lo for r in self.regions], axis=0)
        hi = np.max([r.hi for r in self.regions], axis=0)
        return np.array([[lo[0], -ROOM_HEIGHT, lo[1]], [hi[0], 0.0, hi[1]]])


def plan_bounds(corridor_length: float) -> dict[str, tuple[tuple[float, float], tuple[float, float]]]:
    """Region name -> ((x, z) lo, (x, z) hi) of the floor plan (see the module docstring)."""
    hx, hz, w = ROOM_HALF_X, ROOM_HALF_Z, CORRIDOR_WIDTH / 2
    corridor_end = hz + corridor_length
    door_b = corridor_end - 0.3 - DOOR_WIDTH
    bx, bz = w + WALL, door_b - 1.5  # room B's lo corner: door B is 1.5 m from its corner
    door_c = bx + hx - 0.4 - DOOR_WIDTH / 2  # door C: 0.4 m left of the middle of B's far wall
    far = bz + 2 * hz
    plan = {
        "room_a": ((-hx, -hz), (hx, hz)),
        "corridor": ((-w, hz), (w, corridor_end)),
        "door_b": ((w, door_b), (bx, door_b + DOOR_WIDTH)),
        "room_b": ((bx, bz), (bx + 2 * hx, far)),
        "door_c": ((door_c, far), (door_c + DOOR_WIDTH, far + WALL)),
        "room_c": ((bx, far + WALL), (bx + 2 * hx, far + WALL + 2 * hz)),
    }
    # Rounded so that touching regions share their wall planes exactly.
    return {name: tuple(tuple(round(v, 9) for v in corner) for corner in box) for name, box in plan.items()}


def _plain_materials(rng: np.random.Generator, start: int) -> tuple[Materials, dict[str, int]]:
    """Uniform-albedo materials of the corridor (walls, floor, ceiling) and door frames,
    ids from `start`: colour a = colour b, no luminance noise, no pattern."""
    colours = {
        "wall": rng.uniform(0.55, 0.65) * np.array([1.0, rng.uniform(0.95, 1.0), rng.uniform(0.85, 0.95)]),
        "floor": rng.uniform(0.35, 0.45) * np.array([1.0, rng.uniform(0.9, 1.0), rng.uniform(0.8, 0.9)]),
        "ceiling": np.full(3, rng.uniform(0.68, 0.74)),
        "frame": np.full(3, rng.uniform(0.74, 0.8)),
    }
    colour = np.array(list(colours.values()), dtype=np.float32)
    m = len(colour)
    zeros = np.zeros(m, np.float32)
    materials = Materials(colour, colour.copy(), zeros, zeros, zeros, np.ones(m, np.float32),
                          np.zeros((m, 2), np.float32))
    return materials, {name: start + i for i, name in enumerate(colours)}


def concat_materials(parts: list[Materials]) -> Materials:
    """One Materials table of several, ids following each other in order."""
    return Materials(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Materials)))


def _wall_coordinate(wall: str, local: float) -> float:
    """Distance along room wall `wall` (from its start, as recon.synthetic.room lays out
    furniture) of the room-local x (wall0, wall1) or z (wall2, wall3) `local`."""
    return {"wall0": local + ROOM_HALF_X, "wall1": ROOM_HALF_X - local,
            "wall2": ROOM_HALF_Z - local, "wall3": local + ROOM_HALF_Z}[wall]


def _room_doors(region: Region, centre: tuple[float, float], openings) -> dict[int, list[tuple[float, float]]]:
    """Wall index -> doorway intervals along it (with the posts and clearance) of a room."""
    doors: dict[int, list[tuple[float, float]]] = {}
    for o in openings:
        if region.name not in o.regions:
            continue
        side = int(o.regions[0] == region.name)  # the room is on the low side: the opening is its hi wall
        wall = next(name for name, key in WALLS.items() if key == (o.axis, side))
        other = 1 - o.axis // 2  # the (x, z) index along the wall
        a = sorted(_wall_coordinate(wall, e - centre[other]) for e in o.span)
        pad = POST_HALF + _DOOR_CLEARANCE
        doors.setdefault(int(wall[-1]), []).append((a[0] - pad, a[1] + pad))
    return doors


def _furnish(mesh: MeshBuilder, region: Region, seed: int, openings, start: int):
    """Furnish room `region` from `seed` (recon.synthetic.room's layout, moved to the room's
    place, doorways kept free); material ids from `start`. Returns its Materials, the room
    surfaces' material ids and its boxes."""
    centre = ((region.lo[0] + region.hi[0]) / 2, (region.lo[1] + region.hi[1]) / 2)
    boxes, materials, faces = scene_layout(seed, _room_doors(region, centre, openings))
    shift = np.array([centre[0], 0.0, centre[1]])
    moved = [Box(tuple(np.add(b.lo, shift).tolist()), tuple(np.add(b.hi, shift).tolist()), b.material + start, b.skip)
             for b in boxes]
    mesh.add_boxes(moved, lambda axis, level: on_room_boundary(axis, level, shift))
    return materials, {name: start + m for name, m in faces.items()}, moved


def walkthrough_scene(seed: int = 0, corridor_length: float = 5.0) -> WalkthroughScene:
    """The walk-through's floor plan, furniture, materials and lights, deterministic from seed."""
    bounds = plan_bounds(corridor_length)
    rooms = ("room_a", "room_b", "room_c")
    # Regions first without materials: the openings decide where each room's doors are.
    openings = find_openings([Region(name, lo, hi, {}) for name, (lo, hi) in bounds.items()])
    mesh = MeshBuilder()
    parts, faces, boxes, start = [], {}, [], 0
    for k, name in enumerate(rooms):
        region = Region(name, *bounds[name], {})
        # Each room its own layout seed, distinct across walk-through seeds.
        materials, faces[name], moved = _furnish(mesh, region, seed * 16 + k, openings, start)
        parts.append(materials)
        boxes += moved
        start += len(materials.color_a)
    plain, ids = _plain_materials(np.random.default_rng([seed, 6]), start)
    parts.append(plain)
    corridor_faces = {"floor": ids["floor"], "ceiling": ids["ceiling"], **{w: ids["wall"] for w in WALLS}}
    regions = [Region(name, lo, hi, faces.get(name, corridor_faces)) for name, (lo, hi) in bounds.items()]
    posts = add_shell(mesh, regions, ROOM_HEIGHT, ids["frame"])
    vertices, triangles, triangle_materials = mesh.build()
    materials = concat_materials(parts)
    return WalkthroughScene(regions, vertices, triangles, triangle_materials, materials, _is_plain(materials),
                            posts + boxes, _lights(regions))


def _is_plain(materials: Materials) -> np.ndarray:
    """(M,) whether a material's albedo is uniform: no noise, no pattern, one colour."""
    same = np.all(materials.color_a == materials.color_b, axis=1)
    return same & (materials.luminance == 0) & (materials.checker == 0) & (materials.stripes == 0)


def _lights(regions: list[Region]) -> tuple[np.ndarray, np.ndarray]:
    """The single room's three ceiling lights in every room, and one every 2.5 m along the
    corridor, all at _LIGHT_SCALE of their power: the renderer casts no shadows, so every
    room also gets its neighbours' light, which would otherwise saturate the images."""
    positions, powers = [], []
    for r in regions:
        if r.name.startswith("room"):
            p, w = room_lights(((r.lo[0] + r.hi[0]) / 2, 0.0, (r.lo[1] + r.hi[1]) / 2))
            positions.append(p)
            powers.append(w)
        elif r.name == "corridor":
            count = max(1, int(round((r.hi[1] - r.lo[1]) / 2.5)))
            z = r.lo[1] + (np.arange(count) + 0.5) * (r.hi[1] - r.lo[1]) / count
            positions.append(np.stack([np.full(count, (r.lo[0] + r.hi[0]) / 2), np.full(count, -2.55), z], axis=1))
            powers.append(np.full(count, 0.5))
    return np.concatenate(positions).astype(np.float32), (_LIGHT_SCALE * np.concatenate(powers)).astype(np.float32)


# --------------------------------------------------------------------------- the walk


@dataclass
class WalkPath:
    """The scripted walk: position keys (K, 3) rows (frame, x, z) and yaw keys (J, 2) rows
    (frame, yaw radians), interpolated monotonically between keys (PCHIP: no overshoot, so
    the path stays where its keys are and a turn between two keys happens between their
    frames), plus head bob and shake of seeded phases `phase` (12,)."""

    position_keys: np.ndarray
    yaw_keys: np.ndarray
    phase: np.ndarray

    def poses(self, times) -> np.ndarray:
        """(T, 4, 4) float64 camera-to-world poses at (fractional) frame times (T,)."""
        t = np.asarray(times, dtype=np.float64)
        x = PchipInterpolator(self.position_keys[:, 0], self.position_keys[:, 1])(t)
        z = PchipInterpolator(self.position_keys[:, 0], self.position_keys[:, 2])(t)
        yaw = PchipInterpolator(self.yaw_keys[:, 0], self.yaw_keys[:, 1])(t)
        wave = lambda amplitude, period, k: amplitude * np.sin(2 * np.pi * t / period + self.phase[k])  # noqa: E731
        # Walking: the head bobs once a step (~2 steps/s) and sways once a stride; the hand
        # or head adds a few millimetres and tenths of a degree of slower shake.
        y = -(_EYE_HEIGHT + wave(0.015, 15, 0) + wave(0.004, 23, 1))
        x = x + wave(0.01, 30, 2) + wave(0.003, 31, 3)
        z = z + wave(0.003, 27, 4)
        yaw = yaw + wave(np.deg2rad(0.5), 37, 5) + wave(np.deg2rad(0.3), 13, 6)
        pitch = _PITCH_DOWN + wave(np.deg2rad(1.5), 90, 7) + wave(np.deg2rad(0.4), 15, 8) + wave(np.deg2rad(0.2), 19, 9)
        roll = wave(np.deg2rad(0.8), 30, 10) + wave(np.deg2rad(0.3), 21, 11)
        poses = np.tile(np.eye(4), (len(t), 1, 1))
        for i in range(len(t)):
            poses[i, :3, :3] = camera_rotation(yaw[i], pitch[i], roll[i])
        poses[:, :3, 3] = np.stack([x, y, z], axis=1)
        return poses


def _script(bounds: dict, turn_degrees: float, turn_frames: int) -> tuple[list, dict[str, int]]:
    """Walk keys [(frames from the previous key or None for walking pace, x, z, yaw degrees)]
    and the names of keys that start or end a stretch (key index)."""
    hz, w = ROOM_HALF_Z, CORRIDOR_WIDTH / 2
    door_b = (bounds["door_b"][0][1] + bounds["door_b"][1][1]) / 2  # z of door B's middle
    room_b_x = bounds["room_b"][0][0]
    door_c = (bounds["door_c"][0][0] + bounds["door_c"][1][0]) / 2  # x of door C's middle
    far_b, room_c_z = bounds["room_b"][1][1], bounds["room_c"][0][1]
    end_yaw = 90.0 - turn_degrees
    keys = [
        (None, -1.1, -1.7, -75.0),  # room A, looking at its left wall, then around
        (None, -0.4, -0.5, -40.0),
        (None, 0.35, 0.8, 35.0),
        (None, 0.0, 2.0, 5.0),
        (None, 0.0, hz + 0.5, 0.0),  # in the corridor, looking along it
        (None, -0.05, door_b - 1.0, 0.0),  # the corner: a normal right turn through door B
        (None, 0.2, door_b - 0.3, 45.0),
        (None, w + WALL / 2, door_b, 90.0),
        (None, room_b_x + 1.0, door_b + 0.1, 90.0),
        (None, door_c - 0.45, door_b + 0.3, 90.0),  # the fast turn, shuffling a few centimetres
        (int(turn_frames), door_c - 0.4, door_b + 0.38, end_yaw),
        (None, door_c - 0.15, far_b - 1.0, end_yaw / 2),
        (None, door_c, far_b - 0.2, 0.0),  # through door C
        (None, door_c, room_c_z + 0.7, 0.0),
        (None, door_c + 0.4, room_c_z + 1.9, -30.0),
        (30, door_c + 0.5, room_c_z + 2.1, -75.0),  # room C: stop and look around
    ]
    return keys, {"corner": 5, "corner_end": 7, "turn": 9, "turn_end": 10}


def _key_frames(keys: list) -> np.ndarray:
    """(K,) frame of each key: walking pace (WALK_SPEED) from the previous one unless given."""
    frames = [0]
    for (count, x, z, _), (_, x0, z0, _) in zip(keys[1:], keys[:-1]):
        step = count if count is not None else max(1, int(round(np.hypot(x - x0, z - z0) / WALK_SPEED)))
        frames.append(frames[-1] + step)
    return np.array(frames)


@dataclass
class WalkthroughPlan:
    """Everything about the walk-through except its images.

    scene: the WalkthroughScene. path: the WalkPath. poses: (F, 4, 4) camera-to-world of
    every frame of the walk. blur: (F,) int64 sub-frames averaged per frame (1: sharp).
    stretches: name -> (first, stop) frame range, stop exclusive: "room_a", "corridor",
    "door_b", "room_b", "door_c", "room_c" (frames whose camera centre is in that region),
    "textureless" (the longest run of frames that see at most TEXTURELESS_SHARE of textured
    surface), "low_texture" (the run of frames seeing at most LOW_TEXTURE_SHARE that holds
    it), "corner" (the normal-speed right turn into door B, which starts in the plain
    corridor and ends in room B), "fast_turn" (the yaw changes by -turn_degrees from frame
    first to frame stop - 1), "blur" (the frames rendered with motion blur).
    cuts: the frames where a front end is expected to break, sorted: the start of the
    textureless stretch, of the corner (a turn out of a view with nothing to track) and of
    the fast turn. textured_share: (F,) share of each frame's view on textured surfaces.
    settings: the arguments.
    """

    scene: WalkthroughScene
    path: WalkPath
    poses: np.ndarray
    blur: np.ndarray
    stretches: dict[str, tuple[int, int]]
    cuts: list[int]
    textured_share: np.ndarray
    settings: dict

    @property
    def num_frames(self) -> int:
        return len(self.poses)


def textured_share(scene: WalkthroughScene, poses: np.ndarray, probe: tuple[int, int] = _PROBE) -> np.ndarray:
    """(N,) share of each view (poses (N, 4, 4), the synthetic camera's field of view) that
    falls on textured (not plain) surfaces, ray-cast on a `probe` (width, height) grid."""
    fx, fy, cx, cy = intrinsics_for(*probe)
    v, u = np.mgrid[0 : probe[1], 0 : probe[0]].astype(np.float64)
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
    dirs = np.einsum("nij,pj->npi", poses[:, :3, :3], rays)
    origins = np.broadcast_to(poses[:, None, :3, 3], dirs.shape)
    hit = raycasting_scene(scene.vertices, scene.triangles).cast_rays(
        o3d.core.Tensor(np.concatenate([origins, dirs], axis=-1).reshape(-1, 6).astype(np.float32)))
    prim = hit["primitive_ids"].numpy().reshape(len(poses), -1).astype(np.int64)
    return (~scene.plain[scene.triangle_materials[prim]]).mean(axis=1)


def _runs(mask: np.ndarray) -> np.ndarray:
    """(R, 2) first and stop of each run of True in mask (N,)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[False], mask, [False]]).astype(np.int8)))
    return edges.reshape(-1, 2)


def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    """(first, stop) of the longest run of True in mask (N,); (0, 0) if none."""
    runs = _runs(mask)
    if len(runs) == 0:
        return 0, 0
    first, stop = runs[np.argmax(runs[:, 1] - runs[:, 0])]
    return int(first), int(stop)


def _run_holding(mask: np.ndarray, frame: int) -> tuple[int, int]:
    """(first, stop) of the run of True in mask (N,) that holds `frame`."""
    runs = _runs(mask)
    k = np.flatnonzero((runs[:, 0] <= frame) & (runs[:, 1] > frame))
    return (int(runs[k[0], 0]), int(runs[k[0], 1])) if len(k) else (frame, frame)


def _region_stretches(regions: list[Region], poses: np.ndarray) -> dict[str, tuple[int, int]]:
    """Region name -> (first, stop) frames whose camera centre is inside it."""
    out = {}
    for r in regions:
        inside = np.flatnonzero(r.contains(poses[:, 0, 3], poses[:, 2, 3]))
        if len(inside):
            out[r.name] = (int(inside[0]), int(inside[-1]) + 1)
    return out


def walkthrough_plan(seed: int = 0, *, corridor_length: float = 5.0, turn_degrees: float = 90.0,
                     turn_frames: int = 8, turn_blur: int = 8, exposure: float = 0.5) -> WalkthroughPlan:
    """The walk-through's scene, poses and stretches without rendering (see render_walkthrough)."""
    if not 3.5 <= corridor_length <= 20.0:
        raise ReconInputError(f"walk-through: corridor_length must be in [3.5, 20] m, got {corridor_length}")
    if int(turn_frames) < 1 or int(turn_blur) < 1 or not 0.0 <= exposure <= 1.0 or not 0 < turn_degrees <= 180:
        raise ReconInputError(f"walk-through: need turn_frames >= 1, turn_blur >= 1, 0 <= exposure <= 1 and "
                              f"0 < turn_degrees <= 180, got {turn_frames}, {turn_blur}, {exposure}, {turn_degrees}")
    scene = walkthrough_scene(seed, corridor_length)
    keys, marks = _script(plan_bounds(corridor_length), turn_degrees, turn_frames)
    frames = _key_frames(keys)
    table = np.array([(f, x, z, np.deg2rad(yaw)) for f, (_, x, z, yaw) in zip(frames, keys)])
    path = WalkPath(table[:, :3], table[:, [0, 3]], np.random.default_rng([seed, 5]).uniform(0, 2 * np.pi, 12))
    poses = path.poses(np.arange(frames[-1] + 1))
    turn = (int(frames[marks["turn"]]), int(frames[marks["turn_end"]]) + 1)
    blur = np.ones(len(poses), dtype=np.int64)
    blur[turn[0] : turn[1]] = int(turn_blur)
    share = textured_share(scene, poses)
    stretches = _region_stretches(scene.regions, poses)
    stretches["textureless"] = _longest_run(share <= TEXTURELESS_SHARE)
    stretches["low_texture"] = _run_holding(share <= LOW_TEXTURE_SHARE, stretches["textureless"][0])
    stretches["corner"] = (int(frames[marks["corner"]]), int(frames[marks["corner_end"]]) + 1)
    stretches["fast_turn"] = turn
    stretches["blur"] = turn if turn_blur > 1 else (turn[0], turn[0])
    settings = {"corridor_length": corridor_length, "turn_degrees": turn_degrees, "turn_frames": int(turn_frames),
                "turn_blur": int(turn_blur), "exposure": exposure, "walk_speed": WALK_SPEED, "fps": FPS}
    cuts = sorted([stretches["textureless"][0], stretches["corner"][0], turn[0]])
    return WalkthroughPlan(scene, path, poses, blur, stretches, cuts, share, settings)


# --------------------------------------------------------------------------- rendering


@dataclass
class Walkthrough(SyntheticSequence):
    """A rendered walk-through: a SyntheticSequence (rgb, depth, poses, intrinsics, mesh,
    boxes: furniture and jamb posts, room_bounds: the floor plan's (2, 3) corners) of the
    frames `frame_ids` of the walk, with the walk's metadata.

    frame_ids: (N,) int64 frame of the walk of each rendered frame (all: 0 .. F-1).
    stretches, cuts, textured_share (F,), settings: as in WalkthroughPlan, in frames of the
    walk (the same as sequence indices when every frame is rendered). blur: (N,) int64
    sub-frames averaged into each rendered frame. regions: region name -> (2, 3) float64
    min and max corners. fps: frames per second of the walk.
    """

    frame_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    stretches: dict = field(default_factory=dict)
    cuts: list = field(default_factory=list)
    textured_share: np.ndarray = field(default_factory=lambda: np.zeros(0))
    blur: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    regions: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)
    fps: float = FPS


def _batches(ids: np.ndarray, blur: np.ndarray, pixels: int) -> list[np.ndarray]:
    """Positions into ids (N,) in batches of frames with the same blur, each about
    _CHUNK_PIXELS ray-cast pixels."""
    batches = []
    runs = np.flatnonzero(np.diff(blur[ids])) + 1
    for run in np.split(np.arange(len(ids)), runs):
        size = max(1, _CHUNK_PIXELS // (pixels * int(blur[ids[run[0]]])))
        batches += [run[k : k + size] for k in range(0, len(run), size)]
    return batches


def _render_frames(renderer: Renderer, plan: WalkthroughPlan, ids: np.ndarray, exposure: float, shape, threads: int):
    """rgb (N, H, W, 3) uint8 and depth (N, H, W) float32 of walk frames ids (N,); a frame
    with blur b averages b sub-frames spread over `exposure` of the frame interval around
    its time (pose and depth are those of its time), as recon.synthetic.render does."""
    height, width = shape
    rgb = np.empty((len(ids), height, width, 3), dtype=np.uint8)
    depth = np.empty((len(ids), height, width), dtype=np.float32)

    def work(batch: np.ndarray) -> None:
        frames = ids[batch]
        b = int(plan.blur[frames[0]])
        colour, depth[batch] = renderer.render(plan.poses[frames])
        if b == 1:
            rgb[batch] = colour
            return
        offsets = ((np.arange(b) + 0.5) / b - 0.5) * exposure
        sub, _ = renderer.render(plan.path.poses((frames[:, None] + offsets).reshape(-1)))
        rgb[batch] = sub.reshape(len(frames), b, height, width, 3).mean(1).round().astype(np.uint8)

    batches = _batches(ids, plan.blur, width * height)
    # Batches are independent (numpy, OpenCV and Open3D release the GIL): output does not
    # depend on the thread count.
    with ThreadPoolExecutor(max_workers=max(1, min(int(threads), len(batches)))) as pool:
        list(pool.map(work, batches))
    return rgb, depth


def render_walkthrough(width: int = 320, height: int = 240, seed: int = 0, frames=None, threads: int = 2, *,
                       corridor_length: float = 5.0, turn_degrees: float = 90.0, turn_frames: int = 8,
                       turn_blur: int = 8, exposure: float = 0.5) -> Walkthrough:
    """Render the walk-through (see the module docstring): ~400 frames at 30 fps.

    Args:
        width, height: image size in pixels (>= 8); fx = fy = 525 * width / 640, centred
            principal point (recon.synthetic.camera.intrinsics_for).
        seed: furniture, colours, textures and shake phases; the same seed gives
            bit-identical output.
        frames: walk frames to render (indices, a slice or None for all); metadata stays in
            frames of the walk (Walkthrough.frame_ids maps).
        threads: batches rendered concurrently.
        corridor_length: metres (>= 3.5): longer makes the textureless stretch longer.
        turn_degrees, turn_frames: the fast turn (yaw, to the left) and the frames it takes.
        turn_blur, exposure: sub-frames averaged per frame of the fast turn, spread over
            `exposure` of the frame interval (motion blur; other frames are sharp).

    Returns:
        a Walkthrough: rgb (N, H, W, 3) uint8, depth (N, H, W) float32 z-depth > 0, poses
        (N, 4, 4) camera-to-world, intrinsics, the ground-truth mesh, stretches and cuts.
    """
    if int(width) < 8 or int(height) < 8:
        raise ReconInputError(f"walk-through: image size must be at least 8x8, got {width}x{height}")
    width, height = int(width), int(height)
    plan = walkthrough_plan(seed, corridor_length=corridor_length, turn_degrees=turn_degrees,
                            turn_frames=turn_frames, turn_blur=turn_blur, exposure=exposure)
    ids = np.arange(plan.num_frames)[frames if frames is not None else slice(None)]
    ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
    if len(ids) == 0:
        raise ReconInputError(f"walk-through: no frames selected of {plan.num_frames}")
    scene = plan.scene
    intrinsics = intrinsics_for(width, height)
    renderer = Renderer(scene.vertices, scene.triangles, scene.triangle_materials, scene.materials,
                        texture_pyramid(seed), intrinsics, width, height, lights=scene.lights)
    rgb, depth = _render_frames(renderer, plan, ids, exposure, (height, width), threads)
    colors = np.zeros_like(scene.vertices)
    colors[scene.triangles.reshape(-1)] = np.repeat(scene.materials.color_a[scene.triangle_materials], 3, axis=0)
    regions = {r.name: np.array([[r.lo[0], -ROOM_HEIGHT, r.lo[1]], [r.hi[0], 0.0, r.hi[1]]]) for r in scene.regions}
    return Walkthrough(
        rgb=rgb, depth=depth, poses=plan.poses[ids], intrinsics=intrinsics, mesh_vertices=scene.vertices,
        mesh_triangles=scene.triangles, mesh_colors=colors, triangle_materials=scene.triangle_materials,
        boxes=np.array([[b.lo, b.hi] for b in scene.boxes], dtype=np.float64).reshape(-1, 2, 3), seed=int(seed),
        room_bounds=scene.bounds(), frame_ids=ids, stretches=dict(plan.stretches), cuts=list(plan.cuts),
        textured_share=plan.textured_share, blur=plan.blur[ids], regions=regions, settings=dict(plan.settings),
    )
