"""The synthetic walk-through's scene (recon.synthetic.walkthrough): the floor plan of three
furnished rooms and a corridor (built with recon.synthetic.floorplan), the plain corridor
materials (uniform albedo) and the lights of every room.

The rooms are recon.synthetic.room's (6 x 5 x 2.7 m), each furnished from its own seed with
its doorways kept free; the plan (metres, y down, floor y = 0, corridor length L, default 5)
is room A, the corridor, door B, room B, door C, room C. Everything is deterministic from
the seed. More: docs/running.md#the-synthetic-scenes
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .floorplan import POST_HALF, WALLS, Region, add_shell, find_openings
from .render import room_lights
from .room import (
    ROOM_HALF_X,
    ROOM_HALF_Z,
    ROOM_HEIGHT,
    Box,
    Materials,
    MeshBuilder,
    on_room_boundary,
    scene_layout,
)

CORRIDOR_WIDTH = 1.3
WALL = 0.3  # thickness of the walls between regions, i.e. the depth of a doorway's passage
DOOR_WIDTH = 1.0
_DOOR_CLEARANCE = 0.2  # furniture and pictures stay this far from a doorway's posts
_LIGHT_SCALE = 0.7


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
