"""Frames of a rolling-shutter camera resampled to one instant (recon.geometry.rolling_shutter)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.core.config import PipelineConfig
from recon.core.sequence import Sequence
from recon.core.stages import unrolled_frames
from recon.errors import ReconInputError
from recon.eval.trajectory import ate_rmse
from recon.geometry import rolling_shutter as rs
from recon.poses.frontend.streaming import estimate_poses_frontend
from recon.synthetic import render_sequence, simulate_prior

INTRINSICS = (300.0, 300.0, 159.5, 119.5)


def _turning(rate: np.ndarray, count: int = 8, fps: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world poses turning at a constant body rate (rad/s), and their timestamps."""
    stamps = np.arange(count) / fps
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, :3] = Rotation.from_rotvec(np.outer(stamps, rate)).as_matrix()
    poses[:, :3, 3] = np.outer(stamps, [0.1, 0.0, 0.0])
    return poses, stamps


def test_angular_velocity_is_the_body_rate_of_the_poses():
    rate = np.array([0.2, -1.1, 0.3])
    poses, stamps = _turning(rate)
    np.testing.assert_allclose(rs.angular_velocity(poses, stamps), np.tile(rate, (len(poses), 1)), atol=1e-9)
    poses[3] = np.nan  # a frame without a pose: its neighbours' rate is unknown too
    omega = rs.angular_velocity(poses, stamps)
    assert (omega[[2, 4]] == 0).all() and np.allclose(omega[6], rate)


def test_the_shutter_moves_rows_by_the_turn_during_their_readout():
    shape, readout = (240, 320), 0.03
    still = rs.recorded_position(np.zeros(3), INTRINSICS, shape, readout)
    np.testing.assert_allclose(still, np.stack(np.meshgrid(np.arange(320), np.arange(240)), -1), atol=1e-4)
    # Turning about the camera's y axis moves rows sideways, the first and last rows most,
    # by about f * rate * readout / 2 in opposite directions; the middle row stays.
    pos = rs.recorded_position(np.array([0.0, 1.0, 0.0]), INTRINSICS, shape, readout)
    shift = pos[..., 0] - still[..., 0]
    assert shift[0, 160] == pytest.approx(-shift[-1, 160], rel=0.02)
    assert abs(shift[0, 160]) == pytest.approx(300.0 * 1.0 * readout / 2, rel=0.02)
    assert abs(shift[120, 160]) < 0.01
    assert rs.largest_shift(pos[None])[0] == pytest.approx(np.abs(pos - still).max(), rel=0.3)


def test_unrolling_gives_back_the_frames_of_one_instant():
    seq = render_sequence(3, 320, 240, seed=0)
    positions = rs.recorded_positions(np.tile([0.3, 1.5, 0.2], (3, 1)), seq.intrinsics, (240, 320), 0.03)
    recorded = rs.roll_images(seq.rgb, positions)
    restored = rs.unroll_images(recorded, positions)
    inner = (slice(None), slice(20, -20), slice(20, -20))
    before = np.abs(recorded[inner].astype(float) - seq.rgb[inner]).mean()
    after = np.abs(restored[inner].astype(float) - seq.rgb[inner]).mean()
    assert after < 0.25 * before, (before, after)


def test_a_sequence_is_unrolled_with_the_turn_rate_of_its_poses():
    room = render_sequence(6, 320, 240, seed=0)
    stamps = np.arange(6) / 30.0
    readout = 0.03
    positions = rs.recorded_positions(rs.angular_velocity(room.poses, stamps), room.intrinsics, (240, 320), readout)
    features = np.random.default_rng(0).normal(size=(6, 4, 30, 40)).astype(np.float32)
    recorded = Sequence(np.arange(6), stamps, rs.roll_images(room.rgb, positions), [f"{i}" for i in range(6)],
                        tuple(room.intrinsics), room.depth.astype(np.float32), features, room.poses)
    unrolled, info = unrolled_frames(recorded, readout * 1000)
    inner = (slice(None), slice(20, -20), slice(20, -20))
    before = np.abs(recorded.rgb[inner].astype(float) - room.rgb[inner]).mean()
    after = np.abs(unrolled.rgb[inner].astype(float) - room.rgb[inner]).mean()
    assert after < 0.5 * before, (before, after)
    assert info["frames_resampled"] == 6 and info["max_shift_px"] > 1.0
    assert unrolled.prior_depth.shape == recorded.prior_depth.shape and unrolled.features.shape == features.shape
    # A global shutter (no turn) leaves the frames untouched.
    still, info = unrolled_frames(recorded.with_(poses=np.tile(np.eye(4), (6, 1, 1))), 30.0)
    assert info["frames_resampled"] == 0 and np.array_equal(still.rgb, recorded.rgb)


@pytest.mark.parametrize("readout", [-1.0, 150.0])
def test_a_readout_outside_a_frame_is_refused(tmp_path, readout):
    config = PipelineConfig(tmp_path, tmp_path / "out", rolling_shutter=readout)
    with pytest.raises(ReconInputError, match="rolling-shutter readout"):
        config.validate()


def test_poses_estimated_again_on_unrolled_frames_lose_the_shutter_error():
    """The synthetic room walked at twice its speed (45 deg/s) and recorded with a 30 ms
    rolling shutter: the front end's estimate is several times worse than on the frames of
    one instant; the frames unrolled with that estimate's own turn rate (what `recon run
    --rolling-shutter` does) bring most of it back."""
    count, readout = 40, 0.03
    room = render_sequence(count, 320, 240, seed=0, speed=2)
    stamps = np.arange(count) / 30.0
    prior = simulate_prior(room.depth, seed=1)
    positions = rs.recorded_positions(rs.angular_velocity(room.poses, stamps), room.intrinsics, (240, 320), readout)
    recorded = Sequence(np.arange(count), stamps, rs.roll_images(room.rgb, positions),
                        [f"{i}" for i in range(count)], tuple(room.intrinsics), prior)

    def ate(seq: Sequence) -> tuple[float, np.ndarray]:
        poses = estimate_poses_frontend(seq.rgb, seq.prior_depth, seq.intrinsics, progress=False).poses
        return ate_rmse(poses, room.poses, "sim3")["rmse"], poses

    still, _ = ate(recorded.with_(rgb=room.rgb))
    rolled, first = ate(recorded)
    unrolled, _ = ate(unrolled_frames(recorded.with_(poses=first), readout * 1000)[0])
    assert rolled > 3 * still, (still, rolled)
    assert unrolled < 0.5 * rolled, (rolled, unrolled)


def test_features_follow_the_frame_pixels_at_their_own_resolution():
    """A feature that is its own cell's x coordinate, read where the frame pixels were
    recorded (here 16 frame pixels to the right): the cell coordinate of that place."""
    height, width, h, w = 240, 320, 30, 40
    grid = np.stack(np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32)), -1)
    positions = (grid + np.array([16.0, 0.0], np.float32))[None]
    ramp = np.broadcast_to(np.arange(w, dtype=np.float32), (h, w))
    out = rs.unroll_features(np.stack([ramp])[None], positions)
    expected = np.minimum(ramp + 16.0 * (w - 1) / (width - 1), w - 1)
    np.testing.assert_allclose(out[0, 0], expected, atol=1e-3)


def test_a_streamed_run_with_given_poses_resamples_its_depth_frames(tmp_path):
    """The synthetic room walked at three times its speed and recorded with a 50 ms rolling
    shutter, run streamed with its true poses: resampling the depth frames (what
    `--rolling-shutter` does there) puts the fused surface back where the scene is, and
    report.json says what was resampled."""
    from dataclasses import replace

    from medea_core import MedeaConfig
    from recon.commands.demo import mesh_scores, write_demo_inputs
    from recon.io.output_folder import OutputFolder
    from recon.pipeline import run_pipeline

    count, readout = 24, 0.05
    room = render_sequence(count, 256, 192, seed=0, speed=3)
    stamps = np.arange(count) / 30.0
    positions = rs.recorded_positions(rs.angular_velocity(room.poses, stamps), room.intrinsics, (192, 256), readout)
    recorded = replace(room, rgb=rs.roll_images(room.rgb, positions))
    inputs = write_demo_inputs(OutputFolder(tmp_path / "input"), recorded,
                               rs.roll_images(simulate_prior(room.depth, seed=1), positions))
    fast = MedeaConfig.fast()
    medea = replace(fast, seed=0, stage1=replace(fast.stage1, epochs=60), stage2=replace(fast.stage2, epochs=10))

    def streamed(name: str, readout_ms: float):
        return run_pipeline(PipelineConfig(
            input=inputs["video"], output=tmp_path / name, width=None, intrinsics=room.intrinsics,
            poses=str(inputs["poses"]), prior="folder", prior_path=inputs["prior"], medea=medea, polish=False,
            stream="on", depth_frames="all", window=12, window_overlap=4, rerun="off", progress=False,
            rolling_shutter=readout_ms))

    as_recorded, resampled = streamed("recorded", 0.0), streamed("resampled", readout * 1000)
    assert "rolling_shutter" not in as_recorded.report["poses"]
    shutter = resampled.report["poses"]["rolling_shutter"]
    assert shutter["readout_ms"] == 50.0 and shutter["frames_resampled"] >= count // 2 and shutter["max_shift_px"] > 2
    f_recorded = mesh_scores(as_recorded.fusion.mesh, room)["fscore"]
    f_resampled = mesh_scores(resampled.fusion.mesh, room)["fscore"]
    assert f_resampled > f_recorded + 0.15, (f_recorded, f_resampled)  # measured 0.50 -> 0.83
