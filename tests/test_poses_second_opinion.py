"""A second opinion on an estimated trajectory (recon.poses.second_opinion): the front end and
SfM compared under the Sim(3) that best aligns them, per stretch, and the verdict."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.poses.second_opinion import SecondOpinion, doubts, second_opinion, stretches, trajectory_agreement


def _walk(n: int = 30) -> np.ndarray:
    """Camera-to-world poses along a curved 3 m path, turning as they go."""
    t = np.linspace(0.0, 1.0, n)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(t, [0.0, 1.0, 0.1])).as_matrix()
    poses[:, :3, 3] = np.stack([2.0 * t, 0.3 * np.sin(3 * t), t * t], axis=1)
    return poses


def _similar(poses: np.ndarray, scale: float, rotvec, shift) -> np.ndarray:
    """The same trajectory in another world: x -> s R x + t."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    out = poses.copy()
    out[:, :3, :3] = R @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ R.T + np.asarray(shift)
    return out


def test_the_same_trajectory_in_another_world_agrees():
    """World frame and scale do not count; frames one of them did not pose are left out."""
    walk = _walk()
    other = _similar(walk, 0.3, [0.2, -0.5, 1.0], [4.0, 1.0, -2.0])
    other[5] = np.nan
    compared, share = trajectory_agreement(walk, other)
    assert compared == 29 and share < 1e-9


def test_a_bent_trajectory_disagrees_by_its_error_as_a_share_of_the_path():
    walk = _walk()
    bent = walk.copy()
    bent[15:, :3, 3] += [0.0, 0.2, 0.0]  # a 20 cm step in a ~2.3 m path
    _, share = trajectory_agreement(walk, bent)
    assert 0.02 < share < 0.06
    # Pieces in worlds of their own (a restart after a loss): each compared on its own.
    pieces = np.r_[np.zeros(15, np.int64), np.ones(15, np.int64)]
    moved = bent.copy()
    moved[15:] = _similar(bent[15:], 2.0, [0.0, 0.0, 0.7], [1.0, 1.0, 1.0])
    _, per_piece = trajectory_agreement(walk, moved, pieces)
    assert per_piece < 1e-9
    # Stretch by stretch, named by the rows' frames: only the bent one disagrees.
    bent_twice = moved.copy()
    bent_twice[22:, :3, 3] += [0.0, 0.5, 0.0]
    each = second_opinion(walk, bent_twice, "asked", False, pieces, frames=np.arange(100, 130)).by_stretch
    assert [s["frames"] for s in each] == [[100, 114], [115, 129]] and [s["compared"] for s in each] == [15, 15]
    assert each[0]["disagreement"] < 1e-9 and each[1]["disagreement"] > 0.02


def test_the_verdict_keeps_the_estimator_with_less_against_it():
    """Agreement within 2 % of the path trusts the stretch; otherwise the front end's own
    refusal or mark hands the trajectory to SfM, unless SfM's checks doubt its map and the
    front end only marked part of its own; without SfM the front end's result stands, marked."""
    walk = _walk()
    bent = walk.copy()
    bent[15:, :3, 3] += [0.0, 0.3, 0.0]
    agree = second_opinion(walk, _similar(walk, 2.0, [0, 0, 1.0], [0, 0, 0]), "steps short", False)
    assert agree.verdict == "agree" and agree.trusted and agree.kept == "SfM" and "agree within" in agree.said()
    refused = second_opinion(bent, walk, "frames far apart", True, sfm_doubt="its scale varies x1.4")
    assert refused.verdict == "disagree" and refused.kept == "SfM" and not refused.trusted
    assert "disagree by" in refused.said() and "not to be trusted" in refused.said()
    doubted = second_opinion(bent, walk, "steps short", False, sfm_doubt="its scale varies x1.4")
    assert doubted.kept == "front end" and "x1.4" in doubted.why
    alone = second_opinion(bent, None, "steps short", False, sfm_failure="SfM registered 3 of 30 frames")
    assert alone.verdict == "one only" and alone.kept == "front end" and "3 of 30" in alone.said()
    assert SecondOpinion.from_dict(refused.to_dict()) == refused


def test_what_asks_for_a_second_opinion():
    """Short steps and breaks of the front end's trajectory ask; a turn on the spot does not
    (SfM has no parallax there either), nor does a clean run."""
    assert doubts({}) == ""
    turning = {"motion_checks": {"rotation_only": [[0, 20]], "short_flow": []}, "scale_watch": {
        "frames": [], "ratio": [], "noise": 0.05, "breaks": [], "judged": True}}
    assert doubts(turning) == ""
    flagged = {"motion_checks": {"short_flow": [[3, 9]]}, "scale_watch": {
        "frames": [], "ratio": [], "noise": 0.05, "judged": True,
        "breaks": [{"before": 10, "after": 12, "factor": 1.5, "z": 6.0, "kind": "step"}]}}
    assert doubts(flagged) == "the dense flow made the camera's steps short at frames 3-9; the trajectory breaks " \
                              "at frames 10-12"
    # Said as the video numbers its frames (a run under --start 350), as every other message.
    assert doubts(flagged, lambda p: 350 + p) == "the dense flow made the camera's steps short at frames 353-359; " \
                                                 "the trajectory breaks at frames 360-362"
    assert stretches(flagged, 15).tolist() == [0] * 12 + [1] * 3
    assert stretches({}, 4).tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize("n", [2])
def test_too_few_frames_are_not_compared(n):
    compared, share = trajectory_agreement(_walk(n), _walk(n))
    assert compared == n and np.isnan(share)


def _shortened(poses: np.ndarray, first: int, factor: float) -> np.ndarray:
    """The trajectory with every step from frame `first` on `factor` as long (short flow)."""
    out = poses.copy()
    steps = np.diff(poses[:, :3, 3], axis=0)
    steps[first - 1:] *= factor
    out[1:, :3, 3] = poses[0, :3, 3] + np.cumsum(steps, axis=0)
    return out


def test_sfm_on_some_frames_judges_a_streamed_trajectory(sfm_room):
    """A streamed run's second opinion (on_views): COLMAP's model of some frames agrees
    with the room's true poses; with the steps after frame 15 half as long (what the short
    flow does) it disagrees by more than the bar, and the front end is kept either way."""
    pytest.importorskip("pycolmap")
    from recon.poses.second_opinion import MAX_DISAGREEMENT, on_views

    seq, _ = sfm_room
    keyframes = np.arange(0, 30, 2)
    right = on_views(seq.poses, keyframes, lambda p: seq.rgb[p], seq.intrinsics, "asked")
    assert right.verdict == "agree" and right.compared >= 12 and right.disagreement < 0.005
    assert right.kept == "front end"
    short = on_views(_shortened(seq.poses, 15, 0.5), keyframes, lambda p: seq.rgb[p], seq.intrinsics, "asked")
    assert short.verdict == "disagree" and short.disagreement > MAX_DISAGREEMENT
    assert short.kept == "front end" and "some frames only" in short.why
