"""Synthetic ground truth: a textured, furnished room rendered by ray casting.

This module owns the procedural scene (room + furniture boxes), its procedural textures,
the hand-held camera path and the renderer (Open3D ``RaycastingScene``); writing its frames
as a video is :func:`recon.io.video.write_video`.

World frame: metres, **y points down** (gravity) so that a level camera looking along +z
has the identity rotation in OpenCV axes. The room spans x in [-3, 3], z in [-2.5, 2.5];
the floor is the plane y = 0 and the ceiling y = -2.7. Everything else follows the package
conventions (camera-to-world poses, z-depth, intrinsics fx, fy, cx, cy with pixel centres
at integer coordinates, so the principal point of a centred camera is ((W-1)/2, (H-1)/2)).

Surfaces are axis-aligned, so textures are 2-D band-limited noise and pattern images laid
on each face's plane (world coordinates, shifted and scaled per material): the albedo of a
point depends only on the point and its object, and shading is Lambertian with fixed point
lights, so a surface point has the same colour in every view.
"""

from __future__ import annotations

import colorsys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d
import scipy.fft

from ..errors import ReconInputError

ROOM_HALF_X = 3.0
ROOM_HALF_Z = 2.5
ROOM_HEIGHT = 2.7
# Room faces reach past the corners so no ray can slip through a seam between walls.
_ROOM_OVERLAP = 0.05

# Textures: one periodic image stack shared by all materials, 4 mm texels, 8.192 m period
# (a power of two, so checker and stripe periods tile it exactly).
TEXEL = 0.004
TEXTURE_SIZE = 2048
TEXTURE_PERIOD = TEXEL * TEXTURE_SIZE
_TEXTURE_LEVELS = 7  # mip levels down to 25.6 cm texels: enough for grazing views at low resolution
_CHECKER_PERIOD = 0.512  # 25.6 cm tiles
_STRIPE_PERIOD = 0.128

# Camera path: per-frame rates, so longer sequences just go on along the same kind of path.
_YAW_RATE = np.deg2rad(0.4)  # rad/frame of the slow turn through the room: 48 degrees in 120 frames
_FIXATION = 3.0  # metres: sideways steps turn the camera toward a point this far ahead
_PATH_SQUASH = (1.0, 0.75)  # x, z: fits the walk's disk (radius <= 1.1 m) into the free middle of the room
_EYE_HEIGHT = 1.45
_PITCH_DOWN = np.deg2rad(17.0)

_LIGHTS = np.array([[-1.6, -2.55, -1.1], [1.7, -2.55, 1.2], [0.3, -2.55, -1.9]], dtype=np.float32)
_LIGHT_POWER = np.array([0.75, 0.75, 0.5], dtype=np.float32)
_LIGHT_FALLOFF = 2.5  # metres at which a light's irradiance halves
_AMBIENT = 0.35
_CHUNK_PIXELS = 1_250_000  # pixels ray-cast and shaded per batch: ~150 MB of temporaries


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


@dataclass
class SyntheticSequence:
    """A rendered sequence with its ground truth.

    Attributes:
        rgb: (N, H, W, 3) uint8 frames.
        depth: (N, H, W) float32 z-depth in metres, > 0 everywhere (the room is closed).
        poses: (N, 4, 4) float64 camera-to-world poses (OpenCV camera axes).
        intrinsics: (fx, fy, cx, cy) in pixels; cx = (W-1)/2, cy = (H-1)/2.
        mesh_vertices: (V, 3) float64 ground-truth mesh vertices, world coordinates
            (y down, floor at y = 0; see the module docstring). Exactly the rendered
            geometry: the room's faces reach 5 cm past its edges (outside, never seen);
            box faces flush with the floor, a wall or a supporting box are left out.
        mesh_triangles: (F, 3) int64 vertex indices, counter-clockwise seen from the
            visible side (normals point into free space).
        mesh_colors: (V, 3) float64 in [0, 1], each object's base colour.
        triangle_materials: (F,) int64 material id of each triangle.
        boxes: (B, 2, 3) float64 min and max corners of the furniture boxes.
        seed: the scene seed.
        room_bounds: (2, 3) float64 min and max corners of the room.
    """

    rgb: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    mesh_vertices: np.ndarray
    mesh_triangles: np.ndarray
    mesh_colors: np.ndarray
    triangle_materials: np.ndarray
    boxes: np.ndarray
    seed: int = 0
    room_bounds: np.ndarray = field(
        default_factory=lambda: np.array([[-ROOM_HALF_X, -ROOM_HEIGHT, -ROOM_HALF_Z], [ROOM_HALF_X, 0.0, ROOM_HALF_Z]])
    )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 pinhole matrix."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def num_frames(self) -> int:
        return self.rgb.shape[0]

    @property
    def height(self) -> int:
        return self.rgb.shape[1]

    @property
    def width(self) -> int:
        return self.rgb.shape[2]

    def o3d_mesh(self) -> o3d.geometry.TriangleMesh:
        """The ground-truth mesh as a legacy Open3D TriangleMesh with vertex colours and normals."""
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.mesh_vertices),
            o3d.utility.Vector3iVector(self.mesh_triangles.astype(np.int32)),
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.mesh_colors)
        mesh.compute_triangle_normals()
        mesh.compute_vertex_normals()
        return mesh

    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        """A RaycastingScene of the ground-truth mesh (for distances, extra rays)."""
        return _raycasting_scene(self.mesh_vertices, self.mesh_triangles)


# --------------------------------------------------------------------------- scene layout


def intrinsics_for(width: int, height: int) -> tuple[float, float, float, float]:
    """Pinhole intrinsics of the synthetic camera: fx = fy = 525 * W / 640, centred."""
    focal = 525.0 * width / 640.0
    return (focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)


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


def scene_layout(seed: int) -> tuple[list[Box], Materials, dict[str, int]]:
    """Furniture boxes, materials and the room surfaces' material ids, deterministic from seed.

    Furniture stands against the walls (at most 0.87 m deep, so the middle of the room,
    |x| < 2.1 m and |z| < 1.6 m, is free for the camera), pictures hang on the walls, and
    a rug with a low (< 0.45 m) coffee table lies in the middle.
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
    for i, kind in enumerate(kinds):
        w, _, parts = _FURNITURE[kind](rng)
        # Try walls in a seed-dependent order; an item that fits nowhere is dropped.
        for k in (i + rng.permutation(4)) % 4:
            # The last 0.9 m of each wall is the next wall's corner (its furniture is <= 0.87 m deep).
            if cursor[k] + w <= walls[k][3] - 0.9:
                _add_piece(boxes, book, parts, walls[k], cursor[k])
                if max(part[5] for part in parts) > 1.1:
                    tall[k].append((cursor[k], cursor[k] + w))
                cursor[k] += w + rng.uniform(0.1, 0.6)
                break
    for k, wall in enumerate(walls):
        _add_piece(boxes, book, _pictures(rng, wall[3], tall[k]), wall, 0.0)
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


def _on_room_boundary(axis: int, level: float) -> bool:
    bounds = {0: (-ROOM_HALF_X, ROOM_HALF_X), 1: (-ROOM_HEIGHT, 0.0), 2: (-ROOM_HALF_Z, ROOM_HALF_Z)}[axis]
    return min(abs(level - bounds[0]), abs(level - bounds[1])) < 1e-9


def scene_mesh(boxes: list[Box], room: dict[str, int]):
    """Triangle soup of the room (inward faces) and boxes (outward faces).

    Box faces lying on the floor or a wall are hidden and left out. Returns vertices
    (V, 3) float64, triangles (F, 3) int64 and per-triangle material ids (F,) int64.
    """
    verts, tris, mats = [], [], []

    def add(corners, t, material):
        tris.append(t + sum(len(v) for v in verts))
        verts.append(corners)
        mats.append(np.full(len(t), material))

    lo_room = np.array([-ROOM_HALF_X, -ROOM_HEIGHT, -ROOM_HALF_Z]) - _ROOM_OVERLAP
    hi_room = np.array([ROOM_HALF_X, 0.0, ROOM_HALF_Z]) + _ROOM_OVERLAP
    room_faces = {(1, 1): "floor", (1, 0): "ceiling", (2, 1): "wall0", (2, 0): "wall1",
                  (0, 1): "wall2", (0, 0): "wall3"}
    for (axis, side), name in room_faces.items():
        level = (0.0, -ROOM_HEIGHT)[1 - side] if axis == 1 else (-1, 1)[side] * (ROOM_HALF_X, 0, ROOM_HALF_Z)[axis]
        u, v = [a for a in range(3) if a != axis]
        corners, t = _quad(axis, level, (lo_room[u], lo_room[v]), (hi_room[u], hi_room[v]), -1.0 if side else 1.0)
        add(corners, t, room[name])
    for box in boxes:
        lo, hi = np.array(box.lo), np.array(box.hi)
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            for side, level in enumerate((lo[axis], hi[axis])):
                if (axis, side) in box.skip or _on_room_boundary(axis, level):
                    continue
                corners, t = _quad(axis, level, (lo[u], lo[v]), (hi[u], hi[v]), 1.0 if side else -1.0)
                add(corners, t, box.material)
    return np.concatenate(verts), np.concatenate(tris).astype(np.int64), np.concatenate(mats).astype(np.int64)


def _raycasting_scene(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    return scene


# --------------------------------------------------------------------------- textures


def _frequency_grid() -> np.ndarray:
    """(S, S//2+1) radial frequency in cycles/metre of an rfft2 of a level-0 texture."""
    fy = np.fft.fftfreq(TEXTURE_SIZE, d=TEXEL).astype(np.float32)
    fx = np.fft.rfftfreq(TEXTURE_SIZE, d=TEXEL).astype(np.float32)
    return np.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2)


def _noise_spectrum(rng: np.random.Generator, freq: np.ndarray, shortest: float, longest: float) -> np.ndarray:
    """rfft2 (S, S//2+1) of periodic noise with equal energy per octave between the wavelengths."""
    white = rng.standard_normal((TEXTURE_SIZE, TEXTURE_SIZE), dtype=np.float32)
    f = np.maximum(freq, np.float32(1e-3))
    # 1/f amplitude = equal energy per octave in 2-D; the band edges are soft (logistic in
    # log frequency) to avoid ringing.
    low, high = np.float32(1.0 / longest), np.float32(1.0 / shortest)
    gain = 1.0 / (f * (1.0 + (low / f) ** 4) * (1.0 + (f / high) ** 4))
    spectrum = scipy.fft.rfft2(white, workers=-1)
    spectrum *= gain
    spectrum[0, 0] = 0.0
    return spectrum


def _pattern_spectra() -> tuple[np.ndarray, np.ndarray]:
    """rfft2 of a 0/1 checkerboard (varying along both axes) and of 0/1 stripes along u."""
    x = (np.arange(TEXTURE_SIZE) + 0.5) * TEXEL
    checker_1d = np.floor(x / (_CHECKER_PERIOD / 2)) % 2
    stripes_1d = (np.floor(x / (_STRIPE_PERIOD / 2)) % 2).astype(np.float32)
    checker = (checker_1d[:, None] != checker_1d[None, :]).astype(np.float32)
    stripes = np.ascontiguousarray(np.broadcast_to(stripes_1d[None, :], (TEXTURE_SIZE, TEXTURE_SIZE)))
    return scipy.fft.rfft2(checker, workers=-1), scipy.fft.rfft2(stripes, workers=-1)


def _crop(spectrum: np.ndarray, size: int) -> np.ndarray:
    """The (size, size//2+1) low-frequency corner block of a full rfft2 layout."""
    half = size // 2
    return np.concatenate([spectrum[:half, : half + 1], spectrum[-half:, : half + 1]])


def _mip_level(spectra: list[np.ndarray], freq: np.ndarray, level: int) -> np.ndarray:
    """Band-limited images (s, s, C) float32 at mip `level` (texel TEXEL * 2^level) from full rfft2s."""
    size = TEXTURE_SIZE >> level
    nyquist = 0.5 / (TEXEL * 2**level)
    # A Gaussian roll-off to ~5% at the level's Nyquist frequency keeps bilinear lookups alias-free.
    gain = np.exp(-0.5 * (_crop(freq, size) / (nyquist / 2.5)) ** 2) * np.float32((size / TEXTURE_SIZE) ** 2)
    out = np.empty((size, size, len(spectra)), dtype=np.float32)
    for c, spectrum in enumerate(spectra):
        out[..., c] = scipy.fft.irfft2(_crop(spectrum, size) * gain, s=(size, size), workers=-1)
    return out


def texture_pyramid(seed: int) -> list[np.ndarray]:
    """Mip levels of the shared texture stack, level k of shape (S/2^k, S/2^k, 4) float32.

    Channels: fine luminance noise (2 cm - 50 cm features, unit std), coarse colour-mix
    noise (5 cm - 80 cm, unit std), checkerboard and stripes (both ~0/1). Texel (i, j) of
    level k sits at (u, v) = (j, i) * TEXEL * 2^k; the stack is periodic with TEXTURE_PERIOD.
    """
    rng = np.random.default_rng([seed, 2])
    freq = _frequency_grid()
    spectra = [_noise_spectrum(rng, freq, 0.02, 0.5), _noise_spectrum(rng, freq, 0.05, 0.8), *_pattern_spectra()]
    levels = [_mip_level(spectra, freq, k) for k in range(_TEXTURE_LEVELS)]
    for c in (0, 1):
        std = levels[0][..., c].std()
        for image in levels:
            image[..., c] /= std
    return levels


class _MipAtlas:
    """All mip levels in one image, each wrapped by a 1-texel periodic border, so that a
    whole batch of trilinear lookups is two cv2.remap calls.

    Layout: level 0 at the left, the smaller levels stacked in a column to its right.
    """

    def __init__(self, pyramid: list[np.ndarray]):
        sizes = [p.shape[0] for p in pyramid]
        height = sizes[0] + 2
        width = sizes[0] + 2 + (sizes[1] + 2 if len(sizes) > 1 else 0)
        self.image = np.zeros((height, width, pyramid[0].shape[2]), dtype=np.float32)
        origins = []
        x, y = sizes[0] + 2, 0
        for k, level in enumerate(pyramid):
            ox, oy = (0, 0) if k == 0 else (x, y)
            padded = np.pad(level, ((1, 1), (1, 1), (0, 0)), mode="wrap")
            self.image[oy : oy + sizes[k] + 2, ox : ox + sizes[k] + 2] = padded
            origins.append((ox + 1, oy + 1))
            if k > 0:
                y += sizes[k] + 2
        origin = np.array(origins, dtype=np.float32)
        self.origin_x, self.origin_y = origin[:, 0].copy(), origin[:, 1].copy()  # (L,) atlas position of texel (0, 0)
        self.inv_texel = (1.0 / (TEXEL * 2.0 ** np.arange(len(sizes)))).astype(np.float32)  # (L,) texels per metre
        self.levels = len(sizes)

    def sample(self, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Trilinear lookup (P, C) at texture-plane metres u, v (P,) and fractional mip level (P,)."""
        level = np.clip(level, 0.0, self.levels - 1.001).astype(np.float32)
        base = level.astype(np.int32)
        weight = (level - base)[:, None]
        # Every level has the same period in metres, so wrap once here.
        period = np.float32(TEXTURE_PERIOD)
        u = u - np.floor(u / period) * period
        v = v - np.floor(v / period) * period
        out = self._bilinear(u, v, base)
        out += (self._bilinear(u, v, base + 1) - out) * weight
        return out

    def _bilinear(self, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
        scale = self.inv_texel[level]
        x = u * scale + self.origin_x[level]
        y = v * scale + self.origin_y[level]
        # cv2.remap wants 2-D maps with sides below SHRT_MAX: lay the points out in rows.
        n, cols = len(u), 1024
        if n % cols:
            pad = cols - n % cols
            x, y = np.concatenate([x, np.zeros(pad, np.float32)]), np.concatenate([y, np.zeros(pad, np.float32)])
        out = cv2.remap(self.image, x.reshape(-1, cols), y.reshape(-1, cols), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(-1, self.image.shape[2])[:n]


# --------------------------------------------------------------------------- camera path


def _rotation(yaw: float, pitch_down: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (3, 3): yaw about world y (down), then pitch, then roll."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch_down), np.sin(pitch_down)
    cr, sr = np.cos(roll), np.sin(roll)
    r_yaw = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    # Positive pitch_down tilts the optical axis (+z) toward +y, i.e. toward the floor.
    r_pitch = np.array([[1, 0, 0], [0, cp, sp], [0, -sp, cp]])
    r_roll = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return r_yaw @ r_pitch @ r_roll


def camera_path(num_frames: int, seed: int, speed: float = 1.0, times=None) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world poses of a smooth hand-held scan of the room.

    speed: path time per frame (2: every other frame of the speed-1 path, twice the motion
    per frame). times: explicit path times (N,) instead (sub-frames for motion blur).

    The heading turns slowly (0.4 deg/frame plus a gentle sway) so the camera sweeps the
    room; meanwhile the camera steps sideways back and forth (up to 1 m, ~2 cm/frame) and
    a little forward/back, turning toward a point ~3 m ahead as it steps, like a person
    scanning what is in front of them. That keeps frames 32-64 apart overlapping while
    giving plenty of parallax. The walk stays in the free middle of the room (|x| <= 1.1 m,
    |z| <= 0.85 m, eye height ~1.45 m), looking ~17 degrees down with small smooth
    pitch/roll wobble and hand shake. Motion per frame does not depend on num_frames.
    """
    rng = np.random.default_rng([seed, 3])
    t = np.arange(num_frames, dtype=np.float64) * float(speed) if times is None else np.asarray(times, np.float64)
    num_frames = len(t)
    phase = rng.uniform(0, 2 * np.pi, 12)
    wave = lambda amplitude, period, k: amplitude * np.sin(2 * np.pi * t / period + phase[k])  # noqa: E731
    heading = rng.uniform(0, 2 * np.pi) + rng.choice([-1.0, 1.0]) * _YAW_RATE * t + wave(0.04, 95, 0)
    side = wave(0.85, 170, 1) + wave(0.15, 80, 2)  # metres along the heading's right vector
    ahead = -0.2 + wave(0.2, 150, 3) + wave(0.05, 47, 4)  # metres along the heading (mostly behind the centre)
    right = np.stack([np.cos(heading), -np.sin(heading)], axis=1)  # (x, z) of the camera's x axis at yaw = heading
    forward = np.stack([np.sin(heading), np.cos(heading)], axis=1)
    xz = (side[:, None] * right + ahead[:, None] * forward) * np.array(_PATH_SQUASH)
    # Hand shake: small and smooth (periods of 17-31 frames).
    x = xz[:, 0] + wave(0.005, 23, 5)
    z = xz[:, 1] + wave(0.005, 31, 6)
    y = -(_EYE_HEIGHT + wave(0.04, 70, 7) + wave(0.004, 17, 8))
    # Stepping right turns the camera left (toward the fixation point) and vice versa.
    yaw = heading - np.arctan(side / _FIXATION)
    pitch = _PITCH_DOWN + wave(0.035, 53, 9) + wave(0.01, 19, 10)
    roll = wave(0.025, 61, 11) + 0.008 * np.sin(2 * np.pi * t / 21 + phase[0])
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(num_frames):
        poses[i, :3, :3] = _rotation(yaw[i], pitch[i], roll[i])
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses


# --------------------------------------------------------------------------- rendering


def _camera_rays(intrinsics, width: int, height: int) -> np.ndarray:
    """(H*W, 3) float64 camera-frame ray directions with unit z through the pixel centres."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)


def _pick(axis: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Per point, the component (x, y or z) along its face axis (P,)."""
    return np.where(axis == 0, x, np.where(axis == 1, y, z))


def _irradiance(px, py, pz, axis, facing, p_axis) -> np.ndarray:
    """Lambertian irradiance (P,) from ambient light and point lights at points (px, py, pz)
    on axis-aligned faces whose visible normal is `facing` (+1/-1) along `axis`; p_axis is
    the points' coordinate along that axis."""
    irradiance = np.full(len(px), _AMBIENT, dtype=np.float32)
    for light, power in zip(_LIGHTS, _LIGHT_POWER):
        dist2 = np.square(light[0] - px)
        dist2 += np.square(light[1] - py)
        dist2 += np.square(light[2] - pz)
        # n . (light - p) for an axis-aligned normal is one signed component.
        along = light[axis] - p_axis
        along *= facing
        np.maximum(along, 0.0, out=along)
        falloff = dist2 * np.float32(1.0 / _LIGHT_FALLOFF**2) + 1.0
        falloff *= np.sqrt(dist2)
        along *= np.float32(power)
        along /= falloff
        irradiance += along
    return irradiance


def _albedo(params: np.ndarray, tex: np.ndarray) -> list[np.ndarray]:
    """Albedo channels [r, g, b], each (P,), from per-point material parameters (12, P)
    (rows as in Materials.table) and texture samples (P, 4)."""
    mix = np.clip(0.5 + 0.4 * tex[:, 1], 0.0, 1.0)
    pattern = 1.0 + params[7] * (tex[:, 2] - 0.5)
    pattern += params[8] * (tex[:, 3] - 0.5)
    lum = np.exp(params[6] * tex[:, 0])
    lum *= pattern
    return [(params[c] + (params[3 + c] - params[c]) * mix) * lum for c in range(3)]


# Linear intensity -> 8-bit with a display gamma (dark regions keep visible texture).
_GAMMA_STEPS = 4096
_GAMMA_LUT = np.round(255.0 * (np.arange(_GAMMA_STEPS) / (_GAMMA_STEPS - 1)) ** (1 / 2.2)).astype(np.uint8)


def _encode(linear: np.ndarray) -> np.ndarray:
    index = np.clip(linear, 0.0, 1.0)
    index *= _GAMMA_STEPS - 1
    index += 0.5
    return _GAMMA_LUT[index.astype(np.int32)]


# Shading runs over blocks of this many pixels: their temporaries stay in the CPU cache,
# which makes the long chain of elementwise numpy operations several times faster.
_SHADE_BLOCK = 16384


class _Renderer:
    """Renders frames of one scene; holds the ray-casting scene, per-triangle data and textures."""

    def __init__(
        self, vertices, triangles, triangle_materials, materials: Materials, pyramid, intrinsics, width, height
    ):
        self.scene = _raycasting_scene(vertices, triangles)
        corners = vertices[triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self.triangle_axis = np.abs(normals).argmax(axis=1).astype(np.int64)
        self.triangle_params_t = np.ascontiguousarray(materials.table()[triangle_materials].T)  # (12, F)
        self.atlas = _MipAtlas(pyramid)
        rays = _camera_rays(intrinsics, width, height)
        self.ray_x, self.ray_y = rays[:, 0].astype(np.float32), rays[:, 1].astype(np.float32)
        self.ray_norm = np.linalg.norm(rays, axis=1).astype(np.float32)
        # A fronto-parallel surface at depth d covers d / (|ray| * f) metres per pixel.
        self.footprint = 1.0 / (self.ray_norm * np.float32(intrinsics[0]))
        self.shape = (height, width)

    def render(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb (n, H, W, 3) uint8 and z-depth (n, H, W) float32 for poses (n, 4, 4)."""
        n, pixels = len(poses), len(self.ray_x)
        origin = poses[:, :3, 3].astype(np.float32)[:, :, None]  # (n, 3, 1)
        rot = poses[:, :3, :3].astype(np.float32)[:, :, :, None]  # (n, 3, 3, 1)
        # Components are kept as separate contiguous arrays: much faster than (P, 3) columns.
        d = [rot[:, k, 0] * self.ray_x + rot[:, k, 1] * self.ray_y + rot[:, k, 2] for k in range(3)]  # 3 x (n, P)
        rays = np.empty((n, pixels, 6), dtype=np.float32)
        for k in range(3):
            rays[:, :, k] = origin[:, k]
            rays[:, :, 3 + k] = d[k]
        hit = self.scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)))
        del rays
        # Ray directions have unit z in the camera frame, so the ray parameter is the z-depth.
        depth = hit["t_hit"].numpy().reshape(n, pixels)
        if not np.isfinite(depth).all():
            raise RuntimeError("synthetic renderer: a ray left the room (camera outside?)")
        prim = hit["primitive_ids"].numpy().reshape(-1)
        points = [(origin[:, k] + d[k] * depth).reshape(-1) for k in range(3)]
        dirs = [c.reshape(-1) for c in d]
        flat_depth = depth.reshape(-1)
        rgb = np.empty((n * pixels, 3), dtype=np.uint8)
        for start in range(0, n * pixels, _SHADE_BLOCK):
            block = slice(start, start + _SHADE_BLOCK)
            pix = np.arange(start, min(start + _SHADE_BLOCK, n * pixels)) % pixels
            rgb[block] = self._shade(
                [c[block] for c in points], [c[block] for c in dirs], prim[block].astype(np.int64), flat_depth[block],
                pix,
            )
        return rgb.reshape(n, *self.shape, 3), depth.reshape(n, *self.shape)

    def _shade(self, points, dirs, prim, depth, pix) -> np.ndarray:
        """Colours (P, 3) uint8 of ray hits: points and ray directions as 3 x (P,), triangle
        ids, depths and pixel indices (P,)."""
        px, py, pz = points
        axis = self.triangle_axis[prim]
        d_axis = _pick(axis, *dirs)
        # The visible side of a face is the one facing the camera; closed solids are only
        # seen from outside, so this is view-independent.
        facing = np.where(d_axis > 0, np.float32(-1.0), np.float32(1.0))
        cos = np.abs(d_axis) / self.ray_norm[pix]
        params = np.take(self.triangle_params_t, prim, axis=1)  # (12, P)
        tex = self._texture(px, py, pz, axis, params, depth * self.footprint[pix], cos)
        irradiance = _irradiance(px, py, pz, axis, facing, _pick(axis, px, py, pz))
        rgb = np.empty((len(px), 3), dtype=np.uint8)
        for c, albedo in enumerate(_albedo(params, tex)):
            np.clip(albedo, 0.02, 1.0, out=albedo)
            albedo *= irradiance
            rgb[:, c] = _encode(albedo)
        return rgb

    def _texture(self, px, py, pz, axis, params, footprint, cos) -> np.ndarray:
        """Texture samples (P, 4) at hit points on faces normal to axis (P,) with material
        parameters (12, P)."""
        # In-plane coordinates: horizontal first, so stripes along u are vertical on walls.
        u = np.where(axis == 0, pz, px)
        v = np.where(axis == 1, pz, py)
        scale = params[9]
        u = u * scale + params[10]
        v = v * scale + params[11]
        # Mip level from the pixel footprint; the square root splits a grazing view's
        # stretch between blur and aliasing.
        footprint *= scale
        footprint /= np.sqrt(np.maximum(cos, 0.05))
        level = np.log2(np.maximum(footprint, 1e-6) * np.float32(1.0 / TEXEL))
        return self.atlas.sample(u, v, level)


def render_sequence(
    num_frames: int = 120,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    chunk: int | None = None,
    threads: int = 2,
    speed: float = 1.0,
    blur: int = 1,
    exposure: float = 0.5,
) -> SyntheticSequence:
    """Render the synthetic room along the hand-held camera path.

    Args:
        num_frames: N >= 1; the path advances ~2 cm and ~0.4 degrees of yaw per frame
            (times `speed`).
        speed: motion per frame relative to the default path (a fast hand-held walk: 4-8).
        blur: sub-frames rendered and averaged per frame, spread over `exposure` (a
            fraction of the frame interval) centred on the frame's time: motion blur.
            The pose, depth and mesh are those of the frame's time (the middle of the
            exposure); 1 renders sharp frames.
        width, height: image size in pixels (>= 8); fx = fy = 525 * width / 640,
            cx = (width - 1) / 2, cy = (height - 1) / 2.
        seed: scene layout, colours, textures and path phases; the same seed gives
            bit-identical output.
        chunk: frames ray-cast per batch (memory vs. overhead); default: about 1.2
            million pixels, fewer if that leaves a thread idle.
        threads: batches rendered concurrently.

    Returns:
        a SyntheticSequence with rgb (N, H, W, 3) uint8, depth (N, H, W) float32, poses
        (N, 4, 4) camera-to-world in a y-down world frame, intrinsics and the ground-truth
        mesh.
    """
    if int(num_frames) < 1:
        raise ReconInputError(f"synthetic sequence: num_frames must be >= 1, got {num_frames}")
    if int(width) < 8 or int(height) < 8:
        raise ReconInputError(f"synthetic sequence: image size must be at least 8x8, got {width}x{height}")
    num_frames, width, height, seed = int(num_frames), int(width), int(height), int(seed)
    boxes, materials, room = scene_layout(seed)
    vertices, triangles, triangle_materials = scene_mesh(boxes, room)
    intrinsics = intrinsics_for(width, height)
    blur = int(blur)
    if blur < 1 or not (0.0 <= exposure <= 1.0) or not speed > 0:
        raise ReconInputError(f"synthetic sequence: need blur >= 1, 0 <= exposure <= 1 and speed > 0, got "
                              f"blur={blur}, exposure={exposure}, speed={speed}")
    times = np.arange(num_frames, dtype=np.float64) * float(speed)
    poses = camera_path(num_frames, seed, times=times)
    # Sub-frame times, frame-major: blur steps evenly over the exposure around each frame.
    offsets = (np.arange(blur) + 0.5) / blur - 0.5 if blur > 1 else np.zeros(1)
    sub_poses = camera_path(0, seed, times=(times[:, None] + offsets * exposure * float(speed)).reshape(-1))
    renderer = _Renderer(vertices, triangles, triangle_materials, materials, texture_pyramid(seed), intrinsics, width,
                         height)
    rgb = np.empty((num_frames, height, width, 3), dtype=np.uint8)
    depth = np.empty((num_frames, height, width), dtype=np.float32)
    threads = max(1, int(threads))
    if chunk is None:
        chunk = min(max(_CHUNK_PIXELS // (width * height * blur), 1), -(-num_frames // threads))
    chunk = max(1, int(chunk))
    starts = range(0, num_frames, chunk)

    def work(start: int) -> None:
        stop = min(start + chunk, num_frames)
        if blur == 1:
            rgb[start:stop], depth[start:stop] = renderer.render(poses[start:stop])
            return
        colour, _ = renderer.render(sub_poses[start * blur : stop * blur])
        # Averaged in linear light would be more exact; the renderer's output is what a
        # camera integrates well enough for a tracking test.
        rgb[start:stop] = colour.reshape(stop - start, blur, height, width, 3).mean(1).round().astype(np.uint8)
        depth[start:stop] = renderer.render(poses[start:stop])[1]

    # numpy, OpenCV and Open3D release the GIL in their kernels, so two chunks in flight
    # keep both cores of a small machine busy; chunks are independent, so output is identical.
    with ThreadPoolExecutor(max_workers=min(threads, len(starts))) as pool:
        list(pool.map(work, starts))
    colors = np.zeros_like(vertices)
    colors[triangles.reshape(-1)] = np.repeat(materials.color_a[triangle_materials], 3, axis=0)
    return SyntheticSequence(
        rgb=rgb,
        depth=depth,
        poses=poses,
        intrinsics=intrinsics,
        mesh_vertices=vertices,
        mesh_triangles=triangles,
        mesh_colors=colors,
        triangle_materials=triangle_materials,
        boxes=np.array([[b.lo, b.hi] for b in boxes], dtype=np.float64).reshape(-1, 2, 3),
        seed=seed,
    )
