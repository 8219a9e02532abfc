"""The synthetic room: its walls, furniture and materials, and their triangle mesh.

This module owns the room's layout, the per-material albedo parameters drawn for it, and the
mesh and ray-casting scene made of it, deterministic from the seed; the walk-through
furnishes several such rooms with the same MeshBuilder. World frame: metres, **y points
down** (gravity), so a level camera looking along +z has the identity rotation in OpenCV
axes; x in [-3, 3], z in [-2.5, 2.5], floor y = 0, ceiling y = -2.7; axis-aligned boxes.
More: docs/running.md#the-synthetic-scenes
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .textures import TEXTURE_PERIOD

ROOM_HALF_X = 3.0
ROOM_HALF_Z = 2.5
ROOM_HEIGHT = 2.7
# Room faces reach past the corners so no ray can slip through a seam between walls.
_ROOM_OVERLAP = 0.05


@dataclass(frozen=True)
class Box:
    """Axis-aligned box ``lo`` (3,) to ``hi`` (3,) with a material index.

    ``skip`` names faces left out of the mesh because they are hidden (e.g. a leg's top
    under a table top) as (axis, side) pairs, side 0 = the ``lo`` face, 1 = ``hi``.
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    material: int
    skip: frozenset = frozenset()


@dataclass(frozen=True)
class Materials:
    """Per-material albedo parameters, all arrays indexed by material id (M, ...).

    ``color_a``/``color_b`` (M, 3) are mixed by a coarse noise channel, ``luminance`` (M,)
    is the strength of the fine multiplicative noise, ``checker``/``stripes`` (M,) the
    strength of those patterns, ``scale`` (M,) stretches the texture (>1: finer features)
    and ``offset`` (M, 2) shifts it so that objects do not share texture.
    """

    color_a: np.ndarray
    color_b: np.ndarray
    luminance: np.ndarray
    checker: np.ndarray
    stripes: np.ndarray
    scale: np.ndarray
    offset: np.ndarray

    def table(self) -> np.ndarray:
        """(M, 12) float32 rows: color_a (3), color_b (3), luminance, checker, stripes, scale, offset (2).

        One row gather per pixel is much cheaper than a gather per parameter.
        """
        columns = [self.color_a, self.color_b, self.luminance[:, None], self.checker[:, None], self.stripes[:, None],
                   self.scale[:, None], self.offset]
        return np.concatenate(columns, axis=1).astype(np.float32)


# --------------------------------------------------------------------------- scene layout


def _random_color(rng: np.random.Generator, hue: tuple, sat: tuple, val: tuple) -> np.ndarray:
    """(3,) RGB in [0, 1] drawn uniformly in an HSV box (hue wraps)."""
    h = rng.uniform(*hue) % 1.0
    return np.array(colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val)))


# HSV ranges of colour families: (hue, saturation, value), then the range of the
# brightness of the second (blotch) colour relative to the first.
_PALETTES = {
    "wall": ((0.0, 1.0), (0.05, 0.25), (0.65, 0.85), (0.6, 0.8)),
    "floor": ((0.05, 0.11), (0.35, 0.6), (0.35, 0.6), (0.45, 0.7)),
    "ceiling": ((0.0, 1.0), (0.0, 0.08), (0.75, 0.88), (0.65, 0.8)),
    "wood": ((0.05, 0.12), (0.4, 0.75), (0.3, 0.65), (0.45, 0.7)),
    "paint": ((0.0, 1.0), (0.25, 0.65), (0.45, 0.85), (0.5, 0.8)),
    "fabric": ((0.0, 1.0), (0.45, 0.85), (0.3, 0.7), (0.45, 0.75)),
}


class _MaterialBook:
    """Collects material parameters as the layout is built (material id = insertion order)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.rows: list[tuple] = []

    def add(self, family: str, checker: float = 0.0, stripes: float = 0.0) -> int:
        rng = self.rng
        hue, sat, val, darker = _PALETTES[family]
        a = _random_color(rng, hue, sat, val)
        # The second colour is a darker, slightly shifted variant: the coarse noise mixing
        # the two reads as blotches/grain.
        b = np.clip(a * rng.uniform(*darker) + rng.uniform(-0.04, 0.04, 3), 0.02, 1.0)
        luminance = rng.uniform(0.3, 0.45)
        scale = rng.uniform(0.8, 1.25)
        offset = rng.uniform(0.0, TEXTURE_PERIOD, 2)
        self.rows.append((a, b, luminance, checker, stripes, scale, offset))
        return len(self.rows) - 1

    def build(self) -> Materials:
        cols = list(zip(*self.rows))
        return Materials(*(np.array(c, dtype=np.float32) for c in cols))


# Furniture is built in a wall-local frame: a along the wall, b out of the wall, h up
# (metres above the floor), boxes as (a0, b0, h0, a1, b1, h1, part name).
def _table(rng):
    w, d, h = rng.uniform(1.1, 1.4), rng.uniform(0.65, 0.8), rng.uniform(0.72, 0.76)
    top, leg, inset = 0.04, 0.05, 0.04
    boxes = [(0, 0.02, h - top, w, d, h, "top")]
    for a in (inset, w - inset - leg):
        for b in (0.02 + inset, d - inset - leg):
            boxes.append((a, b, 0, a + leg, b + leg, h - top, "leg"))
    # A few objects standing on the table.
    a = rng.uniform(0.1, 0.3)
    for _ in range(2):
        ow, od, oh = rng.uniform(0.15, 0.35), rng.uniform(0.12, 0.3), rng.uniform(0.08, 0.3)
        if a + ow > w - 0.05:
            break
        boxes.append((a, 0.1, h, a + ow, 0.1 + od, h + oh, "object"))
        a += ow + rng.uniform(0.1, 0.3)
    return w, d, boxes


def _cabinet(rng):
    w, d, h = rng.uniform(0.8, 1.0), rng.uniform(0.45, 0.55), rng.uniform(0.85, 1.1)
    boxes = [(0, 0, 0.08, w, d, h, "body"), (0.03, 0.03, 0, w - 0.03, d - 0.03, 0.08, "plinth")]
    ow, od, oh = rng.uniform(0.35, 0.55), rng.uniform(0.25, 0.35), rng.uniform(0.25, 0.4)
    a = rng.uniform(0.05, w - ow - 0.05)
    boxes.append((a, 0.05, h, a + ow, 0.05 + od, h + oh, "object"))
    return w, d, boxes


def _shelf(rng):
    w, d, h = rng.uniform(0.8, 1.0), 0.35, rng.uniform(1.8, 2.0)
    t = 0.025
    boxes = [(0, 0, 0, t, d, h, "frame"), (w - t, 0, 0, w, d, h, "frame"), (t, 0, 0, w - t, 0.012, h, "back")]
    levels = np.linspace(0.05, h - t, 5)
    for y in levels:
        boxes.append((t, 0.012, y, w - t, d, y + t, "board"))
    # Books/boxes on the lower shelves.
    for y0, y1 in zip(levels[:-1], levels[1:]):
        a = t + rng.uniform(0.0, 0.1)
        while True:
            bw, bh = rng.uniform(0.05, 0.25), rng.uniform(0.5, 0.85) * (y1 - y0 - t)
            if a + bw > w - t - 0.02:
                break
            boxes.append((a, 0.03, y0 + t, a + bw, rng.uniform(0.2, 0.3), y0 + t + bh, "book"))
            a += bw + rng.uniform(0.01, 0.15)
    return w, d, boxes


def _sofa(rng):
    w, d = rng.uniform(1.6, 2.0), rng.uniform(0.75, 0.85)
    arm = 0.18
    boxes = [
        (arm, 0.2, 0, w - arm, d, 0.42, "seat"),
        (0, 0, 0, w, 0.2, 0.85, "back"),
        (0, 0.2, 0, arm, d, 0.6, "arm"),
        (w - arm, 0.2, 0, w, d, 0.6, "arm"),
    ]
    for a in (arm + 0.05, w - arm - 0.45):
        boxes.append((a, 0.2, 0.42, a + 0.4, 0.34, 0.78, "cushion"))
    return w, d, boxes


def _wardrobe(rng):
    w, d, h = rng.uniform(0.9, 1.2), rng.uniform(0.55, 0.62), rng.uniform(1.9, 2.1)
    return w, d, [(0, 0, 0, w, d, h, "body"), (0.1, d, h * 0.45, w - 0.1, d + 0.02, h * 0.47, "handle")]


def _crates(rng):
    w, d, h = rng.uniform(0.45, 0.6), rng.uniform(0.35, 0.45), rng.uniform(0.3, 0.4)
    ow, od, oh = w * rng.uniform(0.6, 0.85), d * rng.uniform(0.6, 0.9), rng.uniform(0.25, 0.35)
    return w, d, [(0, 0, 0, w, d, h, "crate"), (0.03, 0.03, h, 0.03 + ow, 0.03 + od, h + oh, "crate2")]


_INDIVIDUAL_PARTS = {"book", "object", "picture"}
_FURNITURE = {
    "table": _table, "cabinet": _cabinet, "shelf": _shelf, "sofa": _sofa, "wardrobe": _wardrobe, "crates": _crates,
}
# Material family and patterns of each part.
_PART_STYLE = {
    "top": ("wood", 0.0, 0.35), "leg": ("wood", 0.0, 0.0), "object": ("paint", 0.0, 0.0),
    "body": ("paint", 0.0, 0.0), "plinth": ("wood", 0.0, 0.0), "frame": ("wood", 0.0, 0.4),
    "back": ("paint", 0.0, 0.0), "board": ("wood", 0.0, 0.4), "book": ("fabric", 0.0, 0.0),
    "seat": ("fabric", 0.0, 0.0), "arm": ("fabric", 0.0, 0.0), "cushion": ("fabric", 0.3, 0.0),
    "handle": ("paint", 0.0, 0.0), "crate": ("wood", 0.0, 0.45), "crate2": ("paint", 0.35, 0.0),
    "picture": ("paint", 0.25, 0.0),
}


def _wall_frames():
    """For each wall: (origin (x, z) of a = b = 0, unit along-wall (x, z), unit into-room (x, z), length)."""
    hx, hz = ROOM_HALF_X, ROOM_HALF_Z
    return [
        ((-hx, hz), (1.0, 0.0), (0.0, -1.0), 2 * hx),
        ((hx, -hz), (-1.0, 0.0), (0.0, 1.0), 2 * hx),
        ((hx, hz), (0.0, -1.0), (-1.0, 0.0), 2 * hz),
        ((-hx, -hz), (0.0, 1.0), (1.0, 0.0), 2 * hz),
    ]


def _to_world(local, wall, start: float):
    """Wall-local box (a0, b0, h0, a1, b1, h1) placed at `start` along `wall` -> world lo, hi (3,)."""
    (ox, oz), (ax, az), (bx, bz), _ = wall
    a0, b0, h0, a1, b1, h1 = local
    corners = []
    for a in (start + a0, start + a1):
        for b in (b0, b1):
            corners.append((ox + a * ax + b * bx, oz + a * az + b * bz))
    corners = np.array(corners)
    lo = (corners[:, 0].min(), -h1, corners[:, 1].min())
    hi = (corners[:, 0].max(), -h0, corners[:, 1].max())
    return tuple(float(x) for x in lo), tuple(float(x) for x in hi)


def _hidden_faces(part: str) -> frozenset:
    """Faces of a part that touch what it stands on or carries, left out of the mesh:
    (1, 0) is a box's top (y = lo), (1, 1) its bottom (y = hi, world y points down)."""
    if part == "leg":
        return frozenset({(1, 0)})
    if part == "leg_on_rug":
        return frozenset({(1, 0), (1, 1)})
    if part in ("object", "book", "crate2", "cushion"):
        return frozenset({(1, 1)})
    return frozenset()


def _add_piece(boxes: list[Box], book: _MaterialBook, parts, wall, start: float) -> None:
    """Append the boxes of one piece of furniture (wall-local parts) placed at `start` along `wall`."""
    materials: dict[str, int] = {}
    for part in parts:
        name = part[6]
        # Parts of one piece share a material, small loose items get their own.
        if name not in materials or name in _INDIVIDUAL_PARTS:
            family, checker, stripes = _PART_STYLE[name]
            materials[name] = book.add(family, checker, stripes)
        lo, hi = _to_world(part[:6], wall, start)
        boxes.append(Box(lo, hi, materials[name], _hidden_faces(name)))


def _pictures(rng, length: float, blocked: list[tuple[float, float]]):
    """Wall-local boxes of 1-3 framed pictures/boards hung at 1.15-2.4 m along a wall of
    `length`, avoiding the intervals `blocked` by tall furniture."""
    parts = []
    for _ in range(int(rng.integers(1, 4))):
        w, h = rng.uniform(0.35, 1.1), rng.uniform(0.3, 0.8)
        for _ in range(10):  # a few tries for a free spot
            a = rng.uniform(0.3, length - 0.3 - w)
            if all(a + w + 0.1 < b0 or a > b1 + 0.1 for b0, b1 in blocked):
                h0 = rng.uniform(1.15, 2.4 - h)
                parts.append((a, 0, h0, a + w, rng.uniform(0.02, 0.04), h0 + h, "picture"))
                blocked.append((a, a + w))
                break
    return parts


def _fit(cursor: float, width: float, length: float, doors: list[tuple[float, float]]) -> float | None:
    """Where along a wall of `length` a piece `width` wide goes at or after `cursor`: moved
    past any door interval it would overlap; None if it no longer fits. The last 0.9 m of
    each wall is the next wall's corner (its furniture is <= 0.87 m deep)."""
    start = cursor
    for a0, a1 in sorted(doors):
        if start < a1 and start + width > a0:
            start = a1
    return start if start + width <= length - 0.9 else None


def _middle_pieces(rng):
    """World boxes (lo, hi, part) of a rug and a low coffee table in the middle of the room;
    the camera walks above them."""
    pieces = []
    rx, rz = rng.uniform(1.2, 1.8), rng.uniform(0.8, 1.2)
    cx, cz = rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3)
    pieces.append(((cx - rx, -0.01, cz - rz), (cx + rx, 0.0, cz + rz), "rug"))
    w, d, h = rng.uniform(0.8, 1.1), rng.uniform(0.5, 0.65), rng.uniform(0.38, 0.45)
    x0, z0 = cx + rng.uniform(-0.3, 0.3) - w / 2, cz + rng.uniform(-0.2, 0.2) - d / 2
    pieces.append(((x0, -h, z0), (x0 + w, -(h - 0.04), z0 + d), "top"))
    for lx in (x0 + 0.03, x0 + w - 0.08):
        for lz in (z0 + 0.03, z0 + d - 0.08):
            pieces.append(((lx, -(h - 0.04), lz), (lx + 0.05, -0.01, lz + 0.05), "leg"))
    return pieces


def scene_layout(seed: int, doors: dict[int, list[tuple[float, float]]] | None = None,
                 ) -> tuple[list[Box], Materials, dict[str, int]]:
    """Furniture boxes, materials and the room surfaces' material ids, deterministic from seed.

    Furniture stands against the walls (at most 0.87 m deep, so the middle of the room,
    |x| < 2.1 m and |z| < 1.6 m, is free for the camera), pictures hang on the walls, and
    a rug with a low (< 0.45 m) coffee table lies in the middle.

    doors: wall index (0-3, as in the mesh: wall0 at z = +ROOM_HALF_Z, wall1 at -Z, wall2
    at x = +ROOM_HALF_X, wall3 at -X) -> intervals (a0, a1) along that wall (metres from
    its start, see _wall_frames) kept free of furniture and pictures, for doorways (used by
    recon.synthetic.walkthrough). A piece that would overlap one is moved past it; without
    doors the layout is exactly the single room's.
    """
    rng = np.random.default_rng([seed, 1])
    book = _MaterialBook(rng)
    striped_wall = int(rng.integers(4))
    room = {"floor": book.add("floor", checker=0.7)}
    room["ceiling"] = book.add("ceiling")
    for k in range(4):
        room[f"wall{k}"] = book.add("wall", stripes=0.4 if k == striped_wall else 0.0)

    kinds = ["table", "cabinet", "shelf", "sofa", "wardrobe", "crates", "cabinet", "crates", "shelf"]
    kinds = [kinds[i] for i in rng.permutation(len(kinds))]
    walls = _wall_frames()
    cursor = [rng.uniform(0.05, 0.5) for _ in walls]
    tall: list[list[tuple[float, float]]] = [[] for _ in walls]
    boxes: list[Box] = []
    doors = doors or {}
    for i, kind in enumerate(kinds):
        w, _, parts = _FURNITURE[kind](rng)
        # Try walls in a seed-dependent order; an item that fits nowhere is dropped.
        for k in (i + rng.permutation(4)) % 4:
            start = _fit(cursor[k], w, walls[k][3], doors.get(k, []))
            if start is not None:
                _add_piece(boxes, book, parts, walls[k], start)
                if max(part[5] for part in parts) > 1.1:
                    tall[k].append((start, start + w))
                cursor[k] = start + (w + rng.uniform(0.1, 0.6))  # summed as before: bit-identical layouts
                break
    for k, wall in enumerate(walls):
        _add_piece(boxes, book, _pictures(rng, wall[3], tall[k] + list(doors.get(k, []))), wall, 0.0)
    middle = _middle_pieces(rng)
    rug = book.add("fabric", checker=0.0, stripes=0.5)
    table = book.add("wood", stripes=0.3)
    for lo, hi, part in middle:
        boxes.append(Box(lo, hi, rug if part == "rug" else table,
                         _hidden_faces("leg_on_rug" if part == "leg" else part)))
    return boxes, book.build(), room


# --------------------------------------------------------------------------- geometry


def _quad(axis: int, level: float, lo2, hi2, outward: float):
    """Four corners (4, 3) of an axis-aligned rectangle and its two triangles, wound so
    their normal is ``outward`` (+1/-1) along ``axis``."""
    u, v = [a for a in range(3) if a != axis]
    corners = np.zeros((4, 3))
    corners[:, axis] = level
    corners[:, u] = [lo2[0], hi2[0], hi2[0], lo2[0]]
    corners[:, v] = [lo2[1], lo2[1], hi2[1], hi2[1]]
    tris = np.array([[0, 1, 2], [0, 2, 3]])
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    if normal[axis] * outward < 0:
        tris = tris[:, ::-1]
    return corners, tris


def on_room_boundary(axis: int, level: float, centre=(0.0, 0.0, 0.0)) -> bool:
    """Whether the plane at `level` along `axis` is a wall, the floor or the ceiling of the
    room whose floor centre is `centre` (3,) (the origin for the single room)."""
    bounds = {0: (-ROOM_HALF_X, ROOM_HALF_X), 1: (-ROOM_HEIGHT, 0.0), 2: (-ROOM_HALF_Z, ROOM_HALF_Z)}[axis]
    level = level - centre[axis]
    return min(abs(level - bounds[0]), abs(level - bounds[1])) < 1e-9


class MeshBuilder:
    """Collects axis-aligned quads and boxes into one triangle soup with per-triangle materials."""

    def __init__(self):
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.mats: list[np.ndarray] = []
        self.count = 0

    def add(self, corners: np.ndarray, tris: np.ndarray, material: int) -> None:
        """Corners (k, 3), triangles (t, 3) indexing them, one material id."""
        self.tris.append(tris + self.count)
        self.verts.append(corners)
        self.mats.append(np.full(len(tris), material))
        self.count += len(corners)

    def add_quad(self, axis: int, level: float, lo2, hi2, outward: float, material: int) -> None:
        """A rectangle normal to `axis` at `level` spanning lo2..hi2 (2,) in the other two
        axes (in increasing order), visible side `outward` (+1/-1) along `axis`."""
        self.add(*_quad(axis, level, lo2, hi2, outward), material)

    def add_boxes(self, boxes: list[Box], hidden=lambda axis, level: False) -> None:
        """Outward faces of closed boxes, less each box's ``skip`` faces and those for which
        ``hidden(axis, level)`` is true (faces flush with a wall, floor or ceiling)."""
        for box in boxes:
            lo, hi = np.array(box.lo), np.array(box.hi)
            for axis in range(3):
                u, v = [a for a in range(3) if a != axis]
                for side, level in enumerate((lo[axis], hi[axis])):
                    if (axis, side) in box.skip or hidden(axis, level):
                        continue
                    self.add_quad(axis, level, (lo[u], lo[v]), (hi[u], hi[v]), 1.0 if side else -1.0, box.material)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vertices (V, 3) float64, triangles (F, 3) int64, per-triangle material ids (F,) int64."""
        return (np.concatenate(self.verts), np.concatenate(self.tris).astype(np.int64),
                np.concatenate(self.mats).astype(np.int64))


def scene_mesh(boxes: list[Box], room: dict[str, int]):
    """Triangle soup of the room (inward faces) and boxes (outward faces).

    Box faces lying on the floor or a wall are hidden and left out. Returns vertices
    (V, 3) float64, triangles (F, 3) int64 and per-triangle material ids (F,) int64.
    """
    mesh = MeshBuilder()
    lo_room = np.array([-ROOM_HALF_X, -ROOM_HEIGHT, -ROOM_HALF_Z]) - _ROOM_OVERLAP
    hi_room = np.array([ROOM_HALF_X, 0.0, ROOM_HALF_Z]) + _ROOM_OVERLAP
    room_faces = {(1, 1): "floor", (1, 0): "ceiling", (2, 1): "wall0", (2, 0): "wall1",
                  (0, 1): "wall2", (0, 0): "wall3"}
    for (axis, side), name in room_faces.items():
        level = (0.0, -ROOM_HEIGHT)[1 - side] if axis == 1 else (-1, 1)[side] * (ROOM_HALF_X, 0, ROOM_HALF_Z)[axis]
        u, v = [a for a in range(3) if a != axis]
        mesh.add_quad(axis, level, (lo_room[u], lo_room[v]), (hi_room[u], hi_room[v]), -1.0 if side else 1.0,
                      room[name])
    mesh.add_boxes(boxes, on_room_boundary)
    return mesh.build()


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    return scene
