"""End to end on the rendered room: a prior with per-pixel shape errors (bumps, ramps,
smeared depth edges) that no 8x10 grid represents is repaired by the MVS refinement after
MEDeA (ground-truth poses), in depth and in the fused mesh."""

from __future__ import annotations

import numpy as np
import pytest

from medea_core import MedeaConfig
from recon.demo import mesh_scores
from recon.eval.depth import depth_metrics
from recon.fusion import FusionOptions, fuse
from recon.medea import adjust_sequence
from recon.refine import fusion_confidence, refine_sequence
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
