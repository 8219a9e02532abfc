"""The sparse feature start (recon.poses.matching.features): ORB + PnP gives a large relative pose that
unseeded flow cannot reach, and refuses unrelated images."""

from __future__ import annotations

import numpy as np

from recon.poses.matching import features as ft
from recon.synthetic import render_sequence


def test_orb_pnp_recovers_a_large_relative_pose():
    """The feature start: a keyframe and a frame 5 path-steps of the fast walk apart (too far
    for unseeded flow at a quarter of the size) give their relative pose by ORB + PnP."""
    seq = render_sequence(3, 320, 240, seed=2, speed=10)
    cfg = ft.FeatureConfig()
    gray = [np.ascontiguousarray(g.mean(-1).astype(np.uint8)) for g in seq.rgb]
    rel, inliers = ft.relative_pose(ft.detect(gray[0], cfg), seq.depth[0], ft.detect(gray[2], cfg),
                                    seq.intrinsics, (240, 320), cfg)
    assert rel is not None and inliers >= cfg.min_inliers
    truth = np.linalg.inv(seq.poses[2]) @ seq.poses[0]  # camera 0 -> camera 2
    assert np.linalg.norm(rel[:3, 3] - truth[:3, 3]) < 0.05 * max(np.linalg.norm(truth[:3, 3]), 0.1)
    angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3].T @ truth[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 1.0  # a start for the flow alignment, not the final pose


def test_orb_pnp_refuses_unrelated_images():
    a = render_sequence(1, 320, 240, seed=2)
    noise = np.random.default_rng(0).integers(0, 256, (240, 320), dtype=np.uint8)
    cfg = ft.FeatureConfig()
    rel, _ = ft.relative_pose(ft.detect(np.ascontiguousarray(a.rgb[0].mean(-1).astype(np.uint8)), cfg), a.depth[0],
                              ft.detect(noise, cfg), a.intrinsics, (240, 320), cfg)
    assert rel is None
