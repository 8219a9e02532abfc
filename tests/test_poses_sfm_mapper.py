"""The pycolmap SfM fallback (recon.poses.sfm.mapper) on the synthetic room (conftest: sfm_room):
accuracy, metric scale from the prior, dense registration of the frames COLMAP did not see,
the lens' radial term, keyframes by motion, and the check that refuses a partial model."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from recon.eval.trajectory import ate_rmse, path_length, scale_error
from recon.geometry.lens import distort_images
from recon.poses import TrackingLostError, estimate_poses
from recon.poses.config import make_geometry
from recon.poses.matching import flow as fl
from recon.poses.result import FRAME_STATES, TRUSTED_STATES
from recon.poses.sfm import mapper as sfm

pytest.importorskip("pycolmap")


def test_sfm_synthetic_accuracy_and_metric_scale(sfm_room):
    seq, prior = sfm_room
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="sfm", progress=False, keyframe_stride=3,
                         num_threads=1)
    assert res.poses.shape == (30, 4, 4) and np.isfinite(res.poses).all()
    d = res.diagnostics
    assert d["method"] == "sfm" and d["registered_keyframes"] == d["num_keyframes"] == 11  # every 3rd + the last
    # The other 19 frames were never seen by COLMAP: they are registered densely.
    status = d["frame_status"]
    assert set(status) <= set(FRAME_STATES)
    assert status.count("keyframe") == 11 and status.count("tracked") == 19
    assert d["lost_frames"] == [] and d["registered_fraction"] == 1.0
    inlier = np.array(d["frame_inlier"])
    model = np.array([s == "keyframe" for s in status])
    # Model frames: the share of their verified matches that the model explains, well above
    # the quality gate's floor (recon.poses.checks.quality: 0.25).
    assert inlier.shape == (30,) and ((inlier[model] > 0.4) & (inlier[model] <= 1.0)).all(), inlier[model]
    assert np.isnan(inlier[~model]).all() or ((inlier[~model] >= 0) & (inlier[~model] <= 1)).all()
    length = path_length(seq.poses)
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.01 * length
    assert scale_error(res.poses, seq.poses) <= 0.10
    assert abs(d["lens_k1"]) < 0.01  # a pinhole camera
    # The prior's depth follows the triangulated points' (recon.poses.checks.prior_agreement; 0.80 measured).
    agreement = d["prior_agreement"]
    assert agreement["judged"] and agreement["trusted"] and agreement["median"] > 0.7, agreement


def test_a_model_whose_scale_the_prior_contradicts_is_marked(sfm_room, caplog):
    """The prior of the room's frames 15-29 twice too far: SfM's map and the prior then
    disagree in scale from frame to frame beyond the prior's noise, and the model is marked
    (poses.scale_spread): the run warns once, and stops only under --on-break stop; with the
    check off (--on-break keep) it is not judged."""
    from types import SimpleNamespace

    from recon.core.stages import gate_estimate
    from recon.drivers.segments import check_scale_spread
    from recon.errors import ReconInputError

    seq, prior = sfm_room
    split = prior.copy()
    split[15:] *= 2.0
    marked = estimate_poses(seq.rgb, split, seq.intrinsics, method="sfm", progress=False, keyframe_stride=3,
                            num_threads=1)
    spread = marked.diagnostics["scale_spread"]
    assert not spread["consistent"] and spread["log_std"] > 0.25 and spread["factor"] == pytest.approx(
        np.exp(spread["log_std"]))
    _, info, _ = gate_estimate(marked, np.arange(len(seq.rgb)))
    assert info["scale_spread"] == spread
    with pytest.raises(ReconInputError, match="stopped .--on-break stop.: SfM's map and the depth prior disagree"):
        check_scale_spread(SimpleNamespace(on_break="stop"), info)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="recon"):
        check_scale_spread(SimpleNamespace(on_break="segments"), info)
    assert sum("may be at different scales" in r.getMessage() for r in caplog.records) == 1
    kept = estimate_poses(seq.rgb, split, seq.intrinsics, method="sfm", progress=False, keyframe_stride=3,
                          num_threads=1, max_scale_spread=0.0)
    assert kept.diagnostics["scale_spread"]["consistent"] and kept.diagnostics["scale_spread_log_std"] > 0.25


def test_sfm_estimates_the_lens_radial_term(sfm_room):
    """The room filmed through a barrel lens (k1 = -0.1): asked to (the intrinsics are given,
    so by default the lens is not estimated), COLMAP's SIMPLE_RADIAL camera finds it, and the
    frames it did not see are registered through it."""
    seq, prior = sfm_room
    rgb = distort_images(seq.rgb, seq.intrinsics, -0.1)
    depth = distort_images(prior, seq.intrinsics, -0.1, nearest=True)
    res = estimate_poses(rgb, depth, seq.intrinsics, method="sfm", progress=False, keyframe_stride=3,
                         num_threads=1, calibrate_lens=True)
    assert abs(res.diagnostics["lens_k1"] + 0.1) < 0.02, res.diagnostics["lens_k1"]
    assert res.diagnostics["frame_status"].count("tracked") == 19
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.01 * path_length(seq.poses)
    assert scale_error(res.poses, seq.poses) <= 0.10


def _grays(rgb: np.ndarray) -> tuple[list[np.ndarray], float]:
    geo = make_geometry(rgb.shape[1:3], sfm.SfMConfig().frontend.ba_stride)
    return [fl.prepare_gray(f, geo.flow_shape) for f in rgb], geo.px_scale


def test_keyframes_follow_the_motion(sfm_room):
    """The room moves ~4 px per frame (at 640 px width): at stride 1 about every 5th frame is
    a keyframe, in every 5th frame (~20 px per step) nearly all; max_keyframes caps the
    count, and a cut (unrelated frames) puts keyframes on both sides of it."""
    seq, _ = sfm_room
    cfg = sfm.SfMConfig(keyframe_motion=16.0)
    dense, spacing = sfm.choose_keyframes(*_grays(seq.rgb), cfg)
    assert spacing == 16.0 and dense[0] == 0 and dense[-1] == 29 and 5 <= len(dense) <= 9
    sparse, _ = sfm.choose_keyframes(*_grays(seq.rgb[::5]), cfg)
    assert len(sparse) >= 5  # of 6
    capped, spacing = sfm.choose_keyframes(*_grays(seq.rgb), sfm.SfMConfig(keyframe_motion=16.0, max_keyframes=4))
    assert len(capped) <= 4 and capped[0] == 0 and capped[-1] == 29 and spacing > 16.0
    noise = np.random.default_rng(0).integers(0, 256, (3, 240, 320, 3), dtype=np.uint8)
    cut, _ = sfm.choose_keyframes(*_grays(np.concatenate([seq.rgb[:12], noise])), cfg)
    assert {11, 12, 13, 14} <= set(cut)


def test_sfm_refuses_a_partial_model(sfm_room, monkeypatch):
    """The room followed by frames of noise: COLMAP registers the room only. With a lenient
    gate the noise frames are marked "interpolated" (their flow to the last room keyframe
    fails), not padded out as registered; with the default gate (80 %) the same COLMAP
    result fails, naming the noise frames."""
    seq, prior = sfm_room
    # The whole room (24 of its frames left COLMAP without a good initial pair) and one thread:
    # COLMAP's multi-threaded mapper does not give the same model twice.
    noise = np.random.default_rng(1).integers(0, 256, (12, 240, 320, 3), dtype=np.uint8)
    rgb = np.concatenate([seq.rgb, noise])
    depth = np.concatenate([prior, prior[:12]])
    colmap_runs = []
    run_colmap = sfm._run_colmap

    def once(*args):  # the same COLMAP result for both gates
        if not colmap_runs:
            colmap_runs.append(run_colmap(*args))
        return colmap_runs[0]

    monkeypatch.setattr(sfm, "_run_colmap", once)
    res = estimate_poses(rgb, depth, seq.intrinsics, method="sfm", progress=False, min_registered=0.5, num_threads=1)
    d = res.diagnostics
    # Every noise frame is left unregistered (with the last room frames past COLMAP's last
    # keyframe, which the one-spacing rule will not pad either); most of the room is in.
    n, kept = len(rgb), d["registered_frames"]
    assert len(seq.rgb) - 4 <= kept <= len(seq.rgb)
    assert d["lost_frames"] == list(range(kept, n)) and d["unregistered_ranges"] == [[kept, n - 1]]
    assert all(s in TRUSTED_STATES for s in d["frame_status"][:kept])
    # No evidence for them: no flow to align with (NaN), or an alignment that explains little.
    assert all(not (v >= 0.25) for v in d["frame_inlier"][36:]), d["frame_inlier"][36:]
    assert ate_rmse(res.poses[:kept], seq.poses[:kept], "sim3")["rmse"] <= 0.01 * path_length(seq.poses[:kept])
    with pytest.raises(TrackingLostError, match=rf"^SfM registered only {kept} of {n} frames \(.*\): frames "
                                                 rf"{kept}-{n - 1} could not be registered$") as err:
        estimate_poses(rgb, depth, seq.intrinsics, method="sfm", progress=False)
    assert err.value.frame == kept and len(colmap_runs) == 1


def test_sfm_failure_is_a_tracking_lost_error(capfd):
    frames = np.random.default_rng(0).integers(0, 256, (5, 120, 160, 3), dtype=np.uint8)
    prior = np.ones((5, 120, 160), dtype=np.float32)
    with pytest.raises(TrackingLostError, match=r"SfM registered only 0 of 5 frames \(0 of 5 keyframes in COLMAP's "
                                                r"model, 0 densely; need 80%\): frames 0-4 could not be registered"):
        estimate_poses(frames, prior, (150.0, 150.0, 79.5, 59.5), method="sfm", progress=False)
    # Our message is the whole story: COLMAP's own log lines (C++, straight to fd 2) stay out.
    assert capfd.readouterr().err == ""
