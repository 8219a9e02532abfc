"""The synthetic camera: its pinhole intrinsics and its smooth hand-held path through the
room (camera-to-world poses, OpenCV axes, in the y-down world frame of recon.synthetic.room).
"""

from __future__ import annotations

import numpy as np

# Camera path: per-frame rates, so longer sequences just go on along the same kind of path.
_YAW_RATE = np.deg2rad(0.4)  # rad/frame of the slow turn through the room: 48 degrees in 120 frames
_FIXATION = 3.0  # metres: sideways steps turn the camera toward a point this far ahead
_PATH_SQUASH = (1.0, 0.75)  # x, z: fits the walk's disk (radius <= 1.1 m) into the free middle of the room
_EYE_HEIGHT = 1.45
_PITCH_DOWN = np.deg2rad(17.0)


def intrinsics_for(width: int, height: int) -> tuple[float, float, float, float]:
    """Pinhole intrinsics of the synthetic camera: fx = fy = 525 * W / 640, centred."""
    focal = 525.0 * width / 640.0
    return (focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)


def camera_rotation(yaw: float, pitch_down: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (3, 3) from radians: yaw about world y (down), then pitch, then roll."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch_down), np.sin(pitch_down)
    cr, sr = np.cos(roll), np.sin(roll)
    r_yaw = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    # Positive pitch_down tilts the optical axis (+z) toward +y, i.e. toward the floor.
    r_pitch = np.array([[1, 0, 0], [0, cp, sp], [0, -sp, cp]])
    r_roll = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return r_yaw @ r_pitch @ r_roll


def camera_path(num_frames: int, seed: int, speed: float = 1.0, times=None) -> np.ndarray:
    """(N, 4, 4) float64 camera-to-world poses of a smooth hand-held scan of the room.

    speed: path time per frame (2: every other frame of the speed-1 path, twice the motion
    per frame). times: explicit path times (N,) instead (sub-frames for motion blur).

    The heading turns slowly (0.4 deg/frame plus a gentle sway) so the camera sweeps the
    room; meanwhile the camera steps sideways back and forth (up to 1 m, ~2 cm/frame) and
    a little forward/back, turning toward a point ~3 m ahead as it steps, like a person
    scanning what is in front of them. That keeps frames 32-64 apart overlapping while
    giving plenty of parallax. The walk stays in the free middle of the room (|x| <= 1.1 m,
    |z| <= 0.85 m, eye height ~1.45 m), looking ~17 degrees down with small smooth
    pitch/roll wobble and hand shake. Motion per frame does not depend on num_frames.
    """
    rng = np.random.default_rng([seed, 3])
    t = np.arange(num_frames, dtype=np.float64) * float(speed) if times is None else np.asarray(times, np.float64)
    num_frames = len(t)
    phase = rng.uniform(0, 2 * np.pi, 12)
    wave = lambda amplitude, period, k: amplitude * np.sin(2 * np.pi * t / period + phase[k])  # noqa: E731
    heading = rng.uniform(0, 2 * np.pi) + rng.choice([-1.0, 1.0]) * _YAW_RATE * t + wave(0.04, 95, 0)
    side = wave(0.85, 170, 1) + wave(0.15, 80, 2)  # metres along the heading's right vector
    ahead = -0.2 + wave(0.2, 150, 3) + wave(0.05, 47, 4)  # metres along the heading (mostly behind the centre)
    right = np.stack([np.cos(heading), -np.sin(heading)], axis=1)  # (x, z) of the camera's x axis at yaw = heading
    forward = np.stack([np.sin(heading), np.cos(heading)], axis=1)
    xz = (side[:, None] * right + ahead[:, None] * forward) * np.array(_PATH_SQUASH)
    # Hand shake: small and smooth (periods of 17-31 frames).
    x = xz[:, 0] + wave(0.005, 23, 5)
    z = xz[:, 1] + wave(0.005, 31, 6)
    y = -(_EYE_HEIGHT + wave(0.04, 70, 7) + wave(0.004, 17, 8))
    # Stepping right turns the camera left (toward the fixation point) and vice versa.
    yaw = heading - np.arctan(side / _FIXATION)
    pitch = _PITCH_DOWN + wave(0.035, 53, 9) + wave(0.01, 19, 10)
    roll = wave(0.025, 61, 11) + 0.008 * np.sin(2 * np.pi * t / 21 + phase[0])
    poses = np.tile(np.eye(4), (num_frames, 1, 1))
    for i in range(num_frames):
        poses[i, :3, :3] = camera_rotation(yaw[i], pitch[i], roll[i])
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses
