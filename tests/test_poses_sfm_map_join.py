"""Joining across a break through SfM's map (recon.poses.sfm.map_join): views of both stretches in
one COLMAP model give each stretch's similarity into it, and the join is one followed by the
other's inverse; a stretch that does not fit the model is not joined. Also the same through
recon.drivers.segments.join_breaks, where the ORB join finds nothing."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.drivers.segments import join_breaks
from recon.geometry.rigid import apply_similarity
from recon.poses.checks import join as orb_join
from recon.poses.checks.join import View
from recon.poses.sfm.map_join import compose_join, fit_stretch, map_join

pycolmap = pytest.importorskip("pycolmap")


def _slipped(poses: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Camera-to-world poses moved by x -> scale R x + t."""
    out = poses.copy()
    out[:, :3, :3] = rotation @ out[:, :3, :3]
    out[:, :3, 3] = scale * out[:, :3, 3] @ rotation.T + translation
    return out


SLIP = (1.7, Rotation.from_euler("xyz", [4.0, -20.0, 6.0], degrees=True).as_matrix(), np.array([0.5, 0.2, -0.3]))


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a[:, :3, :3] @ np.transpose(b[:, :3, :3], (0, 2, 1)))
                            .magnitude()).max())


def test_two_similarities_compose_into_the_join():
    """A stretch and its slipped copy, each fitted exactly onto one model frame: the composed
    join takes the slipped poses back onto the first stretch's frame."""
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.3, (6, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 1.0, (6, 3))
    model = _slipped(poses, 0.3, Rotation.from_euler("y", 50, degrees=True).as_matrix(), np.array([1.0, 0, 0]))
    slipped = _slipped(poses, *SLIP)
    before, after = fit_stretch(poses, model), fit_stretch(slipped, model)
    assert before.residual < 1e-9 and after.residual < 1e-9 and after.turn_deg < 1e-4
    scale, rotation, translation = compose_join(before, after)
    back = _slipped(slipped, scale, rotation, translation)
    assert scale == pytest.approx(1 / 1.7, rel=1e-9)
    assert np.abs(back - poses).max() < 1e-9


def test_the_stretch_after_a_break_comes_back_through_the_map(sfm_room):
    """The room's frames 0-14 as they are and 15-29 slipped (x1.7, turned 20 degrees, moved
    half a metre): COLMAP's model of 8 views of each gives the inverse, and the moved poses
    land on the true ones within a centimetre and half a degree."""
    seq, _ = sfm_room
    slipped = _slipped(seq.poses[15:], *SLIP)
    before = [View(seq.rgb[i], None, seq.poses[i]) for i in range(0, 15, 2)]
    after = [View(seq.rgb[i], None, slipped[i - 15]) for i in range(15, 30, 2)]
    join = map_join(before, after, seq.intrinsics)
    assert join is not None and len(join.posed) >= 6 and join.residual < 0.02
    assert join.scale == pytest.approx(1 / 1.7, rel=0.02)
    back = apply_similarity(slipped, join.rotation, join.translation, join.scale)
    assert np.abs(back[:, :3, 3] - seq.poses[15:, :3, 3]).max() < 0.01
    assert _rotation_error_deg(back, seq.poses[15:]) < 0.5


def test_a_stretch_that_does_not_fit_the_model_is_not_joined(sfm_room):
    """The stretch after the break with its camera centres shuffled (a trajectory gone
    wrong): its views still register in COLMAP's model, but its poses do not fit it."""
    seq, _ = sfm_room
    wrong = seq.poses[15:].copy()
    wrong[:, :3, 3] = wrong[np.random.default_rng(1).permutation(15), :3, 3]
    before = [View(seq.rgb[i], None, seq.poses[i]) for i in range(0, 15, 2)]
    after = [View(seq.rgb[i], None, wrong[i - 15]) for i in range(15, 30, 2)]
    assert map_join(before, after, seq.intrinsics) is None


def test_join_breaks_falls_back_to_the_map_where_orb_finds_nothing(sfm_room, monkeypatch):
    """join_breaks with the ORB join finding nothing: the break is joined through the map,
    its entry says so, and the trajectory is one again, in the first stretch's frame."""
    seq, prior = sfm_room
    monkeypatch.setattr(orb_join, "join_stretches", lambda *a, **k: None)
    stretch = np.repeat([0, 1], 15)
    poses = np.concatenate([seq.poses[:15], _slipped(seq.poses[15:], *SLIP)])
    label, joined, report = join_breaks(stretch, poses, np.arange(30), lambda p: (seq.rgb[p], prior[p]),
                                        seq.intrinsics)
    assert report[0]["joined"] and report[0]["how"] == "map"
    assert (label == 0).all()
    assert np.abs(joined[:, :3, 3] - seq.poses[:, :3, 3]).max() < 0.01
    _, _, off = join_breaks(stretch, poses, np.arange(30), lambda p: (seq.rgb[p], prior[p]), seq.intrinsics,
                            through_map=False)
    assert not off[0]["joined"]
