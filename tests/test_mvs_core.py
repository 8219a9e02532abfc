"""Unit tests of mvs_core (the multi-view stereo refinement) on analytic textured walls."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from mvs_core import (
    MvsConfig,
    consistent_views,
    patch_statistics,
    refine_depth,
    select_sources,
    select_winner,
    sweep_cost,
)
from mvs_core.sweep import mean_of_smallest

from helpers import look_at, render_wall

H, W = 96, 128
INTR = (100.0, 100.0, 63.5, 47.5)


def _sideways(num: int, step: float = 0.06, distance: float = 3.0) -> np.ndarray:
    """Camera-to-world poses moving sideways (x) in front of the wall z = distance."""
    return np.stack([look_at([i * step - (num - 1) * step / 2, 0.0, 0.0], [i * step * 0.5, 0.0, distance])
                     for i in range(num)])


def _bumpy(depth: np.ndarray, amplitude: float, seed: int = 0) -> np.ndarray:
    """Depth times a smooth per-pixel bump field exp(+-amplitude) different in every frame."""
    import cv2

    rng = np.random.default_rng(seed)
    out = []
    for d in depth:
        field = cv2.GaussianBlur(rng.standard_normal(d.shape).astype(np.float32), (0, 0), 4.0)
        field *= amplitude / max(float(np.abs(field).max()), 1e-6)
        out.append(d * np.exp(field))
    return np.stack(out).astype(np.float32)


def _abs_rel(pred, truth, mask=None):
    mask = (truth > 0) & (pred > 0) if mask is None else mask & (truth > 0) & (pred > 0)
    return float(np.mean(np.abs(pred[mask] - truth[mask]) / truth[mask]))


def _world_x(poses: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World x (N, H, W) of every pixel's surface point."""
    fx, fy, cx, cy = INTR
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)[None] * depth[..., None]
    return np.einsum("nc,nhwc->nhw", poses[:, 0, :3], cam) + poses[:, 0, 3, None, None]


def test_sources_are_other_views_with_parallax_in_range():
    poses = torch.as_tensor(_sideways(9, step=0.05))
    depth = torch.full((9, H, W), 3.0)
    index, scores = select_sources(depth, poses, torch.tensor(INTR), num_sources=2, min_angle=2.0, max_angle=6.0)
    assert index.shape == (9, 2)
    assert not (index == torch.arange(9)[:, None]).any(), "a frame is never its own source"
    # 5 cm steps at 3 m: ~1 degree per step, so the best sources are 2-6 steps away, not neighbours.
    gaps = (index - torch.arange(9)[:, None]).abs()
    assert bool((gaps >= 2).all()) and bool((gaps <= 6).all()), gaps
    assert float(scores.min()) > 0.3


def test_sweep_finds_the_wall_from_a_wrong_start():
    poses = _sideways(3, step=0.15)
    grey, depth = render_wall(poses, INTR, H, W)
    images = torch.as_tensor(grey)
    p = torch.as_tensor(poses)
    ref_to_src = torch.linalg.solve(p[[0, 2]], p[1].expand(2, 4, 4))
    offsets = torch.linspace(-0.4, 0.4, 33)
    start = torch.as_tensor(depth[1]) * 1.2  # 20 % too far
    cost = sweep_cost(images[1], patch_statistics(images[1], 3), start, images[[0, 2]], torch.tensor(INTR), ref_to_src,
                      offsets, 3, 2, 0.02)
    offset, best, gap, at_edge = select_winner(cost, offsets)
    found = start * torch.exp(offset)
    inner = (slice(10, -10), slice(20, -20))
    rel = ((found - torch.as_tensor(depth[1])).abs() / torch.as_tensor(depth[1]))[inner]
    assert float(rel.median()) < 0.005, float(rel.median())
    assert not bool(at_edge[inner].any())
    assert float(best[inner].median()) < 0.1 and float(gap[inner].median()) > 0.02


def test_the_mean_of_the_smallest_costs_is_topks_to_the_bit():
    torch.manual_seed(0)
    cost = torch.rand(6, 4, 30, 40) * 2.0
    cost[:, :, :5] = 1.0  # sources that do not see a pixel all score 1: ties
    cost[2, 1] = cost[4, 1]
    for keep in range(1, 7):
        expected = cost.topk(keep, dim=0, largest=False).values.mean(0)
        assert torch.equal(mean_of_smallest(cost, keep), expected), keep
    assert torch.equal(mean_of_smallest(cost, 1), cost.amin(0))


def test_consistency_counts_views_that_agree():
    poses = _sideways(4, step=0.1)
    _, depth = render_wall(poses, INTR, H, W)
    sources = torch.tensor([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    d = torch.as_tensor(depth).clone()
    d[3] *= 1.1  # frame 3 disagrees with everyone by 10 %
    count, mean = consistent_views(d, torch.as_tensor(poses), torch.tensor(INTR), sources)
    centre = (slice(30, 66), slice(40, 88))
    assert float(count[0][centre].median()) == 2.0  # frames 1 and 2 agree, 3 does not
    assert float(count[3][centre].max()) == 0.0
    assert torch.allclose(mean[0][centre], d[0][centre], rtol=1e-3)


def test_refinement_repairs_per_pixel_shape_on_texture_and_leaves_a_flat_wall_alone(device):
    poses = _sideways(8, step=0.08)
    grey, truth = render_wall(poses, INTR, H, W, flat_right=True)
    prior = _bumpy(truth, amplitude=0.15)
    config = replace(MvsConfig(), image_scale=1.0, num_sources=4, keep_best=2, min_angle=1.0, max_angle=10.0,
                     device=device)
    result = refine_depth(torch.as_tensor(grey), torch.as_tensor(prior), torch.as_tensor(poses), torch.tensor(INTR),
                          config)
    result.depth, result.reconstructed, result.confidence = (
        t.cpu() for t in (result.depth, result.reconstructed, result.confidence))
    refined = result.depth.numpy()
    # Which half of each image shows the textured wall: world x < 0. The fill spreads
    # corrections ~3 fill_sigma (0.55 m here) into the flat half; beyond that it is untouched.
    world_x = _world_x(poses, truth)
    textured, flat = world_x < -0.05, world_x > 0.6
    assert _abs_rel(refined, truth, textured) < 0.4 * _abs_rel(prior, truth, textured)
    assert result.reconstructed.numpy()[textured].mean() > 0.5
    # The flat half has nothing to match: little is reconstructed there, and it is no worse.
    assert result.reconstructed.numpy()[flat].mean() < 0.05
    assert _abs_rel(refined, truth, flat) <= _abs_rel(prior, truth, flat) + 0.002
    assert ((result.confidence > 0) == result.reconstructed).all()


def test_a_textureless_wall_is_left_as_it_was():
    poses = _sideways(6, step=0.08)
    grey, truth = render_wall(poses, INTR, H, W)
    grey[:] = 0.5  # nothing to match anywhere
    prior = _bumpy(truth, amplitude=0.15)
    result = refine_depth(torch.as_tensor(grey), torch.as_tensor(prior), torch.as_tensor(poses), torch.tensor(INTR),
                          replace(MvsConfig(), num_sources=3, min_angle=1.0, max_angle=10.0))
    assert not result.reconstructed.any()
    assert bool(result.unsupported.all())
    np.testing.assert_allclose(result.depth.numpy(), prior, rtol=1e-6)


def test_one_frame_is_returned_unchanged():
    grey, depth = render_wall(_sideways(1), INTR, H, W)
    result = refine_depth(torch.as_tensor(grey), torch.as_tensor(depth), torch.as_tensor(_sideways(1)),
                          torch.tensor(INTR))
    assert torch.equal(result.depth, torch.as_tensor(depth))
    assert not result.reconstructed.any() and bool(result.unsupported.all())


def test_frames_swept_before_are_sources_only_and_give_the_same_answer():
    # A streamed window shares its first frames with the window before: their sweep is
    # passed as `known`, and the frames after them come out as a full call gives them.
    poses = _sideways(8, step=0.08)
    grey, truth = render_wall(poses, INTR, H, W)
    prior = _bumpy(truth, amplitude=0.15)
    config = replace(MvsConfig(), image_scale=1.0, num_sources=4, keep_best=2, min_angle=1.0, max_angle=10.0)
    args = torch.as_tensor(grey), torch.as_tensor(prior), torch.as_tensor(poses), torch.tensor(INTR), config
    full = refine_depth(*args)
    swept_frames = []
    tail = refine_depth(*args, progress=swept_frames.append, known=full.swept[:3])
    assert len(swept_frames) == 5, "the known frames are not swept again"
    assert tail.depth.shape == (5, H, W) and tail.swept.shape == (5, H, W)
    assert torch.equal(tail.sources, full.sources[3:])
    assert torch.equal(tail.depth, full.depth[3:]) and torch.equal(tail.confidence, full.confidence[3:])
    assert torch.equal(tail.reconstructed, full.reconstructed[3:])
    assert float(tail.reconstructed.float().mean()) > 0.3
    with pytest.raises(ValueError, match="known swept depth"):
        refine_depth(*args, known=full.swept)
