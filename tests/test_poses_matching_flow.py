"""Dense optical flow of the pose estimator (recon.poses.matching.flow)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon.poses.matching import flow as fl


def test_dis_flow_does_not_depend_on_earlier_calls(pose_room):
    """A seeded DIS call must not change a later unseeded one (OpenCV keeps state in the
    instance; shared instances made front-end results depend on what ran before)."""
    seq, _ = pose_room
    cfg = fl.FlowConfig()
    a, b, c = (fl.prepare_gray(seq.rgb[i], (240, 320)) for i in (0, 3, 9))
    first = fl.dis_flow(a, b, cfg)
    fl.dis_flow(a, c, cfg, init=2.0 * first + 5.0)
    np.testing.assert_array_equal(fl.dis_flow(a, b, cfg), first)


def test_a_flow_pair_on_two_threads_is_the_two_directions_in_turn(pose_room):
    """flow_pair computes the backward flow on a second thread: its four arrays are those of
    the two directions computed one after the other, seeded or not, whatever ran before."""
    seq, _ = pose_room
    cfg = fl.FlowConfig()
    a, b = (fl.prepare_gray(seq.rgb[i], (120, 160)) for i in (0, 4))
    for seed in (None, np.full((120, 160, 2), 1.5, np.float32)):
        fwd, bwd = fl.dis_flow(a, b, cfg, seed), fl.dis_flow(b, a, cfg, None if seed is None else -seed)
        expected = (fwd, bwd, fl.fb_confidence(fwd, bwd, cfg) * fl.photo_confidence(a, b, fwd, cfg),
                    fl.fb_confidence(bwd, fwd, cfg) * fl.photo_confidence(b, a, bwd, cfg))
        for got, want in zip(fl.flow_pair(a, b, cfg, seed, None if seed is None else -seed), expected):
            np.testing.assert_array_equal(got, want)


def test_flow_whitening_weighs_the_directions_the_texture_measures():
    """flow.flow_whitening: across a straight edge weight 2 and along it 0 (the aperture
    problem), about the identity on random texture, about 0 on a plain surface; None when
    the flow is weighed alike in every direction (the default)."""
    cfg = fl.FlowConfig(anisotropic=True)
    edge = np.zeros((40, 48), np.uint8)
    edge[:, 24:] = 200
    info = lambda L: (L.transpose(-1, -2) @ L).double()  # noqa: E731
    at_edge = info(fl.flow_whitening(edge, 2, cfg))[10, 11:13]
    assert np.allclose(at_edge[..., 0, 0], 2.0, atol=0.02) and np.allclose(at_edge[..., 1:, :], 0.0, atol=1e-3)
    texture = np.random.default_rng(0).integers(0, 255, (40, 48)).astype(np.uint8)
    eig = np.linalg.eigvalsh(info(fl.flow_whitening(texture, 2, cfg))[4:-4, 4:-4].numpy())
    assert np.median(eig.sum(-1)) == pytest.approx(2.0, abs=0.02) and np.median(eig[..., 0] / eig[..., 1]) > 0.5
    assert float(fl.flow_whitening(np.full((40, 48), 90, np.uint8), 2, cfg).abs().max()) < 1e-6
    assert fl.flow_whitening(texture, 2, fl.FlowConfig()) is None


def test_dis_flow_leaves_its_seed_as_it_was():
    """OpenCV's DIS writes its result into the initial flow it is given; the caller's seed
    (contiguous float32, as graph.predicted_flow makes them) must not change under it."""
    rng = np.random.default_rng(0)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (60, 80)).astype(np.float32), (0, 0), 1.5).astype(np.uint8)
    b = np.roll(a, 2, axis=1)
    seed = np.full((60, 80, 2), 0.5, np.float32)
    out = fl.dis_flow(a, b, fl.FlowConfig(), seed)
    assert np.all(seed == 0.5)
    assert np.median(out[..., 0]) == pytest.approx(2.0, abs=0.3)
