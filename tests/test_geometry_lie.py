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


def test_a_frame_between_keyframes_lies_on_their_geodesic():
    """interpolated_pose: a quarter of the way from keyframe 4 to keyframe 8 (a turn of 40
    degrees about z and 2 m along x), the keyframe itself on a keyframe, the nearest keyframe
    before the first and after the last."""
    import numpy as np

    a, b = np.eye(4), np.eye(4)
    angle = np.radians(40.0)
    b[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    b[:3, 3] = [2.0, 0.0, 0.0]
    kf_frames, T_kf = np.array([4, 8]), np.stack([a, b])
    quarter = lie.interpolated_pose(5, kf_frames, T_kf)
    assert np.isclose(np.degrees(np.arctan2(quarter[1, 0], quarter[0, 0])), 10.0)
    assert np.allclose(lie.interpolated_pose(8, kf_frames, T_kf), b)
    assert np.allclose(lie.interpolated_pose(0, kf_frames, T_kf), a)
    assert np.allclose(lie.interpolated_pose(12, kf_frames, T_kf), b)
