"""Resampling a trajectory in time (recon.geometry.rigid): one-to-one timestamp association,
interpolation (slerp across a short gap, else the nearest pose within a tolerance) and
snapping to rounded timestamps."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from recon.geometry.rigid import associate_timestamps, interpolate_poses, make_poses


def test_associate_timestamps_is_one_to_one_within_tolerance():
    query = np.array([0.00, 0.033, 0.066, 0.100, 0.500])
    ref = np.array([0.005, 0.030, 0.031, 0.110, 0.2])
    qi, ri = associate_timestamps(query, ref, max_diff=0.02)
    assert qi.tolist() == [0, 1, 3]
    assert ri.tolist() == [0, 2, 3]  # 0.033 takes the closer 0.031; 0.066 has nothing left within 20 ms
    # Order of the reference list does not matter.
    perm = np.array([4, 2, 0, 3, 1])
    qi2, ri2 = associate_timestamps(query, ref[perm], max_diff=0.02)
    assert qi2.tolist() == qi.tolist() and perm[ri2].tolist() == ri.tolist()
    q3, _ = associate_timestamps(query, ref + 10.0, max_diff=0.02)
    assert q3.size == 0


def test_interpolate_poses_slerp_and_nearest():
    ref_ts = np.array([0.0, 0.1, 1.0])
    rot = Rotation.from_euler("z", [[0.0], [20.0], [20.0]], degrees=True).as_matrix()
    ref = make_poses(rot, [[0, 0, 0], [1, 0, 0], [1, 0, 0]])
    out, valid = interpolate_poses([0.025, 0.05, 1.01, 0.5, -0.5], ref_ts, ref, max_gap=0.2, max_diff=0.02)
    assert valid.tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(out[1, :3, 3], [0.5, 0, 0])
    np.testing.assert_allclose(out[0, :3, :3], Rotation.from_euler("z", 5, degrees=True).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(out[2], ref[2])
    assert np.isnan(out[3]).all()


def test_interpolate_poses_snaps_to_rounded_timestamps():
    ref = make_poses(Rotation.from_euler("z", [[0.0], [40.0]], degrees=True).as_matrix(), [[0, 0, 0], [1, 0, 0]])
    out, _ = interpolate_poses([0.001, 0.05], [0.0, 0.1], ref, snap=0.005)
    np.testing.assert_allclose(out[0], ref[0])
    np.testing.assert_allclose(out[1, :3, 3], [0.5, 0, 0])


def test_a_similarity_moves_camera_centres_and_turns_rotations():
    """apply_similarity: x -> s R x + t on the centres, R on the rotations; NaN stays NaN."""
    from recon.geometry.rigid import apply_similarity

    rot = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, :3, 3] = [1.0, 0.0, 0.0]
    poses[1] = np.nan
    moved = apply_similarity(poses, rot, np.array([0.0, 0.0, 1.0]), 2.0)
    assert np.allclose(moved[0, :3, 3], [0.0, 2.0, 1.0]) and np.allclose(moved[0, :3, :3], rot)
    assert np.isnan(moved[1]).all() and poses[0, 0, 3] == 1.0  # the input is left as it was
