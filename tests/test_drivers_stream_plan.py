"""The streamed pipeline's rules: depth frames by motion, windows, the scale anchor."""

from __future__ import annotations

import numpy as np
import pytest

from recon.drivers.stream_plan import (
    MotionSelector,
    anchor_factor,
    depth_gap,
    parse_depth_frames,
    plan_windows,
    select_later,
)


def _walk(steps: np.ndarray, turns_deg: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world poses moving along x by `steps` (metres) and turning about y."""
    poses = np.repeat(np.eye(4)[None], len(steps), axis=0)
    poses[:, 0, 3] = np.cumsum(steps)
    if turns_deg is not None:
        angles = np.radians(np.cumsum(turns_deg))
        c, s = np.cos(angles), np.sin(angles)
        poses[:, 0, 0], poses[:, 0, 2], poses[:, 2, 0], poses[:, 2, 2] = c, s, -s, c
    return poses


def test_motion_rule_takes_a_frame_per_distance_relative_to_depth():
    poses = _walk(np.full(200, 0.011))  # 1.1 cm per frame, 2 m away: 2 % of depth = 4 cm
    select = MotionSelector(motion=0.02, rotation=90.0)
    taken = np.flatnonzero([select(p, 2.0) for p in poses])
    assert taken[0] == 0
    assert np.all(np.diff(taken) == 4)
    # Twice as far away: half as many frames.
    select = MotionSelector(motion=0.02, rotation=90.0)
    assert sum(select(p, 4.0) for p in poses) == pytest.approx(len(taken) / 2, abs=1)


def test_motion_rule_takes_frames_when_turning_on_the_spot():
    poses = _walk(np.zeros(60), np.full(60, 0.6))  # pure rotation, 0.6 degree per frame
    select = MotionSelector(motion=0.02, rotation=2.0)
    taken = np.flatnonzero([select(p, 2.0) for p in poses])
    assert np.all(np.diff(taken) == 4)
    still = MotionSelector(motion=0.02, rotation=2.0)
    assert sum(still(np.eye(4), 2.0) for _ in range(50)) == 1  # a camera that never moves: one frame


def test_every_kth_frame_and_choices():
    select = MotionSelector(step=3)
    assert [select(np.eye(4), 1.0) for _ in range(7)] == [True, False, False, True, False, False, True]
    assert parse_depth_frames("motion") is None and parse_depth_frames("all") == 1 and parse_depth_frames("5") == 5


@pytest.mark.parametrize("count", [2, 30, 48, 49, 100, 901])
def test_windows_cover_every_frame_once_with_the_overlap(count):
    windows = plan_windows(count, 48, 8)
    assert all(w.stop - w.start <= 48 for w in windows)
    new = np.concatenate([np.arange(w.new, w.stop) for w in windows])
    assert np.array_equal(new, np.arange(count))  # each frame finished by exactly one window
    assert windows[0].shared == 0 and all(w.shared == 8 for w in windows[1:])
    sizes = [w.stop - w.start for w in windows]
    assert max(sizes) - min(sizes) <= 2  # no sliver at the end


def test_anchor_factor_is_the_median_ratio_and_ignores_invalid_pixels():
    rng = np.random.default_rng(0)
    current = rng.uniform(1, 3, (3, 20, 20)).astype(np.float32)
    finished = current * 1.07
    finished[0, :5] = 0  # invalid in one of the two
    finished[1, :2] *= 5  # outliers do not move a median
    assert anchor_factor(finished, current) == pytest.approx(1.07, rel=1e-5)
    assert anchor_factor(np.zeros_like(current), current) == 1.0


def test_a_still_camera_still_gets_the_floor_of_depth_frames():
    count = 80
    still = MotionSelector(motion=0.02, rotation=2.0, max_gap=depth_gap(count, 30))
    taken = np.flatnonzero([still(np.eye(4), 2.0) for _ in range(count)])
    assert len(taken) >= 30 and np.all(np.diff(taken) == 2)
    assert still.by_gap == len(taken) - 1  # the first frame is motion's
    # A moving camera takes its frames by motion; the floor adds none.
    poses = _walk(np.full(count, 0.011))
    moving = MotionSelector(motion=0.02, rotation=90.0, max_gap=depth_gap(count, 10))
    assert np.all(np.diff(np.flatnonzero([moving(p, 2.0) for p in poses])) == 4) and moving.by_gap == 0


def test_depth_gap_bounds_the_frames_between_depth_frames():
    assert depth_gap(80, 40) == 2 and depth_gap(100, 40) == 2 and depth_gap(30, 40) == 1
    assert depth_gap(300, 40) == 7 and depth_gap(100, 0) is None and depth_gap(0, 40) is None


def test_frames_posed_later_are_chosen_as_the_rule_would_have_in_order():
    # The 80 frames a focal search buffered, walking 1.1 cm a frame 2 m away: every 4th by
    # motion, as if they had been posed while tracked; a frame without a pose is left out.
    poses = _walk(np.full(80, 0.011))
    poses[41] = np.nan
    asked = []
    taken, by_gap = select_later(poses, lambda k: asked.append(k) or 2.0, 0.02, 2.0)
    live = MotionSelector(motion=0.02, rotation=2.0)
    expected = np.array([live(p, 2.0) for p in poses])
    assert np.array_equal(taken, expected) and not taken[41] and by_gap == 0
    assert taken[0] and 18 <= taken.sum() <= 21
    assert asked == np.flatnonzero(taken).tolist()  # the depth of the frames taken alone
    # The floor and a step apply as while tracking; a still camera gets the floor's frames.
    still, by_gap = select_later(np.repeat(np.eye(4)[None], 80, 0), lambda k: 2.0, 0.02, 2.0,
                                 max_gap=depth_gap(80, 30))
    assert np.all(np.diff(np.flatnonzero(still)) == 2) and by_gap == still.sum() - 1
    every_third, _ = select_later(poses, lambda k: 2.0, 0.02, 2.0, step=3)
    assert np.array_equal(np.flatnonzero(every_third), np.arange(0, 80, 3))
    assert select_later(np.zeros((0, 4, 4)), lambda k: 2.0, 0.02, 2.0)[0].shape == (0,)
