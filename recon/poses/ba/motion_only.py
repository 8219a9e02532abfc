"""Motion-only alignment: frames tracked against fixed keyframes.

Gauss-Newton on one world-to-camera pose per frame, batched over frames, with the
keyframes' poses and BA inverse depth held fixed: the dense BA's residual
(:mod:`recon.poses.ba.bundle`: flow target minus reprojection, the recorded pixels undistorted
with k1, Huber-weighted) without the depth block, as DROID-SLAM's motion-only BA initialises
a new frame. Used by the tracker, the filler and the focal search.

Shapes: M frames, L measurements (one keyframe seen by one frame each), BA grid (H, W).
"""

from __future__ import annotations

import torch

from recon.geometry import lie
from recon.geometry import projective as pj
from recon.poses.ba.bundle import Edges
from recon.poses.ba.normal_equations import huber_weights, pixel_sums, whitened


def align_frames(
    T_init: torch.Tensor,
    T_kf: torch.Tensor,
    disp_kf: torch.Tensor,
    intr: torch.Tensor,
    frame: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    iters: int = 8,
    huber: float = 1.0,
    k1: float = 0.0,
    whiten: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Motion-only Gauss-Newton: world-to-camera poses of M frames against fixed keyframes.

    T_init: (M, 4, 4) initial poses of the frames; for each of L measurements:
    T_kf (L, 4, 4) the keyframe's pose, disp_kf (L, H, W) its inverse depth, frame (L,)
    which of the M frames it observes, target (L, H, W, 2) where the keyframe's pixels
    land in that frame (recorded pixels), weight (L, H, W); k1 the lens' radial term;
    whiten (L, H, W, 2, 2) the keyframe's residual factors (``ba.Edges.whiten``) or None.
    Returns poses (M, 4, 4), the weighted RMS
    residual (M,) in BA pixels and the fraction (M,) of confidence weight within `huber`.
    """
    M = T_init.shape[0]
    L = T_kf.shape[0]
    height, width = disp_kf.shape[-2:]
    P = height * width
    pinhole = Edges(frame, frame, target, weight).undistorted(intr, k1)
    Lw = None if whiten is None else whiten.reshape(L, P, 2, 2).to(T_init.dtype)
    uv = pinhole.source_pixels(T_init.dtype).reshape(1, P, 2)
    Xk = pj.backproject(uv, disp_kf.reshape(L, P), intr)
    Xk_planes = Xk.transpose(1, 2)
    tgt = pinhole.target.reshape(L, P, 2)
    tgt_planes = tgt.transpose(1, 2)
    w0 = weight.reshape(L, P)
    T = T_init.clone()
    on = {"dtype": T.dtype, "device": T.device}
    eye = torch.eye(6, **on)
    for _ in range(iters):
        Tkf_to_f = T[frame] @ lie.inv(T_kf)
        proj, valid, Jf, _ = pj.reproject_with_jacobians(Tkf_to_f, Xk_planes, intr)
        r, Jf = whitened(Lw, tgt_planes - proj, Jf)
        wgt = w0 * valid * huber_weights(torch.hypot(r[:, 0], r[:, 1]), huber)
        JtJ, Jtr = pixel_sums(Jf, wgt, r)
        H = torch.zeros(M, 6, 6, **on).index_add_(0, frame, JtJ)
        g = torch.zeros(M, 6, **on).index_add_(0, frame, Jtr)
        H = H + eye * (1e-4 * H.diagonal(dim1=1, dim2=2).mean(-1, keepdim=True)[..., None] + 1e-9)
        dx = torch.linalg.solve(H, g[..., None])[..., 0]
        T = lie.se3_exp(dx) @ T
        if float(dx.abs().max()) < 1e-7:
            break
    proj, valid = pj.project(pj.transform(T[frame] @ lie.inv(T_kf), Xk), intr)
    res = tgt - proj
    rn = (res if Lw is None else (Lw @ res[..., None])[..., 0]).norm(dim=-1)
    if Lw is not None:
        # A plain pixel's whitened residual is about 0 whatever its flow: the statistics
        # count each pixel by how much its texture measures (trace(L^T L) / 2, 1 on texture).
        w0 = w0 * 0.5 * Lw.square().sum(dim=(-2, -1))
    wv = w0 * valid
    num = torch.zeros(M, **on).index_add_(0, frame, (wv * rn.clamp(max=10 * huber) ** 2).sum(1))
    den = torch.zeros(M, **on).index_add_(0, frame, wv.sum(1))
    inl = torch.zeros(M, **on).index_add_(0, frame, (wv * (rn < huber)).sum(1))
    tot = torch.zeros(M, **on).index_add_(0, frame, w0.sum(1))
    return T, (num / den.clamp(min=1e-9)).sqrt(), inl / tot.clamp(min=1e-9)
