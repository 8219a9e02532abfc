"""The search for the prior's one global scale before Stage I (medea_core.global_scale)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from medea_core import MedeaConfig, run_medea
from medea_core.frames import prepare_frames
from medea_core.global_scale import search_global_scale, spread_pairs
from medea_core.pairs import hierarchical_pairs

from helpers import look_at, render_wall

H, W = 96, 128
INTR = (110.0, 110.0, 63.5, 47.5)


def _wall_walk(num_frames: int = 8):
    """A textured wall 3 m away seen from a sideways walk: grey frames as RGB (N, 3, H, W),
    true depth (N, H, W), camera-to-world poses (N, 4, 4)."""
    poses = np.stack([look_at([0.08 * k, 0.0, 0.0], [0.08 * k + 0.3, 0.2, 3.0]) for k in range(num_frames)])
    grey, depth = render_wall(poses, INTR, H, W, distance=3.0)
    images = torch.as_tensor(grey)[:, None].expand(-1, 3, -1, -1).contiguous()
    return images, torch.as_tensor(depth), torch.as_tensor(poses)


@pytest.mark.parametrize("off_by", [4.0, 0.3])
def test_search_finds_the_factor_that_brings_the_prior_to_the_poses(off_by):
    images, depth, poses = _wall_walk()
    data = prepare_frames(images, depth * off_by, poses, torch.tensor(INTR), None, 1.0, "cpu")
    pairs = hierarchical_pairs(len(images), 0, 2)
    found = search_global_scale(data, pairs)
    assert found.applied and found.gain > 0.2
    assert abs(math.log(found.factor * off_by)) < 0.06  # within 6 % of 1 / off_by


def test_a_prior_at_the_poses_scale_is_left_as_it_is():
    images, depth, poses = _wall_walk()
    data = prepare_frames(images, depth, poses, torch.tensor(INTR), None, 1.0, "cpu")
    pairs = hierarchical_pairs(len(images), 0, 2)
    found = search_global_scale(data, pairs)
    assert abs(math.log(found.factor)) < 0.06
    assert not found.applied and found.gain < 0.05


def test_a_camera_that_only_turns_gives_no_factor():
    """Without parallax the colour term does not depend on depth: nothing is applied."""
    poses = np.stack([look_at([0.0, 0.0, 0.0], [0.4 * k, 0.1, 3.0]) for k in range(6)])
    grey, depth = render_wall(poses, INTR, H, W, distance=3.0)
    images = torch.as_tensor(grey)[:, None].expand(-1, 3, -1, -1).contiguous()
    data = prepare_frames(images, torch.as_tensor(depth) * 4.0, torch.as_tensor(poses), torch.tensor(INTR), None, 1.0,
                          "cpu")
    found = search_global_scale(data, hierarchical_pairs(6, 0, 2))
    assert not found.applied


def test_spread_pairs_keeps_the_ends_and_the_count():
    pairs = torch.stack([torch.arange(100), torch.arange(100) + 1], 1)
    kept = spread_pairs(pairs, 10)
    assert kept.shape == (10, 2) and kept[0, 0] == 0 and kept[-1, 0] == 99
    assert torch.equal(spread_pairs(pairs[:5], 10), pairs[:5])


def test_run_medea_starts_from_the_found_factor_only_when_asked():
    images, depth, poses = _wall_walk()
    prior = depth * 4.0
    config = MedeaConfig(image_scale=1.0, pixel_stride=2)
    config.stage1.epochs, config.stage2.epochs = 3, 2
    plain = run_medea(images, prior, poses, torch.tensor(INTR), config=config)
    config.scale_search = True
    searched = run_medea(images, prior, poses, torch.tensor(INTR), config=config)
    assert plain.global_scale is None and searched.global_scale.applied
    valid = depth > 0
    error = {name: float((r.depth[valid] / depth[valid]).log().abs().median())
             for name, r in (("plain", plain), ("searched", searched))}
    assert error["searched"] < 0.1 < error["plain"]
