"""Unit tests of the MEDeA core: geometry, pair sampling, losses, freezing, propagation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from medea_core import MedeaConfig, StageConfig, hierarchical_pairs, optimise_stage, run_medea, stage_pairs
from medea_core.frames import prepare_frames
from medea_core.geometry import depth_in_view_i, pair_transforms, pixel_grid, reproject, sample
from medea_core.grid import median_pool_to_grid, scale_field
from medea_core.losses import depth_loss, feature_loss_m, feature_loss_s, photometric_loss, relative_depth_loss
from medea_core.objective import pair_overlap
from medea_core.pairs import connects
from medea_core.propagate import propagate_scales

from helpers import look_at, plane_depth

H, W = 96, 128
INTR = (110.0, 110.0, 63.5, 47.5)


def _tensor_pair(pose_i, pose_j, depth_i):
    poses = torch.as_tensor(np.stack([pose_i, pose_j]))
    i_to_j, j_to_i = pair_transforms(poses, torch.tensor([[0, 1]]))
    intr = torch.tensor([INTR])
    return torch.as_tensor(depth_i)[None], intr, i_to_j, j_to_i


def test_reprojection_onto_itself_is_identity():
    pose = look_at([0.3, -0.2, 0.1], [0.5, 0.4, 3.0])
    depth = plane_depth(pose, INTR, H, W, normal=[0.1, 0.2, 1.0], offset=3.0)
    depth_i, intr, i_to_j, j_to_i = _tensor_pair(pose, pose, depth)
    rep = reproject(depth_i, intr, intr, i_to_j, (H, W))
    assert torch.allclose(rep.uv_j[0], pixel_grid(H, W), atol=1e-3)
    assert bool(rep.valid.all())
    sampled = sample(depth_i[:, None], rep.uv_j)[:, 0]
    back = depth_in_view_i(sampled, rep.uv_j, intr, j_to_i)
    assert torch.allclose(back, depth_i, rtol=1e-4)


def test_reprojection_matches_analytic_shift_under_translation():
    z, tx, ty = 2.0, 0.1, -0.05
    pose_i = np.eye(4)
    pose_j = np.eye(4)
    pose_j[:3, 3] = [tx, ty, 0.0]
    depth = np.full((H, W), z, np.float32)
    depth_i, intr, i_to_j, j_to_i = _tensor_pair(pose_i, pose_j, depth)
    rep = reproject(depth_i, intr, intr, i_to_j, (H, W))
    expected = pixel_grid(H, W).clone()
    expected[..., 0] -= INTR[0] * tx / z
    expected[..., 1] -= INTR[1] * ty / z
    assert torch.allclose(rep.uv_j[0], expected, atol=1e-3)
    # Pixels whose footprint leaves frame j are invalid: the right-most 6 columns here.
    shift = INTR[0] * tx / z
    assert not bool(rep.valid[0, :, : int(np.ceil(shift)) - 1].any())
    assert bool(rep.valid[0, 5:-5, int(np.ceil(shift)) + 1 :].all())
    sampled = sample(torch.as_tensor(depth)[None, None], rep.uv_j)[:, 0]
    back = depth_in_view_i(sampled, rep.uv_j, intr, j_to_i)
    assert torch.allclose(back[rep.valid], depth_i[rep.valid], rtol=1e-4)


def _brute_force_pairs(n, a, b):
    out = set()
    for i, j in itertools.product(range(n), repeat=2):
        for level in range(a, b + 1):
            if abs(i - j) == 2**level and i % 2**level == 0:
                out.add((i, j))
    return out


@pytest.mark.parametrize("n", [1, 2, 5, 9, 17, 33, 100, 257])
@pytest.mark.parametrize("levels", [(0, 2), (3, 6), (1, 1)])
def test_pairs_match_formula(n, levels):
    pairs = hierarchical_pairs(n, *levels)
    as_set = {tuple(p) for p in pairs.tolist()}
    assert len(as_set) == len(pairs)
    assert as_set == _brute_force_pairs(n, *levels)


def test_short_sequence_fallback_makes_every_frame_a_keyframe():
    p1, keyframes, p2 = stage_pairs(5, (3, 6), (0, 2))
    assert keyframes.tolist() == [0, 1, 2, 3, 4]
    assert {tuple(p) for p in p1.tolist()} == _brute_force_pairs(5, 0, 2)
    assert p2.numel() == 0
    p1, keyframes, p2 = stage_pairs(40, (3, 6), (0, 2))
    assert keyframes.tolist() == [0, 8, 16, 24, 32]
    assert len(p2) == len(_brute_force_pairs(40, 0, 2))


def test_loss_values_on_known_inputs():
    mask = torch.ones(1, 4, 5, dtype=torch.bool)
    mask[0, 0] = False
    image = torch.rand(1, 3, 4, 5)
    assert float(photometric_loss(image, image, mask)) == 0.0
    assert float(photometric_loss(image, image + 0.1, mask)) == pytest.approx(0.1, abs=1e-6)
    feat_i = torch.ones(1, 2, 4, 5)
    feat_j = 3 * torch.ones(1, 2, 4, 5)
    assert float(feature_loss_s(feat_i, feat_j, mask, eps=0.0)) == pytest.approx(0.5, abs=1e-6)
    assert float(feature_loss_s(feat_i, feat_j, mask)) == pytest.approx(2 / 4.01, abs=1e-6)
    assert float(feature_loss_s(feat_i, feat_i, mask)) == 0.0
    # ReLU features that are both (nearly) off: the bare ratio would say "maximally
    # different" (1) for 0 against 1e-4; with the default eps it says "alike".
    off, barely = torch.zeros(1, 2, 4, 5), torch.full((1, 2, 4, 5), 1e-4)
    assert float(feature_loss_s(off, barely, mask)) < 0.02
    assert float(feature_loss_m(feat_i, feat_j, mask)) == pytest.approx(-6.0)


def test_the_relative_depth_loss_scores_a_disagreement_alike_at_any_scale():
    """The paper's depth term in metres halves with the scene; the relative one does not."""
    mask = torch.ones(1, 4, 5, dtype=torch.bool)
    near, far = torch.full((1, 4, 5), 2.0), torch.full((1, 4, 5), 3.0)
    assert float(relative_depth_loss(near, far, mask)) == pytest.approx(0.2, abs=1e-6)
    assert float(relative_depth_loss(near / 2, far / 2, mask)) == pytest.approx(0.2, abs=1e-6)
    assert float(depth_loss(near / 2, far / 2, mask)) == pytest.approx(float(depth_loss(near, far, mask)) / 2)
    assert float(relative_depth_loss(near, near, mask)) == 0.0


def _plane_sequence(num_frames=3, seed=0):
    """Textured-by-noise frames of a wall seen from a short sideways path."""
    rng = np.random.default_rng(seed)
    poses = [look_at([0.15 * k, 0.0, 0.0], [0.15 * k + 0.2, 0.1, 3.0]) for k in range(num_frames)]
    depth = np.stack([plane_depth(p, INTR, H, W, [0.0, 0.1, 1.0], 3.0) for p in poses])
    images = torch.as_tensor(rng.random((num_frames, 3, H, W)), dtype=torch.float32)
    return images, torch.as_tensor(depth), torch.as_tensor(np.stack(poses)), torch.tensor(INTR)


def test_frozen_grids_get_no_updates():
    images, depth, poses, intr = _plane_sequence(3)
    prior = depth * torch.tensor([1.2, 0.8, 1.1])[:, None, None]
    config = MedeaConfig(image_scale=0.5)
    data = prepare_frames(images, prior, poses, intr, None, config.image_scale, "cpu")
    start = torch.randn(3, 8, 10) * 0.05
    trainable = torch.tensor([False, True, False])
    pairs = torch.tensor([[0, 1], [1, 0], [1, 2], [2, 1], [0, 2], [2, 0]])
    stage = StageConfig(epochs=5, gamma=0.96, patience=100)
    result, history = optimise_stage(data, start, trainable, pairs, stage, config, torch.Generator().manual_seed(0))
    assert history.epochs == 5
    assert torch.equal(result[0], start[0]) and torch.equal(result[2], start[2])
    assert not torch.allclose(result[1], start[1])


def test_adam_eps_damps_steps_of_small_gradients():
    """adam_eps reaches the optimiser: Adam's first step moves a cell by the learning rate
    whatever its gradient (eps 1e-8); with an eps far above the gradients it moves
    gradient x lr / eps, i.e. barely."""
    images, depth, poses, intr = _plane_sequence(3)
    prior = depth * torch.tensor([1.2, 0.8, 1.1])[:, None, None]
    config = MedeaConfig(image_scale=0.5)
    data = prepare_frames(images, prior, poses, intr, None, config.image_scale, "cpu")
    pairs = torch.tensor([[0, 1], [1, 0], [1, 2], [2, 1]])
    moved = {}
    for eps in (1e-8, 10.0):
        stage = StageConfig(epochs=1, gamma=1.0, patience=100, lr=0.1, adam_eps=eps)
        result, _ = optimise_stage(data, torch.zeros(3, 8, 10), torch.ones(3, dtype=torch.bool), pairs, stage,
                                   config, torch.Generator().manual_seed(0))
        moved[eps] = result.abs()
    stepped = moved[1e-8] > 0
    assert stepped.float().mean() > 0.5
    assert torch.allclose(moved[1e-8][stepped], torch.full_like(moved[1e-8][stepped], 0.1), rtol=1e-3)
    assert moved[10.0].max() < 1e-3


def _smooth_log_grid(generator, amplitude=0.15):
    """A smooth (8, 10) log-scale grid: a random 3x3 field interpolated onto the grid."""
    coarse = torch.randn(1, 1, 3, 3, generator=generator) * amplitude
    return torch.nn.functional.interpolate(coarse, size=(8, 10), mode="bicubic", align_corners=True)[0, 0]


def test_median_pool_recovers_smooth_grid():
    generator = torch.Generator().manual_seed(1)
    log_true = torch.stack([_smooth_log_grid(generator, 0.2) for _ in range(2)])
    field = scale_field(log_true, (120, 160))
    pooled = median_pool_to_grid(field, torch.ones_like(field, dtype=torch.bool), (8, 10)).log()
    # Border cells are one-sided, so their median sits a quarter cell inwards.
    assert (pooled - log_true).abs().max() < 0.06
    assert (pooled - log_true)[:, 1:-1, 1:-1].abs().max() < 0.02


def test_propagation_recovers_known_scale_field():
    pose_key = look_at([0.0, 0.0, -0.8], [0.1, 0.1, 3.0])
    pose_other = look_at([0.2, -0.1, 0.0], [0.3, 0.0, 3.0])
    gt = [plane_depth(p, INTR, H, W, [0.05, 0.1, 1.0], 3.0) for p in (pose_key, pose_other)]
    gt = torch.as_tensor(np.stack(gt))
    generator = torch.Generator().manual_seed(3)
    log_true = _smooth_log_grid(generator)
    prior = gt.clone()
    prior[1] = gt[1] / scale_field(log_true[None], (H, W))[0]
    images = torch.zeros(2, 3, H, W)
    poses = torch.as_tensor(np.stack([pose_key, pose_other]))
    data = prepare_frames(images, prior, poses, torch.tensor(INTR), None, 1.0, "cpu")
    recovered = propagate_scales(data, torch.zeros(2, 8, 10), torch.tensor([1]), torch.tensor([0]))[0]
    assert (recovered - log_true).abs().max() < 0.03
    assert (recovered - log_true).abs().mean() < 0.01


def test_run_is_deterministic_for_a_seed_and_keeps_shapes(device):
    from medea_core import run_medea

    images, depth, poses, intr = _plane_sequence(10)
    prior = depth * torch.linspace(0.8, 1.2, 10)[:, None, None]
    config = MedeaConfig(image_scale=0.5, pixel_stride=2, device=device)
    config.stage1.epochs, config.stage2.epochs = 8, 4
    first = run_medea(images, prior, poses, intr, config=config)
    second = run_medea(images, prior, poses, intr, config=config)
    if device == "cpu":
        assert torch.equal(first.depth, second.depth)
    else:
        # CUDA sums the gradients of bilinear sampling with atomic adds, in an order that
        # changes from run to run: the same seed gives the same depth up to that round-off.
        rel = ((first.depth - second.depth).abs() / second.depth).flatten()
        assert float(rel.median()) <= 1e-4 and float(rel.max()) <= 1e-2, (float(rel.median()), float(rel.max()))
    assert first.depth.shape == prior.shape and first.depth.device == prior.device  # back on the caller's device
    assert first.log_scales.shape == (10, 8, 10)
    assert first.keyframes.tolist() == [0, 8]
    assert first.history["stage1"].epochs == 8
    assert len(first.history["stage1"].losses["total"]) == 8
    transposed_intrinsics = torch.tensor([INTR[1], INTR[0], INTR[3], INTR[2]])
    portrait = run_medea(images.transpose(-1, -2), prior.transpose(-1, -2), poses, transposed_intrinsics, config=config)
    assert portrait.log_scales.shape == (10, 10, 8)


def test_single_frame_returns_the_prior():
    from medea_core import run_medea

    images, depth, poses, intr = _plane_sequence(1)
    result = run_medea(images, depth, poses, intr)
    assert torch.equal(result.depth, depth)


def test_feature_channel_selection_keeps_the_most_varying():
    from medea_core.frames import most_varying_channels

    gen = torch.Generator().manual_seed(0)
    spread = torch.tensor([0.0, 3.0, 0.1, 1.0, 0.0, 2.0])
    features = torch.rand(5, 6, 4, 7, generator=gen) * spread[None, :, None, None] + 1.0
    assert most_varying_channels(features, 3).tolist() == [1, 3, 5]
    assert most_varying_channels(features, 10).tolist() == list(range(6))
    prior = torch.full((5, 8, 14), 2.0)
    data = prepare_frames(torch.rand(5, 3, 8, 14), prior, torch.eye(4).expand(5, 4, 4),
                          torch.tensor([10.0, 10.0, 7.0, 4.0]), features, 0.5, "cpu", feature_channels=2)
    assert data.features.maps.shape[1] == 2
    assert torch.allclose(data.features.maps, features[:, [1, 5]])


@pytest.mark.parametrize("change", [dict(batch_pairs=0), dict(image_scale=0.0), dict(pixel_stride=0),
                                    dict(stage2_levels=(2, 1)), dict(feature_channels=0)])
def test_settings_that_cannot_work_are_refused_by_name(change):
    config = MedeaConfig(**change)
    name = next(iter(change))
    with pytest.raises(ValueError, match=name):
        config.validate()
    frames = torch.zeros(2, 3, 8, 8)
    with pytest.raises(ValueError, match=name):
        run_medea(frames, torch.ones(2, 8, 8), torch.eye(4).expand(2, 4, 4), torch.tensor([8.0, 8.0, 4.0, 4.0]),
                  config=config)


def test_a_stage_setting_that_cannot_work_names_its_stage():
    config = MedeaConfig()
    config.stage2.lr = -0.1
    with pytest.raises(ValueError, match=r"stage2\.lr=-0\.1"):
        config.validate()
    MedeaConfig().validate()
    MedeaConfig.fast().validate()


def _wall_pair_data(shift_x: float, image_scale: float = 0.5):
    """Two views of a fronto-parallel wall 3 m away, the second moved shift_x metres right."""
    poses = np.stack([look_at([0.0, 0.0, 0.0], [0.0, 0.0, 3.0]), look_at([shift_x, 0.0, 0.0], [shift_x, 0.0, 3.0])])
    depth = np.stack([plane_depth(p, INTR, H, W, [0.0, 0.0, 1.0], 3.0) for p in poses])
    images = torch.rand((2, 3, H, W), generator=torch.Generator().manual_seed(0))
    return prepare_frames(images, torch.as_tensor(depth), torch.as_tensor(poses), torch.tensor(INTR), None,
                          image_scale, "cpu")


@pytest.mark.parametrize("shift_x", [0.0, 0.5, 1.5, 4.0])
def test_pair_overlap_is_the_share_of_view_i_that_j_sees(shift_x):
    """Moving sideways by t in front of a wall at 3 m shifts every pixel by f t / 3: view i
    keeps the columns that still land inside j (1 - shift / width, 0 once the shift passes it)."""
    data = _wall_pair_data(shift_x)
    w, fx = data.image.size[1], float(data.image.intrinsics[0, 0])
    expected = max(0.0, 1.0 - fx * shift_x / 3.0 / w)
    overlap = pair_overlap(data, torch.tensor([[0, 1], [1, 0]]), torch.zeros(2, 8, 10), 0.999, stride=1)
    # Bilinear validity at 0.999 loses the last column of j; the lattice is whole pixels.
    assert overlap.tolist() == pytest.approx([expected, expected], abs=2.5 / w)


@pytest.mark.parametrize("pairs, joined", [([[0, 8], [8, 16]], True), ([[16, 8], [0, 8]], True),
                                            ([[0, 8]], False), ([[0, 8], [8, 0], [3, 16]], False), ([], False)])
def test_connects_asks_whether_the_pairs_join_every_keyframe(pairs, joined):
    assert connects(torch.tensor(pairs, dtype=torch.long).reshape(-1, 2), torch.tensor([0, 8, 16])) is joined


def _sideways_sequence(step: float, num_frames: int = 17):
    """Frames of a wall 3 m away from a camera moving `step` metres sideways per frame."""
    poses = np.stack([look_at([step * k, 0.0, 0.0], [step * k, 0.0, 3.0]) for k in range(num_frames)])
    depth = np.stack([plane_depth(p, INTR, H, W, [0.0, 0.0, 1.0], 3.0) for p in poses])
    images = torch.rand((num_frames, 3, H, W), generator=torch.Generator().manual_seed(0))
    return images, torch.as_tensor(depth), torch.as_tensor(poses), torch.tensor(INTR)


@pytest.mark.parametrize("step, skipped", [(0.05, False), (0.3, True)])
def test_stage1_is_skipped_when_its_overlapping_pairs_leave_keyframes_apart(step, skipped):
    """Keyframes 8 frames apart: 0.4 m (they share 88 % of the view) or 2.4 m (nothing).
    Apart, every Stage I pair is left out, Stage I is skipped and Stage II moves every
    frame's grid, the keyframes' included; together, Stage I runs on all its pairs."""
    images, depth, poses, intr = _sideways_sequence(step)
    config = MedeaConfig(image_scale=0.5, min_pair_overlap=0.5)
    config.stage1.epochs, config.stage2.epochs = 3, 3
    result = run_medea(images, depth, poses, intr, None, config)
    stage1, stage2 = result.history["stage1"], result.history["stage2"]
    total = stage_pairs(17, config.stage1_levels, config.stage2_levels)[0].shape[0]
    assert stage1.skipped is skipped
    assert (stage1.pairs, stage1.pairs_left_out) == ((0, total) if skipped else (total, 0))
    assert stage1.epochs == (0 if skipped else 3) and stage2.epochs == 3
    keyframes_moved = result.log_scales[result.keyframes].abs().amax() > 0
    assert bool(keyframes_moved)  # by Stage I, or when it was skipped by Stage II
