"""Floor plans of several rooms joined by corridors and doorways: axis-aligned regions of free
space and the closed shell of walls, floors and ceilings around them.

This module owns the shell geometry of recon.synthetic.walkthrough: a :class:`Region` is an
axis-aligned full-height box of free space (floor y = 0, ceiling y = -height, y down), two
touching regions are joined by an :class:`Opening`, and walls have no thickness. The shell
must be closed (a ray from inside always hits a face), which post boxes on the jambs and
skirt quads behind seams ensure.
More: docs/running.md#the-synthetic-scenes
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .room import Box, MeshBuilder

OVERLAP = 0.05  # metres a face reaches past its edges into the solid
POST_HALF = 0.06  # half the side of a jamb post; > OVERLAP, so the walls' overlaps end inside it
_SKIRT_GAP = 0.001  # metres a seam's skirt lies behind the floor or ceiling
_EPS = 1e-9
# Wall names as in recon.synthetic.room: (axis, side) of the plane, side 1 = the region's hi.
WALLS = {"wall0": (2, 1), "wall1": (2, 0), "wall2": (0, 1), "wall3": (0, 0)}


@dataclass(frozen=True)
class Region:
    """Axis-aligned free space from (x, z) = ``lo`` to ``hi`` (metres), floor to ceiling.

    ``faces`` maps "floor", "ceiling" and "wall0".."wall3" (wall0 at z = hi, wall1 at z = lo,
    wall2 at x = hi, wall3 at x = lo) to material ids.
    """

    name: str
    lo: tuple[float, float]
    hi: tuple[float, float]
    faces: dict

    def contains(self, x: np.ndarray, z: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(P,) whether points (x, z) (P,) lie inside, at least `margin` from the walls."""
        return ((x >= self.lo[0] + margin) & (x <= self.hi[0] - margin)
                & (z >= self.lo[1] + margin) & (z <= self.hi[1] - margin))


@dataclass(frozen=True)
class Opening:
    """Where region ``regions[0]`` (on the low side) meets ``regions[1]``: the plane
    ``axis`` (0: x, 2: z) = ``level``, over ``span`` (lo, hi) along the other horizontal axis."""

    axis: int
    level: float
    span: tuple[float, float]
    regions: tuple[str, str]


def _xz(axis: int) -> int:
    """Index into an (x, z) pair of world axis 0 or 2."""
    return axis // 2


def find_openings(regions: list[Region]) -> list[Opening]:
    """Every opening between two touching regions (their shared wall overlap)."""
    out = []
    for i, a in enumerate(regions):
        for b in regions[i + 1:]:
            for axis in (0, 2):
                k, other = _xz(axis), 1 - _xz(axis)
                for low, high in ((a, b), (b, a)):
                    if abs(low.hi[k] - high.lo[k]) > _EPS:
                        continue
                    span = (max(low.lo[other], high.lo[other]), min(low.hi[other], high.hi[other]))
                    if span[1] - span[0] > _EPS:
                        out.append(Opening(axis, low.hi[k], span, (low.name, high.name)))
    return out


def _subtract(interval: tuple[float, float], holes: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The parts of `interval` outside the `holes` (sorted, non-overlapping within it)."""
    pieces, start = [], interval[0]
    for h0, h1 in sorted(holes):
        if h0 - start > _EPS:
            pieces.append((start, h0))
        start = max(start, h1)
    if interval[1] - start > _EPS:
        pieces.append((start, interval[1]))
    return pieces


def _add_walls(mesh: MeshBuilder, region: Region, openings: list[Opening], height: float) -> None:
    """The region's four walls, less its openings; every piece reaches OVERLAP past its
    ends (into the next wall's solid, or into a jamb post) and past floor and ceiling."""
    for name, (axis, side) in WALLS.items():
        k, other = _xz(axis), 1 - _xz(axis)
        level = (region.lo, region.hi)[side][k]
        holes = [o.span for o in openings
                 if region.name in o.regions and o.axis == axis and abs(o.level - level) < _EPS]
        for p0, p1 in _subtract((region.lo[other], region.hi[other]), holes):
            along, vertical = (p0 - OVERLAP, p1 + OVERLAP), (-height - OVERLAP, OVERLAP)
            # The quad's two in-plane axes in increasing order: (y, z) for x walls, (x, y) for z walls.
            lo2, hi2 = ((vertical[0], along[0]), (vertical[1], along[1])) if axis == 0 else \
                ((along[0], vertical[0]), (along[1], vertical[1]))
            mesh.add_quad(axis, level, lo2, hi2, -1.0 if side else 1.0, region.faces[name])


def _add_floor_and_ceiling(mesh: MeshBuilder, region: Region, openings: list[Opening], height: float) -> None:
    """Floor and ceiling, reaching OVERLAP under the walls on sides without an opening and
    ending at the wall plane on sides with one (the neighbour's floor goes on from there)."""
    reach = np.full((2, 2), OVERLAP)  # [side lo/hi, x/z]
    for o in openings:
        if region.name in o.regions:
            reach[int(o.regions[0] == region.name), _xz(o.axis)] = 0.0
    lo2 = (region.lo[0] - reach[0, 0], region.lo[1] - reach[0, 1])
    hi2 = (region.hi[0] + reach[1, 0], region.hi[1] + reach[1, 1])
    mesh.add_quad(1, 0.0, lo2, hi2, -1.0, region.faces["floor"])
    mesh.add_quad(1, -height, lo2, hi2, 1.0, region.faces["ceiling"])


def _add_seam_skirts(mesh: MeshBuilder, opening: Opening, height: float, material: int) -> None:
    """Quads 1 mm below the floor and above the ceiling across an opening's seam."""
    span = (opening.span[0] - POST_HALF, opening.span[1] + POST_HALF)
    across = (opening.level - OVERLAP, opening.level + OVERLAP)
    lo2, hi2 = ((across[0], span[0]), (across[1], span[1])) if opening.axis == 0 else \
        ((span[0], across[0]), (span[1], across[1]))
    mesh.add_quad(1, _SKIRT_GAP, lo2, hi2, -1.0, material)
    mesh.add_quad(1, -height - _SKIRT_GAP, lo2, hi2, 1.0, material)


def jamb_posts(openings: list[Opening], height: float, material: int) -> list[Box]:
    """Closed boxes POST_HALF * 2 square, floor to ceiling, centred on each opening's two jambs."""
    posts = []
    for o in openings:
        for end in o.span:
            across, along = (o.level - POST_HALF, o.level + POST_HALF), (end - POST_HALF, end + POST_HALF)
            x, z = (across, along) if o.axis == 0 else (along, across)
            posts.append(Box((x[0], -height, z[0]), (x[1], 0.0, z[1]), material))
    return posts


def add_shell(mesh: MeshBuilder, regions: list[Region], height: float, post_material: int) -> list[Box]:
    """Add the closed shell of the regions (inward faces, jamb posts, seam skirts) to `mesh`.

    Returns the jamb posts as boxes (already added), e.g. to keep a camera path clear of them.
    """
    openings = find_openings(regions)
    for region in regions:
        _add_walls(mesh, region, openings, height)
        _add_floor_and_ceiling(mesh, region, openings, height)
    by_name = {r.name: r for r in regions}
    for o in openings:
        _add_seam_skirts(mesh, o, height, by_name[o.regions[0]].faces["floor"])
    posts = jamb_posts(openings, height, post_material)
    mesh.add_boxes(posts)
    return posts
