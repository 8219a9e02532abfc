"""SE(3) maps of recon.geometry.lie: exp/log round trip, inverse and adjoint."""

from __future__ import annotations

import torch

from recon.geometry import lie


def test_se3_exp_log_round_trip_and_adjoint():
    g = torch.Generator().manual_seed(0)
    xi = torch.randn(64, 6, generator=g, dtype=torch.float64) * torch.tensor([1, 1, 1, 0.8, 0.8, 0.8])
    xi[:4, 3:] *= 1e-6  # small-angle branch
    T = lie.se3_exp(xi)
    assert torch.allclose(lie.se3_log(T), xi, atol=1e-9)
    assert torch.allclose(lie.inv(T) @ T, torch.eye(4, dtype=torch.float64).expand(64, 4, 4), atol=1e-12)
    d = torch.randn(64, 6, generator=g, dtype=torch.float64) * 0.1
    assert torch.allclose(T @ lie.se3_exp(d) @ lie.inv(T), lie.se3_exp((lie.adjoint(T) @ d[..., None])[..., 0]),
                          atol=1e-10)
