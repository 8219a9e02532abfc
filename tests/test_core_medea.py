"""End to end: MEDeA with ground-truth poses on the rendered synthetic room."""

from __future__ import annotations

import numpy as np
import pytest

from medea_core import MedeaConfig
from recon.core.medea import adjust_sequence
from recon.core.report import scale_vs_prior
from recon.eval.depth import depth_metrics, multiview_inconsistency
from recon.synthetic import render_sequence, simulate_prior


@pytest.fixture(scope="module")
def scene():
    seq = render_sequence(num_frames=33, width=320, height=240, seed=3)
    prior = simulate_prior(seq.depth, seed=3)
    return seq, prior


def _scores(depth, seq):
    metrics = depth_metrics(depth, seq.depth)
    metrics["inconsistency"] = multiview_inconsistency(depth, seq.poses, seq.intrinsics)
    return metrics


@pytest.mark.parametrize("config", [MedeaConfig(), MedeaConfig.fast()], ids=["paper", "fast"])
def test_medea_cuts_error_and_inconsistency(scene, config):
    seq, prior = scene
    before = _scores(prior, seq)
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=config, progress=False)
    after = _scores(result.depth.numpy(), seq)
    assert 0.15 <= before["abs_rel"] <= 0.25
    assert after["abs_rel"] <= 0.4 * before["abs_rel"], (before, after)
    assert after["inconsistency"] <= 0.4 * before["inconsistency"], (before, after)
    assert after["abs_rel"] <= 0.05
    assert after["delta1"] > before["delta1"]
    # Stage I's loss goes down, and both stages ran.
    stage1 = result.history["stage1"].losses["total"]
    assert stage1[-1] < 0.5 * stage1[0]
    assert result.history["stage2"].epochs >= 1


def test_propagation_alone_fixes_non_keyframes(scene):
    seq, prior = scene
    config = MedeaConfig(run_stage2=False)
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=config, progress=False)
    others = np.setdiff1d(np.arange(len(prior)), result.keyframes.numpy())
    before = depth_metrics(prior[others], seq.depth[others])["abs_rel"]
    after = depth_metrics(result.depth.numpy()[others], seq.depth[others])["abs_rel"]
    assert after <= 0.5 * before
    quick = MedeaConfig(run_stage2=False, propagate_scale=False)
    quick.stage1.epochs = 2
    no_propagation = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=quick, progress=False)
    unchanged = no_propagation.depth.numpy()[others]
    assert np.allclose(unchanged, prior[others])


def test_report_gives_the_scale_medea_moved_the_prior_by(scene):
    """report.json's medea.scale_vs_prior: with translation in the poses, MEDeA moves each
    frame's scale to the truth's, so the reported factor matches truth / prior."""
    seq, prior = scene
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=MedeaConfig.fast(), progress=False)
    reported = scale_vs_prior(result.log_scales)
    valid = prior > 0
    truth_over_prior = np.array([np.median(g[v] / p[v]) for g, p, v in zip(seq.depth, prior, valid)])
    assert reported["median"] == pytest.approx(np.median(truth_over_prior), rel=0.05)
    assert reported["p10"] < reported["median"] < reported["p90"]
    # The simulated prior's frames differ in scale by ~20 %: the spread is reported too.
    assert reported["p90"] / reported["p10"] > 1.2


def test_scale_vs_prior_of_known_grids():
    grids = np.log(np.array([0.5, 1.0, 2.0, 4.0, 8.0]))[:, None, None] * np.ones((5, 8, 10))
    grids[:, 0, 0] = 5.0  # one outlying cell per frame does not move a frame's median
    out = scale_vs_prior(grids)
    assert out["median"] == pytest.approx(2.0)
    assert out["p10"] == pytest.approx(np.percentile([0.5, 1, 2, 4, 8], 10))
    assert scale_vs_prior(np.zeros((0, 8, 10))) == {}
