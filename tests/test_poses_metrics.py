"""Trajectory metrics on real-world ground truth quirks (recon.eval.trajectory)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.eval.trajectory import rpe


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
