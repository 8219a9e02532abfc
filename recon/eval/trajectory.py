"""Trajectory metrics: alignment (Umeyama), absolute trajectory error, relative pose error,
metric scale error and path length.

Owns the comparison of an estimated camera trajectory with ground truth. Trajectories are
camera-to-world poses (N, 4, 4) (OpenCV axes, metres) or camera positions (N, 3), matched
frame by frame (associate timestamps first, e.g. with
``recon.poses.formats.associate_timestamps``). Frames whose pose is non-finite in either
trajectory (invalid poses are NaN) are left out. Everything is vectorised numpy.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import apply_similarity, polyline_length, umeyama

AlignMode = Literal["sim3", "se3", "none"]


def _positions(traj) -> np.ndarray:
    """Camera centres (N, 3) of poses (N, 4, 4) or positions (N, 3)."""
    traj = np.asarray(traj, dtype=np.float64)
    if traj.ndim == 3 and traj.shape[1:] == (4, 4):
        return traj[:, :3, 3]
    if traj.ndim == 2 and traj.shape[1] == 3:
        return traj
    raise ReconInputError(f"trajectory must be poses (N, 4, 4) or positions (N, 3), got shape {traj.shape}")


def _as_poses(traj) -> np.ndarray:
    """Poses (N, 4, 4) float64; positions (N, 3) get identity rotations."""
    traj = np.asarray(traj, dtype=np.float64)
    if traj.ndim == 2 and traj.shape[1] == 3:
        poses = np.tile(np.eye(4), (len(traj), 1, 1))
        poses[:, :3, 3] = traj
        return poses
    if traj.ndim == 3 and traj.shape[1:] == (4, 4):
        return traj
    raise ReconInputError(f"trajectory must be poses (N, 4, 4) or positions (N, 3), got shape {traj.shape}")


def _matched(est, gt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """est, gt as poses (N, 4, 4) and the mask (N,) of frames finite in both."""
    est, gt = _as_poses(est), _as_poses(gt)
    if len(est) != len(gt):
        raise ReconInputError(f"trajectories differ in length: estimate has {len(est)} poses, ground truth {len(gt)}")
    valid = np.isfinite(est).all(axis=(1, 2)) & np.isfinite(gt).all(axis=(1, 2))
    return est, gt, valid


def align(est, gt, mode: AlignMode = "sim3") -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) taking est camera centres onto gt's; identity for mode "none"."""
    est_p, gt_p = _positions(est), _positions(gt)
    if mode == "none":
        return np.eye(3), np.zeros(3), 1.0
    if mode not in ("sim3", "se3"):
        raise ValueError(f"mode must be 'sim3', 'se3' or 'none', got {mode!r}")
    return umeyama(est_p, gt_p, with_scale=mode == "sim3")


# The least share of the ground-truth camera centres' spread that the Sim(3) fit must
# explain for its scale to be used on a mesh. Umeyama's scale is the centres' covariance over
# the estimate's variance, so it shrinks towards 0 as the fit explains less.
# why: docs/decisions.md#the-scale-recon-eval-puts-on-a-mesh
MIN_SCALE_EXPLAINED = 0.5


def explained_share(est, gt, rot: np.ndarray, trans: np.ndarray, scale: float) -> float:
    """1 - sum |s R c_est + t - c_gt|^2 / sum |c_gt - mean c_gt|^2 over the camera centres
    (R^2 of the fit; 0 when the ground truth does not move)."""
    est_p, gt_p = _positions(est), _positions(gt)
    spread = float(((gt_p - gt_p.mean(0)) ** 2).sum())
    if spread <= 0.0:
        return 0.0
    return 1.0 - float(((scale * est_p @ rot.T + trans - gt_p) ** 2).sum()) / spread


def pose_alignment(est_poses, gt_poses, mode: AlignMode = "sim3") -> dict:
    """x -> s R x + t taking the estimate's world onto the ground truth's, from whole poses,
    for moving geometry (a mesh) rather than scoring a trajectory.

    R is the rotation nearest to sum_i R_gt_i R_est_i^T (the camera orientations), s the
    Sim(3) Umeyama scale of the centres (1 for "se3"), t the mean of c_gt_i - s R c_est_i.
    Umeyama on camera centres alone (:func:`ate_rmse`) leaves the rotation about a nearly
    straight path undetermined, and everything for a camera that mostly rotates (TUM
    fr1/rpy): harmless for ATE, degrees off for a mesh 2-3 m away. A scale the centres do
    not determine (the fit explains less than MIN_SCALE_EXPLAINED of their spread) is not
    used: s = 1.
    Returns {"scale", "rotation" (3, 3), "translation" (3,), "scale_from", "explained",
    "fitted_scale"}: scale_from "trajectory" (the Sim(3) scale), "undetermined" (scale 1
    because the fit explains too little), "se3" or "none"; explained the fit's R^2 over the
    centres and fitted_scale its scale (None unless mode is "sim3").
    """
    est, gt, valid = _matched(est_poses, gt_poses)
    est, gt = est[valid], gt[valid]
    fit = {"explained": None, "fitted_scale": None}
    if mode == "none":
        return {"scale": 1.0, "rotation": np.eye(3), "translation": np.zeros(3), "scale_from": "none", **fit}
    scale, scale_from = 1.0, "se3"
    if mode == "sim3":
        rot_c, trans_c, fitted = align(est, gt, "sim3")
        fit = {"explained": explained_share(est, gt, rot_c, trans_c, fitted), "fitted_scale": float(fitted)}
        scale, scale_from = ((fitted, "trajectory") if fit["explained"] >= MIN_SCALE_EXPLAINED
                             else (1.0, "undetermined"))
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", gt[:, :3, :3], est[:, :3, :3]))
    rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    trans = (gt[:, :3, 3] - scale * est[:, :3, 3] @ rot.T).mean(0)
    return {"scale": float(scale), "rotation": rot, "translation": trans, "scale_from": scale_from, **fit}


def move_points(points: np.ndarray, alignment: dict | None) -> np.ndarray:
    """Points (M, 3) moved by x -> s R x + t (a :func:`pose_alignment` result); None: unchanged."""
    points = np.asarray(points)
    if alignment is None:
        return points
    return alignment["scale"] * points @ alignment["rotation"].T + alignment["translation"]


def ate_rmse(est_poses, gt_poses, mode: AlignMode = "sim3") -> dict:
    """Absolute trajectory error of camera centres after aligning est to gt.

    est_poses, gt_poses: (N, 4, 4) camera-to-world (or (N, 3) positions), frame-matched.
    mode: "sim3" (rotation, translation, scale: for up-to-scale estimates), "se3" (rigid:
    also penalises a wrong metric scale) or "none" (same world frame already).
    Returns rmse, mean, median, max, std (metres), scale s, rotation R (3, 3), translation
    t (3,), errors (N,) (NaN for left-out frames), aligned (N, 4, 4) est poses in gt's
    frame, and n (frames used).
    """
    est, gt, valid = _matched(est_poses, gt_poses)
    rot, trans, scale = align(est[valid], gt[valid], mode)
    aligned = apply_similarity(est, rot, trans, scale)
    errors = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    errors[~valid] = np.nan
    e = errors[valid]
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "max": float(e.max()),
        "std": float(e.std()),
        "scale": scale,
        "rotation": rot,
        "translation": trans,
        "errors": errors,
        "aligned": aligned,
        "n": int(valid.sum()),
    }


def _rotation_angles(rotations: np.ndarray) -> np.ndarray:
    """Rotation angles (N,) radians of (nearly) rotation matrices (N, 3, 3).

    Uses atan2(|skew part|, trace part), which stays accurate for small angles, after
    projecting onto SO(3): ground truth stored with a few digits (7-Scenes: det 0.99986)
    would otherwise read as ~1 degree of rotation through arccos((trace - 1) / 2).
    """
    u, _, vt = np.linalg.svd(rotations)
    fix = np.ones(rotations.shape[:-1])
    fix[..., -1] = np.sign(np.linalg.det(u @ vt))
    rot = (u * fix[..., None, :]) @ vt
    skew = np.stack([rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]], axis=1)
    return np.arctan2(np.linalg.norm(skew, axis=1) / 2.0, (np.trace(rot, axis1=1, axis2=2) - 1.0) / 2.0)


def _relative(poses: np.ndarray, delta: int) -> np.ndarray:
    """Motions (N - delta, 4, 4) ``T_i^-1 T_{i+delta}`` (camera i+delta in camera i's frame)."""
    a, b = poses[:-delta], poses[delta:]
    rot_t = np.swapaxes(a[:, :3, :3], 1, 2)
    out = np.tile(np.eye(4), (len(a), 1, 1))
    out[:, :3, :3] = rot_t @ b[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", rot_t, b[:, :3, 3] - a[:, :3, 3])
    return out


def rpe(est, gt, delta: int = 1, scale: float = 1.0) -> dict:
    """Relative pose error over frame pairs (i, i + delta) (Sturm et al. 2012).

    est, gt: (N, 4, 4) camera-to-world, frame-matched. The error of a pair is
    ``E = (gt_i^-1 gt_j)^-1 (est_i^-1 est_j)``; its translation norm (metres) and rotation
    angle (degrees) are reported. `scale` multiplies est's translations first (e.g. the
    Sim(3) scale from :func:`ate_rmse` for up-to-scale estimates).
    Returns trans_rmse, trans_mean, trans_median, rot_rmse_deg, rot_mean_deg,
    rot_median_deg, trans_errors (M,), rot_errors_deg (M,) and n (pairs used).
    """
    est, gt, valid = _matched(est, gt)
    if delta < 1 or delta >= len(est):
        raise ReconInputError(f"rpe: delta must be in [1, {len(est) - 1}] for {len(est)} poses, got {delta}")
    est = est.copy()
    est[:, :3, 3] *= scale
    rel_est, rel_gt = _relative(est, delta), _relative(gt, delta)
    pair_ok = valid[:-delta] & valid[delta:]
    if not pair_ok.any():
        raise ReconInputError(f"rpe: no frame pair {delta} apart has valid poses in both trajectories")
    rel_est, rel_gt = rel_est[pair_ok], rel_gt[pair_ok]
    # (gt_rel)^-1 @ est_rel, written out for rigid transforms.
    rot_gt_t = np.swapaxes(rel_gt[:, :3, :3], 1, 2)
    err_rot = rot_gt_t @ rel_est[:, :3, :3]
    err_trans = np.einsum("nij,nj->ni", rot_gt_t, rel_est[:, :3, 3] - rel_gt[:, :3, 3])
    t_err = np.linalg.norm(err_trans, axis=1)
    r_err = np.degrees(_rotation_angles(err_rot))
    return {
        "trans_rmse": float(np.sqrt(np.mean(t_err**2))),
        "trans_mean": float(t_err.mean()),
        "trans_median": float(np.median(t_err)),
        "rot_rmse_deg": float(np.sqrt(np.mean(r_err**2))),
        "rot_mean_deg": float(r_err.mean()),
        "rot_median_deg": float(np.median(r_err)),
        "trans_errors": t_err,
        "rot_errors_deg": r_err,
        "n": int(pair_ok.sum()),
    }


def rotation_error(est, gt) -> dict:
    """Orientation error of each camera after the one rotation that best takes est's
    orientations onto gt's (the orientation fit of :func:`pose_alignment`): the angle of
    R_gt_i^T R R_est_i. For a camera that turns on the spot this is the score (its centres
    say little); for any camera it is independent of the trajectory's scale.

    est, gt: (N, 4, 4) camera-to-world, frame-matched. Returns median_deg, rmse_deg, max_deg,
    errors_deg (N,) (NaN for left-out frames) and n.
    """
    est, gt, valid = _matched(est, gt)
    rot = pose_alignment(est, gt, "se3")["rotation"]
    aligned = rot @ est[:, :3, :3]
    errors = np.full(len(est), np.nan)
    errors[valid] = np.degrees(_rotation_angles(np.swapaxes(gt[valid, :3, :3], 1, 2) @ aligned[valid]))
    e = errors[valid]
    return {"median_deg": float(np.median(e)), "rmse_deg": float(np.sqrt(np.mean(e ** 2))),
            "max_deg": float(e.max()), "errors_deg": errors, "n": int(valid.sum())}


def scale_error(est, gt) -> float:
    """|s - 1| for the Sim(3) scale s that best maps est's camera centres onto gt's.

    0 means est already has metric scale; an est trajectory that is 10 % too small gives
    s = 1 / 0.9 and an error of about 0.11. est, gt: (N, 4, 4) poses or (N, 3) positions.
    """
    est, gt, valid = _matched(est, gt)
    _, _, s = umeyama(est[valid, :3, 3], gt[valid, :3, 3], with_scale=True)
    return abs(s - 1.0)


def path_length(traj) -> float:
    """Length (metres) of the polyline through the camera centres, skipping non-finite ones.

    traj: (N, 4, 4) poses or (N, 3) positions.
    """
    pos = _positions(traj)
    return polyline_length(pos[np.isfinite(pos).all(axis=1)])
