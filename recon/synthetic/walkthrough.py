"""The synthetic walk-through: three furnished rooms and a corridor, walked through hand-held,
with a textureless stretch and a fast blurred turn at known frames: the test scene for
trajectories whose scale breaks between stretches.

This module owns the scripted path (:class:`WalkPath`), the metadata naming each stretch's
frames and the cuts where a front end is expected to break (:func:`walkthrough_plan`) and the
rendering with per-frame motion blur (:func:`render_walkthrough`); the floor plan, materials
and lights are recon.synthetic.walkthrough_scene's. Everything is deterministic from the seed.
More: docs/running.md#the-synthetic-scenes
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.interpolate import PchipInterpolator

from ..errors import ReconInputError
from .camera import camera_rotation, intrinsics_for
from .floorplan import Region
from .render import Renderer, SyntheticSequence
from .room import (
    ROOM_HALF_Z,
    ROOM_HEIGHT,
    raycasting_scene,
)
from .textures import texture_pyramid
from .walkthrough_scene import CORRIDOR_WIDTH, WALL, WalkthroughScene, plan_bounds, walkthrough_scene

FPS = 30.0
WALK_SPEED = 0.045  # metres per frame of the walk between scripted points: 1.35 m/s at 30 fps
_EYE_HEIGHT = 1.6  # a head-mounted camera
_PITCH_DOWN = np.deg2rad(12.0)
# A frame is textureless when at most this share of its view falls on textured surfaces
# (counted on a probe image of _PROBE pixels with the same field of view), low in texture
# up to LOW_TEXTURE_SHARE (a sliver of a room through a doorway).
TEXTURELESS_SHARE = 0.005
LOW_TEXTURE_SHARE = 0.05
_PROBE = (64, 48)
_CHUNK_PIXELS = 1_250_000  # pixels ray-cast per batch, as in recon.synthetic.render


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
