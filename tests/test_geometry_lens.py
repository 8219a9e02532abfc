"""Resampling recorded frames into the pinhole image of an estimated lens (recon.geometry.lens)."""

from __future__ import annotations

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.geometry.lens import distort_images, largest_shift, undistort_features, undistort_images, worth_undistorting
from recon.synthetic import render_sequence


def test_undistorting_recorded_frames_gives_back_the_pinhole_images():
    seq = render_sequence(2, 320, 240, seed=0)
    k1 = -0.1
    recorded = distort_images(seq.rgb, seq.intrinsics, k1)
    restored = undistort_images(recorded, seq.intrinsics, k1)
    inner = (slice(None), slice(30, -30), slice(40, -40))
    before = np.abs(recorded[inner].astype(float) - seq.rgb[inner]).mean()
    after = np.abs(restored[inner].astype(float) - seq.rgb[inner]).mean()
    assert after < 0.35 * before, (before, after)
    # Depth: nearest sampling keeps values that exist in the recorded map.
    depth = distort_images(seq.depth, seq.intrinsics, k1, nearest=True)
    depth_u = undistort_images(depth, seq.intrinsics, k1, nearest=True)
    assert np.isin(depth_u[depth_u > 0], depth).all()
    rel = np.abs(depth_u[inner] - seq.depth[inner]) / seq.depth[inner]
    assert np.median(rel) < 0.01


def test_features_are_resampled_at_their_own_resolution():
    intrinsics = (300.0, 300.0, 159.5, 119.5)
    k1 = -0.08  # barrel: every pinhole pixel comes from inside the recording
    h, w = 30, 40
    # A feature that is the recorded x pixel coordinate (at feature resolution).
    ramp = np.broadcast_to(np.arange(w, dtype=np.float32), (h, w))
    features = np.stack([ramp, 2 * ramp])[None]
    out = undistort_features(features, intrinsics, (240, 320), k1)
    assert out.shape == features.shape
    feat_intr = torch.tensor(pj.scale_intrinsics(intrinsics, w / 320, h / 240), dtype=torch.float64)
    expected = pj.distort(pj.pixel_grid(h, w), feat_intr, k1)[..., 0].numpy()
    assert np.allclose(out[0, 0], expected, atol=1e-3)
    assert np.allclose(out[0, 1], 2 * expected, atol=2e-3)


def test_only_lenses_that_move_pixels_are_worth_resampling():
    intrinsics, size = (525.0, 525.0, 319.5, 239.5), (480, 640)
    # Corner: normalised radius^2 0.58, 400 px from the centre.
    assert abs(largest_shift(intrinsics, size, -0.037) - 0.037 * 0.58 * 400) < 0.3
    assert worth_undistorting(intrinsics, size, -0.037)
    assert not worth_undistorting(intrinsics, size, -0.002)  # what a pinhole camera's estimate looks like
    assert not worth_undistorting(intrinsics, size, 0.0)
