"""The front end's checks of its own motion (recon.poses.checks.motion_checks): rotation-only
stretches, frames farther apart than dense flow follows, the lens at its bound."""

import numpy as np
from scipy.spatial.transform import Rotation

from recon.poses.checks.motion_checks import (
    MotionCheckConfig,
    MotionChecks,
    check_motion,
    keyframe_motion,
    rotation_only_stretches,
)

F, WIDTH = 500.0, 640


def _poses(turn_deg: np.ndarray, step_m: np.ndarray) -> np.ndarray:
    """World-to-camera poses of a camera yawing by turn_deg (N,) cumulatively and moving
    step_m (N,) along x."""
    angles = np.radians(np.cumsum(turn_deg))
    positions = np.cumsum(step_m)
    T_wc = np.tile(np.eye(4), (len(angles), 1, 1))
    T_wc[:, :3, :3] = Rotation.from_euler("y", angles[:, None]).as_matrix()
    T_wc[:, 0, 3] = positions
    return np.linalg.inv(T_wc)


def test_keyframe_motion_measures_the_flow_of_each_part():
    """A 1 degree turn is f * 0.01745 px of flow; a 2 cm step at 2 m depth is f * 0.01 px."""
    T = _poses(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 0.02]))
    depth = np.full((3, 4, 4), 2.0)
    rot, trans = keyframe_motion(T, depth, F)
    np.testing.assert_allclose(rot, [F * np.radians(1.0), 0.0], atol=1e-6)
    np.testing.assert_allclose(trans, [0.0, F * 0.01], atol=1e-6)


def test_a_camera_turned_on_the_spot_is_rotation_only_and_a_walk_is_not():
    """Between keyframes 10-19 the camera turns 3 degrees a keyframe and moves 1 mm (TUM
    fr1/rpy's kind of motion); elsewhere it walks 5 cm a keyframe and turns 1 degree."""
    turn = np.r_[np.ones(10), 3.0 * np.ones(10), np.ones(10)]
    step = np.r_[0.05 * np.ones(10), 0.001 * np.ones(10), 0.05 * np.ones(10)]
    rot, trans = keyframe_motion(_poses(turn, step), np.full((30, 2, 2), 2.0), F)
    stretches = rotation_only_stretches(rot, trans, MotionCheckConfig())
    assert len(stretches) == 1
    first, last = stretches[0]
    assert 9 <= first <= 10 and 18 <= last <= 19
    walking = keyframe_motion(_poses(np.ones(30), 0.05 * np.ones(30)), np.full((30, 2, 2), 2.0), F)
    walk = rotation_only_stretches(*walking, MotionCheckConfig())
    assert walk == []


def test_check_motion_names_what_makes_a_trajectory_untrusted():
    """A lens fit on its bound and (the camera unknown) a run whose frames lie over 10 % of
    the width apart are each said; with the camera known, the last is only marked; a
    rotation-only run is marked and said, never distrusted (its rotations are measured); a
    slow walk with a free lens says nothing."""
    n = 40
    slow = _poses(0.2 * np.ones(n), 0.01 * np.ones(n))
    depth = np.full((n, 2, 2), 2.0)
    ok = check_motion(slow, depth, np.arange(n), slow, F, WIDTH, lens_k1=0.05, k1_bound=0.5)
    assert ok.untrusted() == [] and not ok.moves_too_fast and ok.frame_verdicts(n) == ["ok"] * n
    fast = _poses(10.0 * np.ones(n), 0.3 * np.ones(n))
    verdict = check_motion(fast[::1], depth, np.arange(n), fast, F, WIDTH, lens_k1=0.5, k1_bound=0.5)
    # Frames far apart are judged only with the camera unknown (TUM fr1/rpy at stride 8, its
    # intrinsics given, tracks; the phone's images, focal estimated, did not); the lens always.
    assert verdict.moves_too_fast and verdict.lens_at_bound and len(verdict.untrusted()) == 2
    assert "width apart" in verdict.untrusted()[1] and "between 1 and 39" in verdict.untrusted()[1]
    assert len(verdict.untrusted(focal_estimated=False)) == 1
    assert verdict.median_step_share > 0.1 and set(verdict.frame_verdicts(n)[1:]) == {"large motion"}
    spin = _poses(2.0 * np.ones(n), 0.0005 * np.ones(n))
    turned = check_motion(spin, depth, np.arange(n), spin, F, WIDTH)
    assert turned.rotation_only == [[0, n - 1]] and turned.translation_share < 0.05 and turned.turns_on_the_spot
    assert turned.untrusted() == [] and turned.untrusted(focal_estimated=False) == []
    assert "turns on the spot (its translation makes 1 % of" in turned.turning_said()
    assert "its path and the map's scale there are not" in turned.turning_said()
    # A walk that stops to look around for a quarter of its frames: marked, not judged.
    pause = _poses(np.r_[0.5 * np.ones(15), 3.0 * np.ones(10), 0.5 * np.ones(15)],
                   np.r_[0.03 * np.ones(15), 0.0005 * np.ones(10), 0.03 * np.ones(15)])
    looked = check_motion(pause, depth, np.arange(n), pause, F, WIDTH)
    assert len(looked.rotation_only) == 1 and not looked.turns_on_the_spot and looked.untrusted() == []
    assert looked.turning_said().startswith("frames 14-24: the camera turns on the spot: its rotations")
    assert "rotation only" in looked.frame_verdicts(n)[15:25]
    again = MotionChecks.from_dict(turned.to_dict()).renumbered(list(range(100, 100 + n)))
    assert again.rotation_only == [[100, 100 + n - 1]]


def test_stretches_are_named_as_every_other_frame_range():
    """'a-b' for a stretch, 'a' for a single frame, the rest counted after the first four."""
    checks = MotionChecks(short_flow=[[3, 3], [10, 14], [20, 21], [30, 30], [40, 44], [50, 52]], short_flow_slope=1.4)
    said = checks.short_said()
    assert said.startswith("frames 3, 10-14, 20-21, 30 and 2 more: the dense flow made the camera's steps short")
    turned = MotionChecks(rotation_only=[[7, 7]], turns_on_the_spot=True, translation_share=0.05)
    assert turned.turning_said().startswith("frames 7: the camera turns on the spot (its translation makes 5 %")
