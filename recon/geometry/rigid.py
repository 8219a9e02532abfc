"""Rigid camera poses as arrays: building them, checking and converting rotations, switching
camera axes, and resampling a trajectory in time.

Poses are (N, 4, 4) float64 rigid transforms (camera-to-world unless a function says
otherwise); quaternions are ``qx qy qz qw``; timestamps are seconds. Pose *files* live in
:mod:`recon.io.pose_formats.trajectories`; :func:`recon.poses.result.invert_poses` inverts poses.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError

# Quaternions shorter than this are noise, not a rotation, and cannot be normalised.
MIN_QUAT_NORM = 1e-6
# OpenGL <-> OpenCV camera axes: flip y and z (its own inverse).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def rotation_errors(rotations: np.ndarray) -> np.ndarray:
    """Orthonormality error max |R^T R - I| of rotation matrices.

    Args:
        rotations: (N, 3, 3) matrices.

    Returns:
        (N,) float64 errors; inf where det <= 0 (a reflection is no camera rotation).
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    gram = np.einsum("nji,njk->nik", rotations, rotations)
    err = np.abs(gram - np.eye(3)).max(axis=(1, 2))
    # A reflection is orthonormal but is not a camera rotation.
    return np.where(np.linalg.det(rotations) > 0, err, np.inf)


def quat_to_matrix(quats_xyzw: np.ndarray, path=None, linenos: Sequence[int] | None = None) -> np.ndarray:
    """Rotation matrices from quaternions ``qx qy qz qw``, normalising them.

    Args:
        quats_xyzw: (N, 4) quaternions (anything reshapeable to it).
        path: names the source in the error message; None: "<quaternions>".
        linenos: (N,) line numbers of the quaternions in `path`, named in the error.

    Returns:
        (N, 3, 3) float64 rotation matrices.

    Raises:
        ReconInputError: a quaternion's norm is below MIN_QUAT_NORM.
    """
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(norm < MIN_QUAT_NORM)
    if bad.size:
        where = "<quaternions>" if path is None else path
        line = "" if linenos is None else f":{int(linenos[bad[0]])}"
        raise ReconInputError(f"{where}{line}: quaternion has near-zero norm ({norm[bad[0]]:.2g})")
    return Rotation.from_quat(q / norm[:, None]).as_matrix()


def matrix_to_quat(rotations: np.ndarray) -> np.ndarray:
    """Quaternions ``qx qy qz qw`` with qw >= 0 from rotation matrices.

    Args:
        rotations: (N, 3, 3) rotation matrices.

    Returns:
        (N, 4) float64 unit quaternions, qw >= 0.
    """
    q = Rotation.from_matrix(np.asarray(rotations, dtype=np.float64)).as_quat()
    # q and -q are the same rotation; a fixed sign makes written files reproducible.
    return np.where(q[:, 3:4] < 0, -q, q)


def make_poses(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """4x4 poses from rotations and translations.

    Args:
        rotations: (N, 3, 3) rotation matrices.
        translations: (N, 3) translations (camera centres for camera-to-world poses).

    Returns:
        (N, 4, 4) float64 poses.
    """
    n = len(rotations)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = translations
    return poses


def opengl_to_opencv(poses: np.ndarray) -> np.ndarray:
    """Camera-to-world poses with OpenGL camera axes -> OpenCV axes (and back: same op).

    Args:
        poses: (N, 4, 4) camera-to-world poses.

    Returns:
        (N, 4, 4) float64 poses with the camera's y and z axes flipped.
    """
    return np.asarray(poses, dtype=np.float64) @ GL_TO_CV


opencv_to_opengl = opengl_to_opencv


# --------------------------------------------------------------------------------------
# Timestamps
# --------------------------------------------------------------------------------------


def associate_timestamps(
    query, reference, max_diff: float = 0.02, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matches between two timestamp lists, closest pairs first (TUM's associate.py).

    A pair (i, j) is allowed when ``|query[i] - (reference[j] + offset)| < max_diff``.

    Args:
        query: (N,) timestamps in seconds.
        reference: (M,) timestamps in seconds.
        max_diff: largest time difference of a match in seconds.
        offset: seconds added to every reference timestamp.

    Returns:
        Index arrays (K,) into query and (K,) into reference, ordered by query index.
    """
    q = np.asarray(query, dtype=np.float64).ravel()
    r = np.asarray(reference, dtype=np.float64).ravel() + offset
    order = np.argsort(r, kind="stable")
    rs = r[order]
    lo = np.searchsorted(rs, q - max_diff, side="left")
    hi = np.searchsorted(rs, q + max_diff, side="right")
    counts = hi - lo
    qi = np.repeat(np.arange(len(q)), counts)
    # Index of each candidate inside its query's window [lo, hi).
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    rj = np.repeat(lo, counts) + within
    diff = np.abs(q[qi] - rs[rj])
    keep = diff < max_diff
    qi, rj, diff = qi[keep], rj[keep], diff[keep]
    # Greedy one-to-one matching is inherently sequential; the loop runs over the few
    # candidate pairs inside the window, not over all N x M combinations.
    used_q = np.zeros(len(q), bool)
    used_r = np.zeros(len(r), bool)
    pick = []
    for k in np.argsort(diff, kind="stable"):
        if not used_q[qi[k]] and not used_r[rj[k]]:
            used_q[qi[k]] = used_r[rj[k]] = True
            pick.append(k)
    pick = np.asarray(pick, dtype=np.int64)
    out_q, out_r = qi[pick], order[rj[pick]]
    s = np.argsort(out_q, kind="stable")
    return out_q[s], out_r[s]


def interpolate_poses(
    query_ts, ref_ts, ref_poses: np.ndarray, max_gap: float = 0.1, max_diff: float = 0.02, snap: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at query timestamps from a trajectory sampled at other timestamps.

    A sample within `snap` s is taken as is (for timestamps that differ only by rounding).
    Else, between two samples at most `max_gap` s apart: SLERP of rotation, linear
    translation. Otherwise (outside the trajectory or across a gap): the nearest sample when
    within `max_diff` s.

    Args:
        query_ts: (M,) timestamps in seconds.
        ref_ts: (N,) timestamps of the trajectory in seconds, any order.
        ref_poses: (N, 4, 4) poses of the trajectory.
        max_gap: longest time in seconds between two samples to interpolate across.
        max_diff: largest time in seconds to the nearest sample outside an interpolation.
        snap: time in seconds within which a sample is taken as is.

    Returns:
        poses (M, 4, 4) float64 (NaN where none applies) and valid (M,) bool.
    """
    q = np.asarray(query_ts, dtype=np.float64).ravel()
    order = np.argsort(np.asarray(ref_ts, dtype=np.float64), kind="stable")
    t = np.asarray(ref_ts, dtype=np.float64)[order]
    ref = np.asarray(ref_poses, dtype=np.float64)[order]
    n = len(t)
    out = np.full((len(q), 4, 4), np.nan)
    if n == 0 or len(q) == 0:
        return out, np.zeros(len(q), bool)
    idx = np.searchsorted(t, q, side="right")  # t[idx-1] <= q < t[idx]
    i0 = np.clip(idx - 1, 0, n - 1)
    i1 = np.clip(idx, 0, n - 1)
    gap = t[i1] - t[i0]
    inside = (idx > 0) & (idx < n) & (gap <= max_gap)
    nearest = np.where(np.abs(q - t[i0]) <= np.abs(t[i1] - q), i0, i1)
    near_dist = np.abs(q - t[nearest])
    inside &= ~(near_dist <= snap)
    near_ok = ~inside & (near_dist <= max(max_diff, snap))

    alpha = np.where(gap > 0, (q - t[i0]) / np.where(gap > 0, gap, 1.0), 0.0)[inside]
    a, b = i0[inside], i1[inside]
    if a.size:
        rot_a = Rotation.from_matrix(ref[a, :3, :3])
        delta = (rot_a.inv() * Rotation.from_matrix(ref[b, :3, :3])).as_rotvec()
        rot = (rot_a * Rotation.from_rotvec(alpha[:, None] * delta)).as_matrix()
        trans = (1 - alpha)[:, None] * ref[a, :3, 3] + alpha[:, None] * ref[b, :3, 3]
        out[inside] = make_poses(rot, trans)
    out[near_ok] = ref[nearest[near_ok]]
    return out, inside | near_ok


def apply_similarity(poses: np.ndarray, rot: np.ndarray, trans: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Camera-to-world poses moved by the similarity ``x -> s R x + t``.

    Args:
        poses: (N, 4, 4) camera-to-world poses (NaN poses stay NaN).
        rot: (3, 3) rotation R.
        trans: (3,) translation t.
        scale: scale s.

    Returns:
        (N, 4, 4) float64: rotations R @ R_i, camera centres s R c_i + t.
    """
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = rot @ out[:, :3, :3]
    out[:, :3, 3] = scale * out[:, :3, 3] @ np.asarray(rot).T + trans
    return out


def polyline_length(points) -> float:
    """Length of the polyline through points in order.

    Args:
        points: (N, 3) points.

    Returns:
        The summed segment length; 0 for fewer than two points.
    """
    points = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def umeyama(src, dst, with_scale: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Args:
        src: (N, 3) points.
        dst: (N, 3) corresponding points.
        with_scale: estimate s; False: s = 1.

    Returns:
        R (3, 3) (a rotation, det +1), t (3,), s (1.0 when not `with_scale`).

    Raises:
        ReconInputError: the point sets are not both (N, 3), N < 2, or the source points
            all coincide.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ReconInputError(f"umeyama needs two (N, 3) point sets of equal shape, got {src.shape} and {dst.shape}")
    if len(src) < 2:
        raise ReconInputError(f"umeyama needs at least 2 points, got {len(src)}")
    mu_src, mu_dst = src.mean(0), dst.mean(0)
    xs, xd = src - mu_src, dst - mu_dst
    var_src = (xs**2).sum() / len(src)
    if var_src <= 1e-18:
        raise ReconInputError("umeyama: source points are all the same (no motion to align)")
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    # Flip the weakest axis when needed so the result is a rotation, not a reflection.
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    scale = float((d * sign).sum() / var_src) if with_scale else 1.0
    trans = mu_dst - scale * rot @ mu_src
    return rot, trans, scale
