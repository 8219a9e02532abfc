"""The short-flow check (recon.poses.checks.normal_flow): Lucas-Kanade steps that find a shift on
texture and only its across-edge part on stripes, the slope that tells a shortened
translation from a right one, the pooling of keyframe pairs into flagged stretches, and the
front end marking the synthetic walk-through's plain corridor (said by the run, by video
frame, and on the timeline) but not the furnished room."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from recon.poses import estimate_poses
from recon.poses.checks.motion_checks import MotionChecks
from recon.poses.checks.normal_flow import NormalFlowConfig, gradient_flow, short_stretches, translation_slope
from recon.poses.matching import flow as fl

SHAPE = (96, 128)


def texture(seed: int = 0) -> np.ndarray:
    """A grey uint8 image (96, 128) of blurred noise: texture in every direction."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.uniform(0, 255, SHAPE).astype(np.float32), (0, 0), 1.5)
    return np.clip((noise - noise.mean()) * 4 + 128, 0, 255).astype(np.uint8)


def stripes() -> np.ndarray:
    """Vertical stripes: grey levels change along x only (every edge is vertical)."""
    x = np.arange(SHAPE[1], dtype=np.float32)
    row = 128 + 60 * np.sin(2 * np.pi * x / 14.0) + 30 * np.sin(2 * np.pi * x / 5.3)
    return np.clip(np.tile(row, (SHAPE[0], 1)), 0, 255).astype(np.uint8)


def moved(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """The image as a camera sees it after every pixel p moved by flow(p) (backward warp,
    exact for a smooth flow to first order)."""
    return fl.sample_along(image.astype(np.float32), -flow, borderMode=cv2.BORDER_REFLECT).astype(np.uint8)


def expansion(scale: float) -> np.ndarray:
    """A forward move's flow (h, w, 2): away from the centre, `scale` pixels at the border."""
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float32)
    cx, cy = (SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2
    return np.stack([(u - cx) / cx, (v - cy) / cx], -1) * scale


def test_gradient_flow_finds_a_shift_on_texture_and_only_its_across_edge_part_on_stripes():
    shift = np.broadcast_to(np.array([1.2, -0.8], np.float32), SHAPE + (2,)).copy()
    inner = (slice(12, -12), slice(12, -12))
    cfg = NormalFlowConfig()
    found = gradient_flow(texture(), moved(texture(), shift), np.zeros_like(shift), cfg)
    assert np.median(np.abs(found[inner] - shift[inner])) < 0.1
    found = gradient_flow(stripes(), moved(stripes(), shift), np.zeros_like(shift), cfg)
    assert np.median(np.abs(found[inner][..., 0] - 1.2)) < 0.1  # across the edges: measured
    assert np.abs(found[inner][..., 1]).max() < 1e-3  # along them: nothing to go on, left as it was


def test_translation_slope_is_one_for_the_right_steps_and_more_for_shortened_ones():
    true = expansion(2.0)
    rotation = np.zeros_like(true)
    valid = np.ones(SHAPE, bool)
    valid[:8], valid[-8:], valid[:, :8], valid[:, -8:] = False, False, False, False
    cfg = NormalFlowConfig()
    for image in (texture(1), stripes()):
        after = moved(image, true)
        right = np.divide(*translation_slope(image, after, rotation, true, valid, cfg))
        short = np.divide(*translation_slope(image, after, rotation, 0.6 * true, valid, cfg))
        assert abs(right - 1.0) < 0.05
        # The BA's steps at 0.6 of the truth: the gradients say about 1 / 0.6 = 1.67 (on the
        # stripes from the across-edge half of the flow alone), well past the check's 1.2.
        assert 1.4 < short < 1.8, (image is texture, short)


def test_short_stretches_pool_judged_pairs_and_flag_windows_past_the_slope():
    cfg = NormalFlowConfig(pairs=3, min_pairs=2, max_slope=1.2)
    den = np.ones(10)
    slope = np.array([1.0, 1.02, 0.98, 1.5, 1.4, 1.45, 1.0, 1.01, 1.6, 0.99])
    judged = np.ones(10, bool)
    judged[8] = False  # a lone steep pair without translation to judge: not counted
    stretches, largest = short_stretches(slope * den, den, judged, cfg)
    assert stretches == [(3, 5)]
    assert largest == pytest.approx(1.45)
    # One right pair inside a shortened stretch does not split it.
    slope[4] = 0.95
    assert short_stretches(slope * den, den, judged, cfg)[0] == [(3, 5)]
    assert short_stretches(slope * den, den, np.zeros(10, bool), cfg) == ([], pytest.approx(np.nan, nan_ok=True))


@pytest.fixture(scope="module")
def corridor():
    """Frames 60-149 of the synthetic walk-through at 320x240 (room A's end, then the plain
    corridor from frame 86) and a simulated prior."""
    from recon.synthetic import simulate_prior
    from recon.synthetic.walkthrough import render_walkthrough, walkthrough_plan

    plan = walkthrough_plan(seed=0)
    walk = render_walkthrough(320, 240, seed=0, frames=np.arange(60, 150))
    return walk, simulate_prior(walk.depth, seed=1), plan.stretches["textureless"]


@pytest.fixture(scope="module")
def corridor_result(corridor):
    walk, prior, _ = corridor
    return estimate_poses(walk.rgb, prior, walk.intrinsics, method="frontend", progress=False)


def test_the_front_end_marks_the_plain_corridor_short(corridor, corridor_result):
    _, _, (plain_start, plain_stop) = corridor
    res = corridor_result
    checks = res.diagnostics["motion_checks"]
    assert checks["short_flow"], f"no stretch marked (largest slope {checks['short_flow_slope']:.2f})"
    for first, last in checks["short_flow"]:  # positions in the 90 frames, 0 = walk frame 60
        assert plain_start - 60 - 8 <= first and last <= plain_stop - 60, (first, last)
    said = MotionChecks.from_dict(checks).short_said()
    assert said.startswith(f"frames {checks['short_flow'][0][0]}-") and "made the camera's steps short" in said


def test_the_front_end_marks_nothing_in_the_furnished_room(pose_room):
    seq, prior = pose_room
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    checks = res.diagnostics["motion_checks"]
    assert checks["short_flow"] == [] and checks["short_flow_slope"] < 1.1


def test_the_run_says_the_marked_frames_by_their_video_numbers(corridor_result, caplog):
    from recon.core.stages import gate_estimate

    frames = np.arange(1000, 1090)  # the 90 frames as a selection of a longer video
    with caplog.at_level(logging.WARNING):
        _, info, _ = gate_estimate(corridor_result, frames)
    first, last = info["motion_checks"]["short_flow"][0]
    assert 1000 <= first < last < 1090
    assert any(f"frames {first}-{last}" in r.getMessage() and "poses.motion_checks" in r.getMessage()
               for r in caplog.records)
    verdicts = info["motion_checks"]["frame_verdicts"]
    assert verdicts[first - 1000] == "flow short" and verdicts.count("flow short") == last - first + 1
