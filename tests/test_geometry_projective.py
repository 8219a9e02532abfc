"""Projective geometry of the pose estimator (recon.geometry.projective): projection and ray
Jacobians, and the radial lens (undistort / distort and its k1 derivative), all against
finite differences."""

from __future__ import annotations

import torch

from recon.geometry import lie
from recon.geometry import projective as pj


def test_projection_jacobians_match_finite_differences():
    g = torch.Generator().manual_seed(1)
    intr = torch.tensor([80.0, 82.0, 39.5, 29.5], dtype=torch.float64)
    Tij = lie.se3_exp(torch.randn(3, 6, generator=g, dtype=torch.float64) * 0.1)
    uv = torch.rand(3, 50, 2, generator=g, dtype=torch.float64) * torch.tensor([80.0, 60.0])
    disp = 0.2 + torch.rand(3, 50, generator=g, dtype=torch.float64)
    X = pj.backproject(uv, disp, intr)
    proj, valid, Jj, Jz = pj.reproject_with_jacobians(Tij, X.transpose(1, 2), intr)
    proj, Jj, Jz = proj.transpose(1, 2), Jj.permute(0, 3, 1, 2), Jz.transpose(1, 2)  # planes -> per pixel
    assert valid.all()
    eps = 1e-6
    for k in range(6):
        step = torch.zeros(6, dtype=torch.float64)
        step[k] = eps
        moved, _ = pj.project(pj.transform(lie.se3_exp(step)[None] @ Tij, X), intr)
        assert torch.allclose((moved - proj) / eps, Jj[..., k], atol=1e-3)
    Xd = pj.backproject(uv, disp + eps, intr)
    moved, _ = pj.project(pj.transform(Tij, Xd), intr)
    assert torch.allclose((moved - proj) / eps, Jz, atol=1e-3)


def test_undistort_inverts_the_lens_and_its_derivatives_match_finite_differences():
    intr = torch.tensor([80.0, 82.0, 39.5, 29.5], dtype=torch.float64)
    uv = pj.pixel_grid(60, 80)
    eps = 1e-6
    for k1 in (-0.15, 0.0, 0.1):
        pinhole, d_k1 = pj.undistort(uv, intr, k1)
        assert torch.allclose(pj.distort(pinhole, intr, k1), uv, atol=1e-6)
        moved = pj.undistort(uv, intr, k1 + eps)[0]
        assert torch.allclose((moved - pinhole) / eps, d_k1, atol=1e-4)
    # Moving the source pixels moves their projections by ray_jacobian (depth held).
    g = torch.Generator().manual_seed(3)
    Tij = lie.se3_exp(torch.randn(2, 6, generator=g, dtype=torch.float64) * 0.1)
    src = torch.rand(50, 2, generator=g, dtype=torch.float64) * torch.tensor([80.0, 60.0])
    dray = torch.randn(50, 2, generator=g, dtype=torch.float64)
    disp = 0.2 + torch.rand(2, 50, generator=g, dtype=torch.float64)
    X = pj.backproject(src, disp, intr)
    proj, _ = pj.project(pj.transform(Tij, X), intr)
    moved, _ = pj.project(pj.transform(Tij, pj.backproject(src + eps * dray, disp, intr)), intr)
    Jray = pj.ray_jacobian(Tij, pj.transform(Tij, X).transpose(1, 2), intr, dray.T)
    assert torch.allclose((moved - proj) / eps, Jray.transpose(1, 2), atol=1e-4)
