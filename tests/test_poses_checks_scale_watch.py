"""The map-against-prior scale check (recon.poses.checks.scale_watch): a step the prior's noise
cannot explain is found where it is, with its factor; noise alone, a constant offset or a
short run is not called a break."""

import numpy as np
import pytest

from recon.poses.checks.scale_watch import (
    ScaleWatchConfig,
    keyframe_log_ratios,
    log_noise,
    smooth_log_ratio,
    watch_scale,
)


def _keyframes(log_scale: np.ndarray, seed: int = 0, noise: float = 0.08, shape=(12, 16)):
    """Map and prior inverse depths of K keyframes: the prior a room's depth with a per-keyframe
    log-normal scale error (`noise`) and per-pixel error; the map the true depth divided by
    exp(log_scale[k]) (its scale against the truth, per keyframe)."""
    rng = np.random.default_rng(seed)
    K = len(log_scale)
    depth = rng.uniform(1.0, 4.0, (K, *shape))
    prior = depth * np.exp(rng.normal(0, noise, (K, 1, 1)) + rng.normal(0, 0.15, (K, *shape)))
    mapped = depth * np.exp(np.asarray(log_scale))[:, None, None]
    valid = rng.uniform(size=(K, *shape)) > 0.1
    return 1.0 / mapped, 1.0 / prior, valid


def test_the_ratio_is_the_median_over_valid_pixels():
    map_disp = np.full((2, 3, 3), 2.0)
    prior_disp = np.ones((2, 3, 3))
    prior_disp[0, 0, 0] = 1e-3  # an outlier pixel: the median ignores it
    valid = np.ones((2, 3, 3), bool)
    valid[1] = False
    ratio = keyframe_log_ratios(map_disp, prior_disp, valid)
    assert ratio[0] == pytest.approx(np.log(2.0)) and np.isnan(ratio[1])


def test_a_step_is_found_where_it_is_with_its_factor():
    """The HoloLens walk-through's second stretch came back at 0.66 of the first's scale."""
    log_scale = np.r_[np.zeros(30), np.full(30, np.log(0.66))]
    frames = np.arange(60) * 4 + 10
    watch = watch_scale(*_keyframes(log_scale), frames)
    assert watch.judged and len(watch.breaks) == 1
    b = watch.breaks[0]
    assert b.after == frames[30] and b.before == frames[29] and b.factor == pytest.approx(0.66, rel=0.08)
    assert 0.04 < watch.noise < 0.14  # the prior's 8 % per keyframe, measured from the run
    verdicts = watch.frame_verdicts(frames[-1] + 1)
    assert verdicts[b.before] == "ok" and verdicts[b.after] == "after break 1" and verdicts[-1] == "after break 1"
    assert "x0.6" in watch.describe() and str(b.after) in watch.describe()


def test_two_steps_both_ways():
    """Scale 1 -> 0.66 -> 7.1 -> 0.5 (the walk-through's stretches): three breaks, in order."""
    log_scale = np.log(np.r_[np.ones(20), np.full(15, 0.66), np.full(15, 4.7), np.full(20, 2.4)])
    watch = watch_scale(*_keyframes(log_scale, seed=3), np.arange(70))
    assert [b.after for b in watch.breaks] == pytest.approx([20, 35, 50], abs=2)
    assert [b.factor for b in watch.breaks] == pytest.approx([0.66, 4.7 / 0.66, 2.4 / 4.7], rel=0.1)


@pytest.mark.parametrize("seed", range(5))
def test_noise_and_a_constant_offset_are_no_break(seed):
    """A map at a constant 0.4 of the prior's scale (the rescale takes that out) with the
    prior's per-keyframe noise: no break, on any of five draws."""
    watch = watch_scale(*_keyframes(np.full(80, np.log(0.4)), seed=seed, noise=0.12), np.arange(80))
    assert watch.breaks == [] and np.median(watch.ratio) == pytest.approx(1.0, rel=1e-3)


def test_a_small_step_is_no_break_however_clean():
    """A 10 % step is within what the prior's scale error does over a video: not a break,
    even without noise."""
    watch = watch_scale(*_keyframes(np.r_[np.zeros(30), np.full(30, np.log(0.9))], noise=0.0), np.arange(60))
    assert watch.breaks == []


def test_a_creep_is_found_as_drift_breaks_where_it_has_crept():
    """The synthetic walk-through's corridor: no step, but the map shrinks to 0.4 of its
    scale over 60 keyframes after 20 steady ones. Drift breaks follow the creep, each where the
    smoothed ratio has moved x1.3 since the last, none in the steady start, so that no stretch
    between them spans much more than x1.3 of the map's true scale (the whole run: x2.5)."""
    log_scale = np.r_[np.zeros(20), np.linspace(0, np.log(0.4), 60)]
    watch = watch_scale(*_keyframes(log_scale, seed=2), np.arange(80))
    assert len(watch.breaks) >= 2 and all(b.kind == "drift" for b in watch.breaks)
    assert min(b.after for b in watch.breaks) > 20
    assert all(0.7 < b.factor < 0.8 for b in watch.breaks)  # 1 / 1.3, give or take a keyframe's creep
    bounds = [0, *[b.after for b in watch.breaks], 80]
    spans = [np.exp(np.ptp(log_scale[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]
    assert max(spans) < 1.45
    assert "creeps x0.7" in watch.describe()
    # Switched off, the same creep gives no break: the step test alone does not see it.
    assert watch_scale(*_keyframes(log_scale, seed=2), np.arange(80), ScaleWatchConfig(drift_share=0)).breaks == []


def test_the_smoothed_ratio_follows_a_trend_and_averages_the_noise():
    rng = np.random.default_rng(4)
    trend = np.linspace(0.0, 0.8, 200)
    noisy = trend + rng.normal(0, 0.2, 200)
    noisy[50] += 3.0  # one keyframe whose prior is far off: the Huber weights keep it from pulling
    smooth = smooth_log_ratio(noisy, 0.2, 0.1)
    assert np.abs(smooth - trend).max() < 0.12 and np.abs(noisy - trend).std() > 0.2
    assert smooth_log_ratio(noisy[:1], 0.2, 0.1).tolist() == [noisy[0]]


def test_too_few_keyframes_are_not_judged():
    watch = watch_scale(*_keyframes(np.r_[np.zeros(7), np.full(7, np.log(0.3))]), np.arange(14))
    assert not watch.judged and watch.breaks == []
    assert watch_scale(*_keyframes(np.zeros(40)), np.arange(40), ScaleWatchConfig(min_keyframes=50)).judged is False


def test_noise_is_measured_from_neighbouring_keyframes():
    rng = np.random.default_rng(1)
    steady = rng.normal(0, 0.1, 2000)
    assert log_noise(steady) == pytest.approx(0.1, rel=0.08)
    stepped = steady + np.r_[np.zeros(1000), np.full(1000, 1.0)]
    assert log_noise(stepped) == pytest.approx(0.1, rel=0.08)  # one step, one outlier difference


def test_the_pipeline_says_a_break_in_the_videos_frame_numbers(caplog):
    """recon.core.stages.gate_estimate renames the front end's frame positions to the video's frame
    numbers (a run from frame 100, every 2nd frame), warns once, and puts each frame's verdict
    in report.json and on the tracking timeline."""
    import logging
    from types import SimpleNamespace

    from recon.core.stages import PoseStage, gate_estimate, tracking_states
    from recon.poses.result import PoseResult

    n = 60
    watch = watch_scale(*_keyframes(np.r_[np.zeros(30), np.full(30, np.log(0.5))]), np.arange(n))
    result = PoseResult(np.tile(np.eye(4), (n, 1, 1)), (500.0, 500.0, 320.0, 240.0), np.arange(n), 1.0,
                        {"method": "frontend", "frame_status": ["tracked"] * n, "scale_watch": watch.to_dict()})
    video_frames = np.arange(100, 100 + 2 * n, 2)
    with caplog.at_level(logging.WARNING, logger="recon"):
        kept, info, _ = gate_estimate(result, video_frames)
    said = [r.getMessage() for r in caplog.records if "scale" in r.getMessage()]
    assert kept.all() and len(said) == 1 and "by frames 158-160" in said[0]
    assert "scale_watch" not in info["diagnostics"]
    assert info["scale_watch"]["breaks"][0]["after"] == 160 and info["scale_watch"]["frames"][0] == 100
    assert info["scale_watch"]["frame_verdicts"][29:31] == ["ok", "after break 1"]
    stage = PoseStage(result.poses, result.intrinsics, "estimated", {**info, "frame_status": ["tracked"] * n})
    states = tracking_states(stage, SimpleNamespace(indices=video_frames))
    assert states[29][1] == "tracked" and states[30][:2] == (160, "tracked; scale after break 1")


def test_a_stretch_after_a_break_is_brought_to_the_scale_before_it():
    """recon.poses.frontend.backend.rescale_stretches: a camera walking 1 m a frame along x, mapped at
    half that after frame 9 (turned 30 degrees, which the rescale keeps), comes back at 1 m a
    frame throughout; the keyframes' depth after the break doubles with it, the rest stays."""
    from types import SimpleNamespace

    import torch

    from recon.poses.ba.graph import FrameGraph
    from recon.poses.frontend import backend

    def T_cw(centre, yaw):
        c, s = np.cos(yaw), np.sin(yaw)
        R = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)  # camera-to-world rotation
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3], T[:3, 3] = R.T, -R.T @ torch.tensor(centre, dtype=torch.float64)
        return T

    x = np.where(np.arange(20) <= 9, np.arange(20), 9 + 0.5 * (np.arange(20) - 9))
    yaw = np.where(np.arange(20) <= 9, 0.0, np.pi / 6)
    graph = FrameGraph((2, 2))
    frame_T = {}
    for i in range(20):
        frame_T[i] = T_cw([x[i], 0.0, 0.0], yaw[i])
        if i % 3 == 0:
            graph.add_keyframe(i, None, frame_T[i], torch.full((2, 2), 0.5), torch.ones(2, 2), torch.ones(2, 2))
    state = SimpleNamespace(graph=graph, frame_T=frame_T, frame_ratios={4: 1.0, 13: 2.0})
    backend.rescale_stretches(state, [(9, 2.0)])
    centres = np.array([(-state.frame_T[i][:3, :3].T @ state.frame_T[i][:3, 3]).numpy() for i in range(20)])
    np.testing.assert_allclose(centres[:, 0], np.arange(20), atol=1e-12)
    np.testing.assert_allclose(centres[:, 1:], 0.0, atol=1e-12)
    for i in range(20):  # rotations untouched
        np.testing.assert_allclose(state.frame_T[i][:3, :3].numpy(), T_cw([0, 0, 0], yaw[i])[:3, :3].numpy())
    kf_centres = [float(-(T[:3, :3].T @ T[:3, 3])[0]) for T in graph.poses()]
    assert kf_centres == pytest.approx(list(range(0, 20, 3)))
    assert [float(d[0, 0]) for d in graph.disps()] == pytest.approx([0.5] * 4 + [0.25] * 3)
    assert state.frame_ratios == {4: 1.0, 13: 1.0}


def test_stretch_factors_are_the_stretches_medians():
    from recon.poses.checks.scale_watch import ScaleBreak, stretch_factors

    log_ratio = np.r_[np.zeros(10), np.full(10, np.log(2.0)), np.full(10, np.log(0.5))]
    frames = np.arange(30) * 2
    breaks = [ScaleBreak(18, 20, 0.5, 9.0), ScaleBreak(38, 40, 4.0, 9.0)]
    assert stretch_factors(log_ratio, frames, breaks) == pytest.approx([2.0, 0.25])


def test_a_step_where_the_camera_turns_on_the_spot_is_not_a_break():
    """Inside a rotation-only stretch the map has no scale to break: the step is kept apart
    (``turning``) with its correction, and said by frame as the breaks are; a step outside
    stays a break."""
    from recon.poses.checks.scale_watch import ScaleBreak, ScaleWatch

    watch = ScaleWatch(list(range(0, 60, 3)), [1.0] * 20, 0.05,
                       [ScaleBreak(9, 12, 1.6, 8.0), ScaleBreak(42, 45, 0.7, 7.0)], corrections=[0.6, 1.4])
    kept = watch.without_turns([[0, 30]])
    assert [b.before for b in kept.breaks] == [42] and kept.corrections == [1.4]
    assert [b.before for b in kept.turning] == [9]
    again = ScaleWatch.from_dict(kept.renumbered(list(range(100, 160))).to_dict())
    assert again.turning[0].before == 109 and again.breaks[0].after == 145
    assert watch.without_turns([]).breaks == watch.breaks
