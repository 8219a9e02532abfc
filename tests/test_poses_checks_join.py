"""Joining the stretches on either side of a scale break (recon.poses.checks.join): the frames after
the break posed by PnP against the depth before it give the similarity between the two."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.geometry.rigid import apply_similarity
from recon.poses.checks.join import View, join_stretches, mean_rotation
from recon.synthetic import render_sequence


@pytest.fixture(scope="module")
def room():
    return render_sequence(24, 256, 192, seed=0)


def _slipped(poses: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Camera-to-world poses moved by the similarity x -> scale R x + t (a stretch whose map slipped)."""
    out = poses.copy()
    out[:, :3, :3] = rotation @ out[:, :3, :3]
    out[:, :3, 3] = scale * out[:, :3, 3] @ rotation.T + translation
    return out


def test_the_stretch_after_a_break_is_brought_back(room):
    """Frames 12-23 of the room mapped 1.6x too large, turned 12 degrees and shifted 0.4 m
    (their depth 1.6x too, as a stretch brought to its own prior's scale is): the join finds
    the inverse, and the moved poses land on the true ones within millimetres."""
    R = Rotation.from_euler("xyz", [3.0, 12.0, -5.0], degrees=True).as_matrix()
    slip = (1.6, R, np.array([0.4, -0.1, 0.2]))
    after_poses = _slipped(room.poses[12:], *slip)
    before = [View(room.rgb[i], room.depth[i], room.poses[i]) for i in (5, 7, 9, 11)]
    after = [View(room.rgb[i], 1.6 * room.depth[i], after_poses[i - 12]) for i in (12, 14, 16, 18)]
    join = join_stretches(before, after, room.intrinsics)
    assert join is not None and len(join.posed) == 4 and min(join.inliers) > 100
    assert join.scale == pytest.approx(1 / 1.6, rel=0.02)
    back = apply_similarity(after_poses, join.rotation, join.translation, join.scale)
    assert np.abs(back[:, :3, 3] - room.poses[12:, :3, 3]).max() < 0.01
    assert np.degrees(Rotation.from_matrix(back[:, :3, :3] @ np.transpose(room.poses[12:, :3, :3], (0, 2, 1)))
                      .magnitude()).max() < 0.3


def test_frames_that_do_not_see_the_same_place_are_not_joined(room):
    """Views after the break of another room (another seed): no PnP pose, no join."""
    other = render_sequence(4, 256, 192, seed=5)
    before = [View(room.rgb[i], room.depth[i], room.poses[i]) for i in (5, 7, 9, 11)]
    after = [View(other.rgb[i], other.depth[i], other.poses[i]) for i in range(4)]
    assert join_stretches(before, after, room.intrinsics) is None


def test_mean_rotation_of_noisy_copies_is_the_rotation():
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    noise = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 0.01, (20, 3))).as_matrix()
    assert np.degrees(Rotation.from_matrix(mean_rotation(noise @ R) @ R.T).magnitude()) < 0.3
