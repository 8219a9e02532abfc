"""End to end on the rendered room: a prior with per-pixel shape errors (bumps, ramps,
smeared depth edges) that no 8x10 grid represents is repaired by the MVS refinement after
MEDeA (ground-truth poses), in depth and in the fused mesh."""

from __future__ import annotations

import numpy as np
import pytest

from medea_core import MedeaConfig
from recon.commands.demo import mesh_scores
from recon.core.medea import adjust_sequence
from recon.core.refine import (
    default_min_confidence,
    default_weight_threshold,
    fusion_confidence,
    refine_sequence,
    refine_summary,
)
from recon.eval.depth import depth_metrics
from recon.fusion import FusionOptions, fuse
from recon.synthetic import add_shape_errors, render_sequence, simulate_prior


@pytest.fixture(scope="module")
def refined():
    seq = render_sequence(num_frames=40, width=320, height=240, seed=5)
    prior = add_shape_errors(simulate_prior(seq.depth, seed=5), seed=5)
    medea = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=MedeaConfig.fast(),
                            progress=False).depth.numpy()
    result = refine_sequence(seq.rgb, medea, seq.poses, seq.intrinsics, progress=False)
    return seq, prior, medea, result


def _mesh_f(depth, seq, confidence=None):
    mesh = fuse(depth, None, seq.poses, seq.intrinsics, FusionOptions(progress=False), confidence=confidence).mesh
    return mesh_scores(mesh, seq)["fscore"]


def test_confirmed_depth_is_meshed_from_one_frame(refined):
    """Every 8th frame's refined depth (a streamed run's depth frames), the given-pose gate:
    the default threshold for refined given poses (1) meshes the surface that one fused frame
    confirmed, which a second-frame requirement drops, at the same precision."""
    seq, _, _, result = refined
    picked = slice(None, None, 8)
    depth, confidence = result.depth.numpy()[picked], fusion_confidence(result)[picked]
    scores = {}
    for threshold in (default_weight_threshold(False, True), 2.0):
        options = FusionOptions(progress=False, min_confidence=default_min_confidence(False),
                                weight_threshold=threshold)
        mesh = fuse(depth, None, seq.poses[picked], seq.intrinsics, options, confidence=confidence).mesh
        scores[threshold] = mesh_scores(mesh, seq)
    one, two = scores[1.0], scores[2.0]
    assert one["recall"] > two["recall"] + 0.02, (one, two)
    assert one["precision"] > two["precision"] - 0.025 and one["fscore"] > two["fscore"] + 0.01, (one, two)
    # Unconfirmed depth, or estimated poses (whose gate admits filled pixels): two frames.
    assert default_weight_threshold(False, False) == default_weight_threshold(True, True) == 2.0


def test_shape_errors_are_beyond_medea(refined):
    seq, prior, medea, _ = refined
    # The simulated network is ~20 % off, and MEDeA's grid leaves the per-pixel shape error.
    assert depth_metrics(prior, seq.depth)["abs_rel"] > 0.15
    assert depth_metrics(medea, seq.depth)["abs_rel"] > 0.035


def test_refinement_repairs_per_pixel_shape(refined):
    seq, prior, medea, result = refined
    before = depth_metrics(medea, seq.depth)["abs_rel"]
    after = depth_metrics(result.depth.numpy(), seq.depth)["abs_rel"]
    assert after < 0.6 * before, (before, after)
    reconstructed = result.reconstructed.numpy()
    assert reconstructed.mean() > 0.6
    on_reconstructed = depth_metrics(np.where(reconstructed, result.depth.numpy(), 0), seq.depth)["abs_rel"]
    assert on_reconstructed < 0.02
    f_medea = _mesh_f(medea, seq)
    f_refined = _mesh_f(result.depth.numpy(), seq, fusion_confidence(result))
    assert f_refined > f_medea + 0.2 and f_refined > 0.75, (f_medea, f_refined)


def test_fusion_confidence_orders_reconstructed_filled_and_unsupported_pixels():
    import torch

    from mvs_core import RefineResult
    from recon.core.refine import FILLED_CONFIDENCE

    depth = torch.ones(3, 4, 6)
    depth[0, 0, 2] = 0.0  # invalid pixel: never fused
    reconstructed = torch.zeros(3, 4, 6, dtype=torch.bool)
    reconstructed[0, :, :2] = True
    confidence = torch.where(reconstructed, torch.tensor(0.5), torch.tensor(0.0))
    support = torch.zeros(3, 4, 6)
    support[0, :, 2] = 0.6  # filled next to evidence
    support[0, :, 5] = 0.02  # filled far from it
    unsupported = torch.tensor([False, False, True])
    result = RefineResult(depth, confidence, reconstructed, torch.zeros(3, 1), torch.zeros(3, 1), unsupported,
                          {}, support)
    weights = fusion_confidence(result)
    assert weights[0, 1, 0] == pytest.approx(0.5)
    assert weights[0, 0, 2] == 0.0
    assert weights[0, 1, 2] == pytest.approx(FILLED_CONFIDENCE * 0.6)
    assert (weights[2] == 1.0).all()  # an unsupported frame is fused whole
    given, estimated = default_min_confidence(False), default_min_confidence(True)
    # Given poses: reconstructed pixels only; estimated: also filled pixels near evidence.
    assert weights[0, 1, 0] >= given > weights[0, 1, 2]
    assert weights[0, 1, 2] >= estimated > weights[0, 1, 5]


def test_a_sparse_frame_fuses_its_filled_pixels_near_evidence():
    """With sparse_frame_share 0.5, the frame reconstructed on a third of its pixels passes
    the given-pose threshold with its filled pixels near evidence (support 0.6), not the
    far ones (0.02); the frame reconstructed on two thirds keeps its reconstructed pixels only."""
    import torch

    from mvs_core import RefineResult

    depth = torch.ones(2, 3, 6)
    reconstructed = torch.zeros(2, 3, 6, dtype=torch.bool)
    reconstructed[0, :, :2] = True  # a third
    reconstructed[1, :, :4] = True  # two thirds
    confidence = torch.where(reconstructed, torch.tensor(0.5), torch.tensor(0.0))
    support = torch.full((2, 3, 6), 0.6)
    support[:, :, 5] = 0.02
    share = reconstructed.flatten(1).float().mean(1)
    unsupported = torch.zeros(2, dtype=torch.bool)

    def result_at(sparse_share: float) -> RefineResult:
        """The frames marked sparse as refine_depth marks them at sparse_share."""
        return RefineResult(depth, confidence, reconstructed, torch.zeros(2, 1), torch.zeros(2, 1), unsupported,
                            {"reconstructed": share}, support, sparse=(share < sparse_share) & ~unsupported)

    result, none_sparse = result_at(0.5), result_at(0.0)
    given = default_min_confidence(False)
    fused = fusion_confidence(result) >= given
    assert fused[0, :, :5].all() and not fused[0, :, 5].any()
    assert fused[1, :, :4].all() and not fused[1, :, 4:].any()
    assert not (fusion_confidence(none_sparse) >= given)[0, :, 2:].any()  # 0: no frame is sparse
    assert refine_summary(result)["sparse_frames"] == [0] and refine_summary(none_sparse)["sparse_frames"] == []
    # With estimated poses the same pixels are fused with the rule or without it.
    estimated = default_min_confidence(True)
    assert ((fusion_confidence(result) >= estimated) == (fusion_confidence(none_sparse) >= estimated)).all()
