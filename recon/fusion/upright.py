"""Which way is up: the rotation that stands a reconstruction upright.

A run's world is the frame its poses came in, not level in general; the GLB and the exports
are rotated upright, while the trajectory, the PLY and the depth maps stay in the run's
world. Up is the cameras' mean down axis (as nerfstudio's "auto orient"), corrected by the
fused surface's normals under the Manhattan-world prior (e.g. Gupta et al., CVPR 2013):
floors along up, walls across it, found by a Hough vote and refined in narrowing cones. When
too little of the surface is floor or wall the cameras' guess stands, and the result says so.
Conventions: world points in the run's OpenCV-like axes, up is -y once upright (the GLB's
conversion to glTF then makes it +y). More: docs/fusion.md#upright-output
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Where "up" points once upright, in OpenCV world axes (y down).
UPRIGHT_UP = np.array([0.0, -1.0, 0.0])
# Rounds of the surface refinement: the cone (degrees) around up, and across it, in which
# a normal counts as a floor's (a wall's).
CONES_DEG = (20.0, 10.0, 5.0)
# The normals: the surface thinned to a grid of this share of its extent, each normal
# fitted over NORMAL_CELLS cells around its point.
GRID_SHARE = 1.0 / 150.0
NORMAL_CELLS = 4.0
# The vote: candidate ups within SEARCH_DEG of the cameras' guess, VOTE_STEP_DEG apart; a
# normal votes within VOTE_CONE_DEG (of the direction: floor; of square to it: wall). Of
# directions that score alike (a wall alone leaves a ridge of them) the one nearest the
# guess wins: each degree away costs VOTE_DEG_COST of share.
SEARCH_DEG = 35.0
VOTE_STEP_DEG = 1.0
VOTE_CONE_DEG = 4.0
VOTE_DEG_COST = 5e-4
# Surfaces in the cones must make at least this share of the surface to move the guess.
MIN_SURFACE_SHARE = 0.02
# The cameras' guess keeps this weight against the surfaces' (shares of the surface).
CAMERA_PRIOR_WEIGHT = 0.01


@dataclass(frozen=True)
class Upright:
    """rotation: (3, 3) taking the run's world to the upright one (up = -y); up: (3,) the
    estimated up direction in the run's world; tilt_deg: the angle between the two ups (how
    far the run's world was from level); source: "surfaces" (the scene's floors and walls
    refined the cameras' guess), "cameras" (too little of either) or "none" (no pose: left
    as it is); horizontal, vertical: the shares of the surface that counted as floors and
    as walls in the last round."""

    rotation: np.ndarray
    up: np.ndarray
    tilt_deg: float
    source: str
    horizontal: float = 0.0
    vertical: float = 0.0

    @property
    def transform(self) -> np.ndarray:
        """The rotation as a rigid transform (no translation).

        Returns:
            (4, 4) float64 transform.
        """
        t = np.eye(4)
        t[:3, :3] = self.rotation
        return t

    def to_dict(self) -> dict:
        """The estimate as JSON-ready values for report.json.

        Returns:
            dict with the transform (4x4 list), up_in_world, tilt_deg, source, the horizontal
            and vertical shares and what the rotation applies to.
        """
        return {"transform": self.transform.round(9).tolist(), "up_in_world": self.up.round(9).tolist(),
                "tilt_deg": round(float(self.tilt_deg), 3), "source": self.source,
                "horizontal_share": round(float(self.horizontal), 4), "vertical_share": round(float(self.vertical), 4),
                "applies_to": "mesh.glb and the COLMAP/nerfstudio exports; trajectory.txt, mesh.ply and the "
                              "depth maps stay in the run's world"}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _smallest_eigenvector(m: np.ndarray) -> np.ndarray:
    return np.linalg.eigh(m)[1][:, 0]


def camera_up(poses: np.ndarray) -> np.ndarray | None:
    """The cameras' mean up (minus their mean image-y axis) in the world.

    Args:
        poses: (N, 4, 4) camera-to-world, OpenCV axes; non-finite poses are ignored.

    Returns:
        (3,) unit vector, or None without a finite pose.
    """
    poses = np.asarray(poses, dtype=np.float64)
    down = poses[np.isfinite(poses).all(axis=(1, 2)), :3, 1].sum(axis=0)
    if np.linalg.norm(down) < 1e-9:
        return None
    return -_unit(down)


def surface_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals of a surface's points, one per equal patch of surface.

    The points are thinned to a grid (``GRID_SHARE`` of the extent, so each normal stands
    for about the same area) and the normals fitted over ``NORMAL_CELLS`` cells.

    Args:
        points: (M, 3) surface points in metres.

    Returns:
        (K, 3) unit normals, sign arbitrary; (0, 3) for fewer than 100 points.
    """
    import open3d as o3d

    points = np.asarray(points, dtype=np.float64)
    if len(points) < 100:
        return np.zeros((0, 3))
    extent = float(np.linalg.norm(np.percentile(points, 98, axis=0) - np.percentile(points, 2, axis=0)))
    cell = max(extent * GRID_SHARE, 1e-6)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(cell)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_CELLS * cell, max_nn=60))
    return np.asarray(cloud.normals)


def refine_with_surfaces(guess: np.ndarray, normals: np.ndarray, cones_deg=CONES_DEG
                         ) -> tuple[np.ndarray, float, float]:
    """The cameras' up refined by the floors and walls (module docstring, part 2).

    Args:
        guess: (3,) unit up.
        normals: (K, 3) unit normals, one per equal patch of surface.
        cones_deg: the cone half-angles in degrees of the successive rounds.

    Returns:
        The refined unit up (3,) (in the guess's hemisphere) and the shares of the normals
        that counted as horizontal and vertical in the last round; the guess itself (and
        zeros) when they make less than ``MIN_SURFACE_SHARE``.
    """
    prior = _unit(np.asarray(guess, dtype=np.float64))
    if not len(normals):
        return prior, 0.0, 0.0
    up = prior
    for cone in cones_deg:
        cosine = np.abs(normals @ up)
        floors = normals[cosine >= np.cos(np.radians(cone))]
        walls = normals[cosine <= np.sin(np.radians(cone))]
        if len(floors) + len(walls) < MIN_SURFACE_SHARE * len(normals):
            return prior, 0.0, 0.0
        # Up most along the floors' normals and most across the walls': the smallest
        # eigenvector of sum (I - n n^T) over floors + sum n n^T over walls (+ the guess).
        m = len(floors) * np.eye(3) - floors.T @ floors + walls.T @ walls
        m += CAMERA_PRIOR_WEIGHT * len(normals) * (np.eye(3) - np.outer(prior, prior))
        refined = _smallest_eigenvector(m)
        up = refined if refined @ prior >= 0 else -refined
    return up, len(floors) / len(normals), len(walls) / len(normals)


def directions_around(axis: np.ndarray, max_deg: float, step_deg: float) -> np.ndarray:
    """Unit directions spread evenly (a Fibonacci spiral) over a cap around an axis.

    Args:
        axis: (3,) unit axis.
        max_deg: the cap's half-angle in degrees.
        step_deg: about this many degrees between directions.

    Returns:
        (K, 3) unit directions, the axis itself first.
    """
    axis = _unit(np.asarray(axis, dtype=np.float64))
    cap = 2.0 * np.pi * (1.0 - np.cos(np.radians(max_deg)))
    count = max(int(np.ceil(cap / np.radians(step_deg) ** 2)), 1)
    k = np.arange(count) + 0.5
    cos_polar = 1.0 - (1.0 - np.cos(np.radians(max_deg))) * k / count
    azimuth = np.pi * (3.0 - np.sqrt(5.0)) * k
    sin_polar = np.sqrt(1.0 - cos_polar**2)
    local = np.stack([sin_polar * np.cos(azimuth), sin_polar * np.sin(azimuth), cos_polar], axis=1)
    # A frame whose third axis is `axis`.
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = _unit(np.cross(axis, helper))
    frame = np.stack([e1, np.cross(axis, e1), axis], axis=1)
    return np.concatenate([axis[None], local @ frame.T])


def vote_up(guess: np.ndarray, normals: np.ndarray, search_deg: float = SEARCH_DEG) -> tuple[np.ndarray, float]:
    """The candidate up that the most normals vote for as floors and walls (module docstring).

    Args:
        guess: (3,) unit up.
        normals: (K, 3) unit normals, sign arbitrary, K >= 1.
        search_deg: candidates lie within this many degrees of `guess`.

    Returns:
        The winning candidate (3,) and its score (a share of the normals).
    """
    candidates = directions_around(guess, search_deg, VOTE_STEP_DEG)
    along, across = np.cos(np.radians(VOTE_CONE_DEG)), np.sin(np.radians(VOTE_CONE_DEG))
    score = np.empty(len(candidates))
    # (16, K) at a time, in place: the block stays in cache. The count over K is the share's
    # numerator, exactly as the mean of the booleans would sum it.
    normals_t = np.ascontiguousarray(normals.T)
    for start in range(0, len(candidates), 16):
        cosine = candidates[start : start + 16] @ normals_t
        np.abs(cosine, out=cosine)
        votes = cosine >= along
        votes |= cosine <= across
        score[start : start + 16] = np.count_nonzero(votes, axis=1) / len(normals)
    away = np.degrees(np.arccos(np.clip(candidates @ _unit(guess), -1.0, 1.0)))
    best = int(np.argmax(score - VOTE_DEG_COST * away))
    return candidates[best], float(score[best])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (Rodrigues).

    Args:
        a: (3,) vector (normalised here).
        b: (3,) vector (normalised here).

    Returns:
        (3, 3) rotation R with R a = b; half a turn when they are opposite.
    """
    a, b = _unit(np.asarray(a, float)), _unit(np.asarray(b, float))
    axis = np.cross(a, b)
    sin, cos = float(np.linalg.norm(axis)), float(a @ b)
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        # Opposite: half a turn about any axis perpendicular to a.
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = _unit(np.cross(a, helper))
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = axis / sin
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sin * kx + (1.0 - cos) * (kx @ kx)


def estimate_upright(poses: np.ndarray, points: np.ndarray | None = None) -> Upright:
    """The upright rotation of a reconstruction (module docstring).

    Without a finite pose the world is taken as upright already (identity, source "none").

    Args:
        poses: (N, 4, 4) camera-to-world (non-finite poses are ignored).
        points: (M, 3) of the fused surface (the mesh's vertices), or None.

    Returns:
        Upright with the rotation taking the run's world to the upright one (up = -y).
    """
    guess = camera_up(poses)
    if guess is None:
        return Upright(np.eye(3), UPRIGHT_UP.copy(), 0.0, "none")
    normals = surface_normals(points) if points is not None else np.zeros((0, 3))
    up, horizontal, vertical = guess, 0.0, 0.0
    if len(normals):
        voted, score = vote_up(guess, normals)
        if score >= MIN_SURFACE_SHARE:
            up, horizontal, vertical = refine_with_surfaces(voted, normals)
    tilt = float(np.degrees(np.arccos(np.clip(up @ UPRIGHT_UP, -1.0, 1.0))))
    source = "surfaces" if horizontal + vertical > 0 else "cameras"
    return Upright(rotation_between(up, UPRIGHT_UP), up, tilt, source, horizontal, vertical)


__all__ = ["Upright", "camera_up", "directions_around", "estimate_upright", "refine_with_surfaces", "rotation_between",
           "surface_normals", "vote_up", "UPRIGHT_UP"]
