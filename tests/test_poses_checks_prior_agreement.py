"""Whether the depth prior's metric scale is trusted (recon.poses.checks.prior_agreement): the
correlation of its log depth with the map's, keyframe by keyframe, its verdict, and what the
front end, SfM and the quality gate's report make of it."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from recon.poses import estimate_poses
from recon.poses.checks import prior_agreement as pa
from recon.poses.result import PoseResult


def _scene(k=6, h=24, w=32, seed=0):
    """(K, h, w) depth maps of slanted planes 1-4 m away, different per keyframe."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    return np.stack([1.0 + 3.0 * (a * u + (1 - a) * v) for a in rng.uniform(0.2, 0.8, k)])


def test_a_prior_that_follows_the_scene_at_another_scale_correlates():
    depth = _scene()
    rng = np.random.default_rng(1)
    prior = 2.5 * depth * np.exp(rng.normal(0, 0.05, depth.shape))  # a wrong scale, 5 % noise
    corr, spread, pixels = pa.log_depth_correlation(depth, prior, np.ones(depth.shape, bool))
    assert (corr > 0.95).all() and np.allclose(spread, np.log(depth).reshape(6, -1).std(1))
    assert (pixels == 24 * 32).all()
    verdict = pa.judge_agreement(range(6), corr, spread, pixels)
    assert verdict.judged and verdict.trusted and verdict.median > 0.95


def test_a_prior_that_sees_another_scene_is_not_trusted():
    """Depth that falls where the scene's rises (the door handle's close-up against SfM's
    points) and depth unrelated to it."""
    depth = _scene()
    mirrored = np.median(depth) ** 2 / depth
    unrelated = _scene(seed=7)[:, ::-1, ::-1]
    for prior in (mirrored, unrelated):
        verdict = pa.judge_agreement(range(6), *pa.log_depth_correlation(depth, prior, np.ones(depth.shape, bool)))
        assert verdict.judged and not verdict.trusted and verdict.median < 0.4, verdict.median
    assert "several times" in verdict.refusal() and "--on-break stop" in verdict.refusal()
    assert "not to be trusted" in verdict.said() and "--on-break stop refuses" in verdict.said()


def test_only_measured_pixels_and_keyframes_that_can_tell_count():
    depth = _scene()
    prior = depth.copy()
    measured = np.zeros(depth.shape, bool)
    measured[:, :, :16] = True
    prior[:, :, 16:] = 1.0 / prior[:, :, 16:]  # wrong only where nothing was measured
    corr, spread, pixels = pa.log_depth_correlation(depth, prior, measured)
    assert np.allclose(corr, 1.0) and (pixels == 24 * 16).all()
    # A wall seen face on (depth within +-1 %) cannot tell; three such keyframes are not judged.
    flat = np.full((3, 24, 32), 2.0) * (1 + 0.01 * np.random.default_rng(2).standard_normal((3, 24, 32)))
    verdict = pa.judge_agreement(range(3), *pa.log_depth_correlation(flat, 1 / flat, np.ones(flat.shape, bool)))
    assert verdict.frames == [] and not verdict.judged and verdict.trusted
    # Nor do keyframes with too few measured pixels or prior depth.
    sparse = np.zeros(depth.shape, bool)
    sparse[:, 0, :10] = True
    assert pa.judge_agreement(range(6), *pa.log_depth_correlation(depth, 1 / depth, sparse)).frames == []


def test_sfm_points_are_judged_the_same_way():
    rng = np.random.default_rng(3)
    z = rng.uniform(0.2, 0.4, 500)
    assert pa.point_log_correlation(z, 5 * z)[0] == pytest.approx(1.0)
    corr, spread, count = pa.point_log_correlation(z, 0.3 / z * rng.uniform(0.9, 1.1, 500))
    assert corr < -0.8 and spread == pytest.approx(np.log(z).std()) and count == 500


def test_the_front_end_trusts_a_prior_that_follows_the_room_and_not_one_that_does_not(pose_room):
    """The synthetic room with its simulated prior (2.5 % scale error, smooth field, noise):
    trusted (0.84 in the median over its keyframes). With each prior map upside down (the
    ceiling where the floor is), the depth the flow measures still follows the room, and the
    prior is not trusted (0.28)."""
    seq, prior = pose_room
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    ok = res.diagnostics["prior_agreement"]
    assert ok["judged"] and ok["trusted"] and ok["median"] > 0.8 and len(ok["frames"]) >= 4, ok
    upside_down = prior[:, ::-1].copy()
    res = estimate_poses(seq.rgb, upside_down, seq.intrinsics, method="frontend", progress=False)
    bad = res.diagnostics["prior_agreement"]
    assert bad["judged"] and not bad["trusted"] and bad["median"] < 0.35, bad


def test_the_gate_reports_by_video_frame_and_the_run_stops_unless_kept(caplog):
    """recon.core.stages.gate_estimate puts the verdict in report.json's poses.metric_scale,
    keyframes named by video frame; recon.drivers.segments warns once of a run whose prior is
    not trusted (the result is written, marked), and stops it only under --on-break stop,
    with one line naming the frames."""
    from types import SimpleNamespace

    from recon.core.stages import gate_estimate
    from recon.drivers.segments import settle_breaks, untrusted_scale
    from recon.errors import ReconInputError

    n = 8
    poses = np.tile(np.eye(4), (n, 1, 1))
    video = [10 + 2 * i for i in range(n)]
    stretch = np.zeros(n, np.int64)
    for corr in (0.9, -0.5):
        verdict = pa.judge_agreement([0, 3, 6], [corr] * 3, [0.3] * 3, [500] * 3)
        result = PoseResult(poses, (100.0, 100.0, 50.0, 40.0), np.array([0, 3, 6]), 1.0,
                            {"frame_status": ["keyframe"] * n, "prior_agreement": verdict.to_dict()})
        kept, info, _ = gate_estimate(result, video)
        assert kept.all() and info["metric_scale"]["frames"] == [10, 16, 22]
        assert info["metric_scale"]["trusted"] is (corr > 0) and "prior_agreement" not in info["diagnostics"]
        # Each verdict once in report.json: the frame states too (poses.frame_status only).
        assert info["frame_status"] == ["keyframe"] * n and "frame_status" not in info["diagnostics"]
        for on_break in ("segments", "stop", "keep"):
            config = SimpleNamespace(on_break=on_break, join_segments=True)
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="recon"):
                if corr < 0 and on_break == "stop":
                    with pytest.raises(ReconInputError, match="does not follow the scene's geometry at frames 10-22"):
                        settle_breaks(config, stretch, poses, np.arange(n), None, None, info)
                    continue
                settle_breaks(config, stretch, poses, np.arange(n), None, None, info)
            said = [r.getMessage() for r in caplog.records if "does not follow the scene" in r.getMessage()]
            assert len(said) == int(corr < 0) and (not said or "poses.metric_scale" in said[0])
            assert untrusted_scale(info) is (corr < 0)


def test_pieces_are_judged_together_by_their_keyframes():
    """recon.poses.frontend.pieces merges the pieces' verdicts: every counted keyframe, renumbered, one median."""
    first = pa.judge_agreement([0, 4, 8], [0.9, 0.8, 0.85], [0.3] * 3, [500] * 3)
    second = pa.judge_agreement([0, 5], [0.1, 0.2], [0.3] * 2, [500] * 2).renumbered({0: 20, 5: 25})
    assert not second.judged and second.frames == [20, 25]
    both = pa.joined([first, second])
    assert both.frames == [0, 4, 8, 20, 25] and both.median == pytest.approx(0.8) and both.judged and both.trusted
