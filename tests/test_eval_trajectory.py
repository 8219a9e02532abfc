"""Trajectory metrics (recon.eval.trajectory): Umeyama alignment, ATE, RPE (also on real ground
truth whose rotations are not quite orthonormal), scale error, path length."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.eval.trajectory import (
    align,
    ate_rmse,
    path_length,
    pose_alignment,
    rpe,
    scale_error,
    umeyama,
)
from recon.geometry.rigid import apply_similarity


def _poses(rotations, positions):
    poses = np.tile(np.eye(4), (len(positions), 1, 1))
    poses[:, :3, :3] = rotations
    poses[:, :3, 3] = positions
    return poses


def _random_trajectory(n=30, seed=0):
    rng = np.random.default_rng(seed)
    rot = Rotation.random(n, random_state=seed).as_matrix()
    return _poses(rot, np.cumsum(rng.normal(size=(n, 3)) * 0.1, axis=0))


def test_umeyama_recovers_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(50, 3))
    rot = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    t, s = np.array([1.0, -2.0, 0.5]), 2.5
    dst = s * src @ rot.T + t
    r_est, t_est, s_est = umeyama(src, dst, with_scale=True)
    np.testing.assert_allclose(r_est, rot, atol=1e-10)
    np.testing.assert_allclose(t_est, t, atol=1e-10)
    assert s_est == pytest.approx(s, abs=1e-10)
    # Rigid fit of a rigid motion: scale stays 1.
    r2, t2, s2 = umeyama(src, src @ rot.T + t, with_scale=False)
    np.testing.assert_allclose(r2, rot, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-10)
    assert s2 == 1.0


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(20, 3))
    r, _, _ = umeyama(src, src * [1.0, 1.0, -1.0])
    assert np.linalg.det(r) == pytest.approx(1.0)


def test_umeyama_rejects_degenerate_input():
    with pytest.raises(ReconInputError):
        umeyama(np.zeros((5, 3)), np.ones((5, 3)))
    with pytest.raises(ReconInputError):
        umeyama(np.zeros((5, 3)), np.ones((4, 3)))


def test_ate_is_zero_for_a_similar_trajectory_and_reports_scale():
    gt = _random_trajectory()
    rot = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    est = apply_similarity(gt, rot, np.array([3.0, 1.0, 0.0]), 0.5)
    res = ate_rmse(est, gt, mode="sim3")
    assert res["rmse"] < 1e-10
    assert res["scale"] == pytest.approx(2.0)
    np.testing.assert_allclose(res["aligned"], gt, atol=1e-10)
    assert ate_rmse(est, gt, mode="se3")["rmse"] > 0.01  # a rigid fit cannot undo the scale


def test_ate_no_alignment_hand_computed():
    gt = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    est = gt + [[0, 0, 0.1], [0, 0, -0.1], [0, 0.2, 0], [0, 0, 0]]
    res = ate_rmse(est, gt, mode="none")
    assert res["rmse"] == pytest.approx(np.sqrt(0.06 / 4))
    assert res["mean"] == pytest.approx(0.1)
    assert res["median"] == pytest.approx(0.1)
    assert res["max"] == pytest.approx(0.2)


def test_ate_of_perturbed_square_hand_computed():
    # Corners of a square; est = rigidly moved gt plus z-noise +d, -d, +d, -d. That noise is
    # uncorrelated with the square, so the rigid fit undoes the motion exactly (errors = d)
    # and the Sim(3) fit shrinks by s = 2 / (2 + d^2).
    d = 0.1
    gt = np.array([[1, 1, 0], [-1, 1, 0], [-1, -1, 0], [1, -1, 0]], dtype=float)
    noisy = gt + np.array([[0, 0, d], [0, 0, -d], [0, 0, d], [0, 0, -d]])
    rot = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix()
    est = noisy @ rot.T + [5.0, -1.0, 2.0]
    se3 = ate_rmse(est, gt, mode="se3")
    assert se3["rmse"] == pytest.approx(d)
    np.testing.assert_allclose(se3["errors"], d)
    sim3 = ate_rmse(est, gt, mode="sim3")
    s = 2 / (2 + d**2)
    assert sim3["scale"] == pytest.approx(s)
    assert sim3["rmse"] == pytest.approx(np.sqrt(2 * (1 - s) ** 2 + (s * d) ** 2))


def test_ate_skips_invalid_frames():
    gt = _random_trajectory(10)
    est = gt.copy()
    est[3] = np.nan
    res = ate_rmse(est, gt, mode="se3")
    assert res["n"] == 9 and res["rmse"] < 1e-10 and np.isnan(res["errors"][3])
    with pytest.raises(ReconInputError, match="differ in length"):
        ate_rmse(est[:5], gt)


def test_rpe_tiny_example():
    gt = _poses(np.eye(3)[None].repeat(3, 0), [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    est = _poses(np.eye(3)[None].repeat(3, 0), [[0, 0, 0], [1, 0, 0], [2.1, 0, 0]])
    res = rpe(est, gt, delta=1)
    np.testing.assert_allclose(res["trans_errors"], [0.0, 0.1], atol=1e-12)
    assert res["trans_rmse"] == pytest.approx(np.sqrt(0.01 / 2))
    assert res["rot_rmse_deg"] == pytest.approx(0.0, abs=1e-6)
    assert rpe(est, gt, delta=2)["trans_rmse"] == pytest.approx(0.1)

    # A 10-degree yaw error on the last frame only.
    est_rot = gt.copy()
    est_rot[2, :3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix()
    res = rpe(est_rot, gt)
    np.testing.assert_allclose(res["rot_errors_deg"], [0.0, 10.0], atol=1e-9)
    assert res["trans_rmse"] == pytest.approx(0.0, abs=1e-12)


def test_rpe_scale_argument_and_invariance_to_world_frame():
    gt = _random_trajectory(20, seed=3)
    rot = Rotation.from_rotvec([1.0, 0.0, 0.5]).as_matrix()
    est = apply_similarity(gt, rot, np.array([1.0, 2.0, 3.0]), 0.25)
    assert rpe(est, gt)["trans_rmse"] > 1e-3
    res = rpe(est, gt, scale=4.0)
    assert res["trans_rmse"] < 1e-10 and res["rot_rmse_deg"] < 1e-5
    with pytest.raises(ReconInputError):
        rpe(est, gt, delta=20)


def test_scale_error():
    gt = _random_trajectory(15, seed=4)
    rot = Rotation.from_rotvec([0.0, 0.5, 0.0]).as_matrix()
    assert scale_error(gt, gt) == pytest.approx(0.0, abs=1e-10)
    assert scale_error(apply_similarity(gt, rot, np.zeros(3), 0.5), gt) == pytest.approx(1.0)
    assert scale_error(apply_similarity(gt, rot, np.ones(3), 2.0), gt) == pytest.approx(0.5)


def test_path_length_and_align_none():
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    assert path_length(square) == pytest.approx(3.0)
    with_gap = np.insert(square, 2, np.nan, axis=0)
    assert path_length(with_gap) == pytest.approx(3.0)
    assert path_length(square[:1]) == 0.0
    r, t, s = align(square, square + 1, mode="none")
    assert np.allclose(r, np.eye(3)) and np.allclose(t, 0) and s == 1.0


def test_pose_alignment_recovers_similarity_even_for_a_rotating_camera():
    rot = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    t, s = np.array([1.0, -2.0, 0.5]), 0.8
    gt = _random_trajectory()
    est = apply_similarity(gt, rot.T, -(rot.T @ t) / s, 1.0 / s)  # the inverse map
    fit = pose_alignment(est, gt, "sim3")
    np.testing.assert_allclose(fit["rotation"], rot, atol=1e-9)
    np.testing.assert_allclose(fit["translation"], t, atol=1e-9)
    assert fit["scale"] == pytest.approx(s)
    # A camera turning on the spot: centres alone fix no rotation, orientations do.
    spin = _poses(Rotation.from_rotvec(np.outer(np.linspace(0, 0.5, 20), [0.2, 1.0, 0.1])).as_matrix(),
                  np.full((20, 3), 0.5) + np.random.default_rng(2).normal(scale=1e-4, size=(20, 3)))
    moved = apply_similarity(spin, rot, t, 1.0)
    fit = pose_alignment(spin, moved, "se3")
    np.testing.assert_allclose(fit["rotation"], rot, atol=1e-9)
    assert fit["scale"] == 1.0
    assert pose_alignment(spin, moved, "none")["scale"] == 1.0


def test_rpe_rotation_ignores_non_orthonormal_ground_truth():
    """7-Scenes stores rotations with det ~0.99986; a pose compared with itself has no error."""
    rng = np.random.default_rng(3)
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (5, 3))).as_matrix()
    noisy = poses.copy()
    noisy[:, :3, :3] *= 0.99993  # det 0.9998
    assert rpe(noisy, poses)["rot_rmse_deg"] < 1e-3
    small = poses.copy()
    small[1:, :3, :3] = small[1:, :3, :3] @ Rotation.from_rotvec([0, 0, 1e-4]).as_matrix()
    assert rpe(small, poses)["rot_errors_deg"][0] == pytest.approx(np.degrees(1e-4), rel=1e-3)


def test_a_scale_the_camera_centres_do_not_determine_is_not_used_on_a_mesh():
    """A camera that turns on the spot with its centres jittering by a centimetre: the Sim(3)
    fit explains nothing of them and its scale is noise, so the mesh keeps scale 1 (and says
    why); a walk that the fit explains keeps the trajectory's scale."""
    rng = np.random.default_rng(3)
    turning = _poses(Rotation.from_rotvec(np.outer(np.linspace(0, 0.8, 40), [0.2, 1.0, 0.1])).as_matrix(),
                     rng.normal(scale=0.01, size=(40, 3)))
    jittered = turning.copy()
    jittered[:, :3, 3] = rng.normal(scale=0.01, size=(40, 3))
    assert align(jittered, turning, "sim3")[2] < 0.5
    fit = pose_alignment(jittered, turning, "sim3")
    assert fit["scale"] == 1.0 and fit["scale_from"] == "undetermined"
    assert fit["explained"] < 0.5 and fit["fitted_scale"] < 0.5
    np.testing.assert_allclose(fit["rotation"], np.eye(3), atol=1e-9)
    gt = _random_trajectory()
    walked = gt.copy()
    walked[:, :3, 3] = 0.9 * gt[:, :3, 3] + rng.normal(scale=0.01, size=(len(gt), 3))
    fit = pose_alignment(walked, gt, "sim3")
    assert fit["scale_from"] == "trajectory" and fit["scale"] == pytest.approx(1 / 0.9, rel=0.02)
    assert fit["explained"] > 0.9 and fit["fitted_scale"] == fit["scale"]



def test_the_orientation_error_ignores_the_world_frame_and_the_scale():
    """Each camera's orientation against the truth after the one best rotation: an estimate
    in another world frame, scaled, scores 0; one camera turned by 3 degrees scores 3 there."""
    from scipy.spatial.transform import Rotation

    from recon.eval.trajectory import rotation_error

    turns = Rotation.from_rotvec(np.outer(np.linspace(0, 1.2, 30), [0.3, 1.0, 0.2])).as_matrix()
    gt = np.tile(np.eye(4), (30, 1, 1))
    gt[:, :3, :3] = turns
    gt[:, :3, 3] = np.linspace(0, 0.1, 30)[:, None]
    world = np.eye(4)
    world[:3, :3] = Rotation.from_rotvec([0.4, -0.2, 0.9]).as_matrix()
    est = world @ gt
    est[:, :3, 3] *= 3.0
    assert rotation_error(est, gt)["median_deg"] < 1e-6
    bent = est.copy()
    bent[7, :3, :3] = bent[7, :3, :3] @ Rotation.from_rotvec([0, np.radians(3.0), 0]).as_matrix()
    errors = rotation_error(bent, gt)["errors_deg"]
    assert errors[7] == pytest.approx(3.0, abs=0.2) and np.median(errors) < 0.2
