"""SE(3) / SO(3) helpers for the pose front end: exponential map, logarithm, inverse, adjoint.

This module owns the tangent-space convention shared by the bundle adjustment, the
motion-only alignment and their Jacobians: a tangent vector is ``xi = (v, w)`` (translation
first), shape (..., 6); poses are **updated on the left**, ``T <- exp(xi) @ T``, which for
the front end's world-to-camera poses is a perturbation in the camera frame (as DROID-SLAM's
``SE3.retr``); ``adjoint(T)`` satisfies ``T exp(xi) T^-1 = exp(adjoint(T) @ xi)``.
Everything is batched torch over leading dimensions, in closed form; small angles use Taylor
expansions so that float64 stays accurate near the identity.
"""

from __future__ import annotations

import numpy as np
import torch

# Below this angle (rad) the closed forms lose digits; use Taylor series instead.
_SMALL_ANGLE = 1e-4


def skew(w: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices of vectors: skew(a) @ b == a x b.

    Args:
        w: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    zero = torch.zeros_like(w[..., 0])
    wx, wy, wz = w.unbind(-1)
    return torch.stack(
        [
            torch.stack([zero, -wz, wy], -1),
            torch.stack([wz, zero, -wx], -1),
            torch.stack([-wy, wx, zero], -1),
        ],
        -2,
    )


def _so3_coefficients(theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """a = sin t / t, b = (1 - cos t) / t^2, c = (t - sin t) / t^3 with Taylor series at small t."""
    small = theta < _SMALL_ANGLE
    t = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / (t * t))
    c = torch.where(small, 1.0 / 6.0 - t2 / 120.0, (t - torch.sin(t)) / (t * t * t))
    return a, b, c


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of axis-angle vectors (Rodrigues).

    Args:
        w: (..., 3) axis-angle vectors, angle in radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    theta = w.norm(dim=-1)
    a, b, _ = _so3_coefficients(theta)
    k = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors of rotation matrices, angle in [0, pi].

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) axis-angle vectors, angle in radians.
    """
    cos = ((rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    vee = torch.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]], -1
    )
    sin = torch.sin(theta)
    small = theta < _SMALL_ANGLE
    scale = torch.where(small, 0.5 + theta * theta / 12.0,
                        theta / (2.0 * torch.where(small, torch.ones_like(sin), sin)))
    w = vee * scale[..., None]
    # Near pi, sin -> 0 and the antisymmetric part vanishes: take the axis from R + I.
    near_pi = theta > np.pi - 1e-3
    if near_pi.any():
        sym = (rot[near_pi] + torch.eye(3, dtype=rot.dtype, device=rot.device)) / 2.0
        col = sym.diagonal(dim1=-2, dim2=-1).argmax(-1)
        axis = sym[torch.arange(len(col)), :, col]
        axis = axis / axis.norm(dim=-1, keepdim=True)
        # Keep the sign consistent with the (small) antisymmetric part.
        sign = torch.where((axis * vee[near_pi]).sum(-1) < 0, -1.0, 1.0).to(rot.dtype)
        w[near_pi] = axis * (theta[near_pi] * sign)[..., None]
    return w


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """4x4 rigid transforms of tangent vectors xi = (v, w).

    Args:
        xi: (..., 6) tangent vectors, translation part v first, then rotation w.

    Returns:
        (..., 4, 4) rigid transforms.
    """
    v, w = xi[..., :3], xi[..., 3:]
    theta = w.norm(dim=-1)
    a, b, c = _so3_coefficients(theta)
    k = skew(w)
    kk = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(k.shape)
    rot = eye + a[..., None, None] * k + b[..., None, None] * kk
    jac = eye + b[..., None, None] * k + c[..., None, None] * kk
    out = torch.zeros(xi.shape[:-1] + (4, 4), dtype=xi.dtype, device=xi.device)
    out[..., :3, :3] = rot
    out[..., :3, 3] = (jac @ v[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """Tangent vectors xi = (v, w) of 4x4 rigid transforms.

    Args:
        T: (..., 4, 4) rigid transforms.

    Returns:
        (..., 6) tangent vectors, translation part v first, then rotation w.
    """
    w = so3_log(T[..., :3, :3])
    theta = w.norm(dim=-1)
    k = skew(w)
    small = theta < _SMALL_ANGLE
    t = torch.where(small, torch.ones_like(theta), theta)
    # V^-1 = I - K/2 + (1/t^2)(1 - (t sin t) / (2 (1 - cos t))) K^2
    coef = torch.where(
        small, 1.0 / 12.0 + theta * theta / 720.0, (1.0 - t * torch.sin(t) / (2.0 * (1.0 - torch.cos(t)))) / (t * t)
    )
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand(k.shape)
    vinv = eye - 0.5 * k + coef[..., None, None] * (k @ k)
    v = (vinv @ T[..., :3, 3:4])[..., 0]
    return torch.cat([v, w], -1)


def inv(T: torch.Tensor) -> torch.Tensor:
    """Inverses of rigid transforms, without a general matrix inverse.

    Args:
        T: (..., 4, 4) rigid transforms.

    Returns:
        (..., 4, 4) inverses [R^T, -R^T t].
    """
    rot_t = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: torch.Tensor) -> torch.Tensor:
    """Adjoint matrices of rigid transforms for xi = (v, w).

    ``Ad(T) = [[R, [t]x R], [0, R]]``, so ``T exp(xi) T^-1 = exp(Ad(T) xi)``.

    Args:
        T: (..., 4, 4) rigid transforms.

    Returns:
        (..., 6, 6) adjoint matrices.
    """
    rot, t = T[..., :3, :3], T[..., :3, 3]
    out = torch.zeros(T.shape[:-2] + (6, 6), dtype=T.dtype, device=T.device)
    out[..., :3, :3] = rot
    out[..., :3, 3:] = skew(t) @ rot
    out[..., 3:, 3:] = rot
    return out


def relative(T_cw: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor) -> torch.Tensor:
    """Transforms from camera ii to camera jj, ``T_j @ T_i^-1``, of world-to-camera poses.

    Args:
        T_cw: (K, 4, 4) world-to-camera poses.
        ii: (E,) indices of the first cameras.
        jj: (E,) indices of the second cameras.

    Returns:
        (E, 4, 4) camera-ii-to-camera-jj transforms.
    """
    return T_cw[jj] @ inv(T_cw[ii])


def interpolate(T_a: np.ndarray, T_b: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Poses on the geodesic from T_a to T_b.

    Interpolates ``T_a exp(alpha log(T_a^-1 T_b))`` (float64 numpy in, numpy out); the frame
    convention does not matter as long as both ends share it.

    Args:
        T_a: (M, 4, 4) start poses.
        T_b: (M, 4, 4) end poses.
        alpha: (M,) fractions, 0 at T_a and 1 at T_b.

    Returns:
        (M, 4, 4) float64 poses.
    """
    a = torch.as_tensor(np.asarray(T_a, dtype=np.float64))
    b = torch.as_tensor(np.asarray(T_b, dtype=np.float64))
    alpha = torch.as_tensor(np.asarray(alpha, dtype=np.float64))
    delta = se3_log(inv(a) @ b)
    return (a @ se3_exp(delta * alpha[..., None])).numpy()


def interpolated_pose(i: int, kf_frames: np.ndarray, T_kf: np.ndarray) -> np.ndarray:
    """Pose of frame i on the geodesic between the keyframes before and after it.

    Args:
        i: the frame's index in the sequence.
        kf_frames: (K,) sorted sequence indices of the keyframes.
        T_kf: (K, 4, 4) float64 poses of the keyframes (either convention, as ``interpolate``).

    Returns:
        (4, 4) float64 pose; the nearest keyframe's pose past either end of the keyframes.
    """
    nxt = int(np.searchsorted(kf_frames, i))
    if nxt == 0 or nxt == len(kf_frames):
        return np.array(T_kf[min(nxt, len(kf_frames) - 1)], dtype=np.float64)
    a = (i - kf_frames[nxt - 1]) / max(kf_frames[nxt] - kf_frames[nxt - 1], 1)
    return interpolate(T_kf[nxt - 1][None], T_kf[nxt][None], np.array([a]))[0]
