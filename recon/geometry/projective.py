"""Pinhole projective geometry with inverse depth, and its Jacobians, for dense BA.

The residual model of the front end (as DROID-SLAM's ``geom/projective_ops``): a pixel
(u, v) of keyframe i with inverse depth d is ``X_i = ((u - cx) / fx, (v - cy) / fy, 1, d)``,
``X_j = T_ij X_i`` with ``T_ij = T_j T_i^-1`` of world-to-camera poses, projected to
``(fx X/Z + cx, fy Y/Z + cy)``. The lens is OpenCV's k1 alone (x seen at ``x (1 + k1 |x|^2)``);
:func:`undistort` moves measured pixels into the pinhole image. Jacobians follow
:mod:`recon.geometry.lie` (tangent ``(v, w)``, left updates). Intrinsics are a (4,) tensor
``(fx, fy, cx, cy)`` in pixels of the grid being projected, pixel centres at integers.
"""

from __future__ import annotations

import torch

from medea_core import geometry
from recon.geometry import lie
from recon.geometry.camera import scale_intrinsics  # noqa: F401  (front-end modules call pj.scale_intrinsics)

# Points closer than this (metres, in the target camera) count as behind it: their
# projection is numerically meaningless.
MIN_DEPTH = 0.05


def pixel_grid(height: int, width: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Pixel coordinates (u, v) of every pixel centre, in float64 unless told otherwise.

    medea_core's grid; the front end's BA works in double precision.

    Args:
        height: image height H in pixels.
        width: image width W in pixels.
        dtype: dtype of the result.
        device: device of the result; None: the default device.

    Returns:
        (H, W, 2) whose entry [v, u] is (u, v).
    """
    return geometry.pixel_grid(height, width, dtype=dtype, device=device)


def backproject(uv: torch.Tensor, disp: torch.Tensor, intr: torch.Tensor) -> torch.Tensor:
    """Homogeneous points (x, y, 1, d) of pixels with inverse depth.

    Args:
        uv: (..., 2) pixel coordinates (u, v).
        disp: (...) inverse depth d in 1/metres (broadcast against uv's leading dimensions).
        intr: (4,) fx, fy, cx, cy in pixels.

    Returns:
        (..., 4) homogeneous points ((u - cx) / fx, (v - cy) / fy, 1, d).
    """
    fx, fy, cx, cy = intr.unbind(-1)
    x = (uv[..., 0] - cx) / fx
    y = (uv[..., 1] - cy) / fy
    x, y, disp = torch.broadcast_tensors(x, y, disp)
    return torch.stack([x, y, torch.ones_like(x), disp], -1)


def undistort(uv: torch.Tensor, intr: torch.Tensor, k1: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole pixels of recorded pixels, and their derivative with respect to k1.

    Undistorting is a 1-D Newton solve per pixel for the factor s = |x_u| / |x_d| (x the
    normalised coordinates): s + k1 |x_d|^2 s^3 = 1. It converges quadratically from s = 1:
    three steps leave a relative error ~ (k1 |x|^2)^8, below float32 precision for
    |k1| |x|^2 < 0.1 (|k1| = 0.2 at the corners of a 60 degree lens).

    Args:
        uv: (..., 2) recorded pixel coordinates.
        intr: (4,) fx, fy, cx, cy in pixels.
        k1: radial distortion term on normalised coordinates; 0 = pinhole.

    Returns:
        Pinhole pixels (..., 2) and d(pinhole pixels)/d(k1) (..., 2).
    """
    fx, fy, cx, cy = intr.unbind(-1)
    x = (uv[..., 0] - cx) / fx
    y = (uv[..., 1] - cy) / fy
    rho = x * x + y * y
    s = torch.ones_like(rho)
    for _ in range(3):
        s = s - (s + k1 * rho * s**3 - 1.0) / (1.0 + 3.0 * k1 * rho * s * s)
    ds = -rho * s**3 / (1.0 + 3.0 * k1 * rho * s * s)
    pinhole = torch.stack([x * s * fx + cx, y * s * fy + cy], -1)
    return pinhole, torch.stack([x * ds * fx, y * ds * fy], -1)


def distort(uv: torch.Tensor, intr: torch.Tensor, k1: float) -> torch.Tensor:
    """Recorded pixels of pinhole pixels: the inverse of :func:`undistort`.

    Args:
        uv: (..., 2) pinhole pixel coordinates.
        intr: (4,) fx, fy, cx, cy in pixels.
        k1: radial distortion term; a normalised point x is recorded at x (1 + k1 |x|^2).

    Returns:
        (..., 2) recorded pixel coordinates.
    """
    fx, fy, cx, cy = intr.unbind(-1)
    x = (uv[..., 0] - cx) / fx
    y = (uv[..., 1] - cy) / fy
    f = 1.0 + k1 * (x * x + y * y)
    return torch.stack([x * f * fx + cx, y * f * fy + cy], -1)


def transform(T: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Homogeneous points moved by one transform per edge.

    Args:
        T: (E, 4, 4) transforms.
        X: (E, ..., 4) homogeneous points.

    Returns:
        (E, ..., 4) points T X.
    """
    shape = X.shape
    Xf = X.reshape(shape[0], -1, 4)
    return (Xf @ T.transpose(-1, -2)).reshape(shape)


def _in_front(Z: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """Validity of homogeneous points with depth coordinate Z and inverse depth W: metric
    depth Z / W > MIN_DEPTH for points with positive W, and Z > 0."""
    return (Z > MIN_DEPTH * W.clamp(min=0.0)) & (Z > 1e-6)


def project(Xj: torch.Tensor, intr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of homogeneous points, and whether they are in front of the camera.

    Validity compares Z with MIN_DEPTH * W, i.e. metric depth > MIN_DEPTH for points with
    positive inverse depth W.

    Args:
        Xj: (..., 4) homogeneous points (X, Y, Z, W) in the camera.
        intr: (4,) fx, fy, cx, cy in pixels.

    Returns:
        uv (..., 2) pixel coordinates (projected with Z = 1 where invalid) and valid (...) bool.
    """
    fx, fy, cx, cy = intr.unbind(-1)
    X, Y, Z, W = Xj.unbind(-1)
    valid = _in_front(Z, W)
    Zs = torch.where(valid, Z, torch.ones_like(Z))
    return torch.stack([fx * X / Zs + cx, fy * Y / Zs + cy], -1), valid


def reproject(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
    uv: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the pixels of keyframes ii land in keyframes jj.

    Args:
        T_cw: (K, 4, 4) world-to-camera poses.
        disps: (K, H, W) inverse depth in 1/metres.
        intr: (4,) fx, fy, cx, cy in pixels of the disps' grid.
        ii: (E,) source keyframe of each edge.
        jj: (E,) target keyframe of each edge.
        uv: (H, W, 2) or (H * W, 2) pixel coordinates of the disps' pixels (None: the grid).

    Returns:
        Coordinates (E, H, W, 2) in jj's pixels and validity (E, H, W) bool.
    """
    height, width = disps.shape[-2:]
    if uv is None:
        uv = pixel_grid(height, width, dtype=disps.dtype, device=disps.device)
    uv = uv.reshape(height, width, 2).to(disps.dtype)
    Xi = backproject(uv[None], disps[ii], intr)
    Xj = transform(lie.relative(T_cw, ii, jj), Xi)
    return project(Xj, intr)


# The Jacobian functions below work on *planes*: pixels last, (E, 4, P) points, (E, 2, 6, P)
# Jacobians. The BA sums J^T W J over pixels; with pixels contiguous that is a plain
# matrix product, 4x faster on CPU than over (E, P, 2, 6) (and the per-plane arithmetic
# runs on contiguous memory too).


def reproject_with_jacobians(
    Tij: torch.Tensor, Xi: torch.Tensor, intr: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Projections of Xi into camera j and their Jacobians with respect to pose j and depth.

    The Jacobian for pose i is ``Ji = -Jj @ adjoint(Tij)`` (a left update of T_i reaches
    T_ij as ``exp(-Ad(T_ij) xi_i)``); callers apply it per edge to the summed normal
    equations instead of per pixel, which is what keeps dense BA cheap.

    Args:
        Tij: (E, 4, 4) camera i -> camera j transforms.
        Xi: (E, 4, P) homogeneous points (x, y, 1, d) as planes.
        intr: (4,) fx, fy, cx, cy in pixels.

    Returns:
        uv (E, 2, P), valid (E, P) bool, Jj (E, 2, 6, P) with respect to a left update of the
        world-to-camera pose T_j, and Jz (E, 2, P) with respect to d.
    """
    return project_with_jacobians(Tij, Tij @ Xi, intr)


def project_with_jacobians(
    Tij: torch.Tensor, Xj: torch.Tensor, intr: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`reproject_with_jacobians` for points already moved into camera j.

    For callers that need Xj = Tij Xi again, e.g. :func:`ray_jacobian`.

    Args:
        Tij: (E, 4, 4) camera i -> camera j transforms (their translation gives Jz).
        Xj: (E, 4, P) homogeneous points Tij Xi in camera j, as planes.
        intr: (4,) fx, fy, cx, cy in pixels.

    Returns:
        uv (E, 2, P), valid (E, P) bool, Jj (E, 2, 6, P) and Jz (E, 2, P), as
        :func:`reproject_with_jacobians`.
    """
    fx, fy, cx, cy = intr.unbind(-1)
    X, Y, Z, W = Xj.unbind(1)
    valid = _in_front(Z, W)
    iz = 1.0 / torch.where(valid, Z, torch.ones_like(Z))
    x, y, w = X * iz, Y * iz, W * iz
    uv = torch.stack([fx * x + cx, fy * y + cy], 1)
    # Closed form of d(u, v)/d xi for xi = (v, w) acting on homogeneous (X, Y, Z, W),
    # written into one buffer (stacking 12 planes costs more than the arithmetic).
    Jj = torch.empty(x.shape[0], 2, 6, x.shape[1], dtype=x.dtype, device=x.device)
    xy = x * y
    ju, jv = Jj[:, 0], Jj[:, 1]
    ju[:, 0] = w
    ju[:, 1] = 0.0
    jv[:, 0] = 0.0
    ju[:, 2] = -x * w
    ju[:, 3] = -xy
    ju[:, 4] = 1.0 + x * x
    ju[:, 5] = -y
    jv[:, 1] = w
    jv[:, 2] = -y * w
    jv[:, 3] = -(1.0 + y * y)
    jv[:, 4] = xy
    jv[:, 5] = x
    ju *= fx
    jv *= fy
    t = Tij[:, :3, 3, None]
    Jz = torch.stack([fx * (t[:, 0] - x * t[:, 2]) * iz, fy * (t[:, 1] - y * t[:, 2]) * iz], 1)
    return uv, valid, Jj, Jz


def ray_jacobian(Tij: torch.Tensor, Xj: torch.Tensor, intr: torch.Tensor, dray: torch.Tensor) -> torch.Tensor:
    """Derivative of the projections in camera j when the source pixels move.

    The pinhole source pixels move by dray per unit of some parameter (e.g. k1): the source
    ray (x, y, 1) moves by dray / (fx, fy), depth d held.

    Args:
        Tij: (E, 4, 4) camera i -> camera j transforms.
        Xj: (E, 4, P) homogeneous points Tij Xi in camera j, as planes.
        intr: (4,) fx, fy, cx, cy in pixels.
        dray: (2, P) motion of the source pixels in pixels per unit of the parameter.

    Returns:
        (E, 2, P) derivative of the projected pixels in camera j.
    """
    fx, fy, _, _ = intr.unbind(-1)
    X, Y, Z, _ = Xj.unbind(1)
    iz = 1.0 / torch.where(Z > 1e-6, Z, torch.ones_like(Z))
    R = Tij[:, :3, :3]
    dX, dY, dZ = (R[:, :, 0:1] * (dray[0] / fx) + R[:, :, 1:2] * (dray[1] / fy)).unbind(1)
    return torch.stack([fx * iz * (dX - X * iz * dZ), fy * iz * (dY - Y * iz * dZ)], 1)
