"""The rules of the streamed pipeline that decide what to work on, as pure functions.

* Depth frames by motion (:class:`MotionSelector`, :func:`select_later`): a frame is taken
  when the camera has moved ``motion`` x the median depth, or turned ``rotation`` degrees,
  since the last one taken (the keyframe rule of KinectFusion- and DROID-SLAM-style
  systems), or ``max_gap`` frames after it. why: docs/decisions.md#depth-frames-of-a-streamed-run
* Windows (:func:`plan_windows`): ``window`` depth frames, the first ``overlap`` shared
  with the previous window, which give the new one its context and its anchor.
More: docs/running.md#how-a-streamed-run-works
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np


def parse_depth_frames(choice: str) -> int | None:
    """The step of a "K" choice of depth frames, None for "motion"; 1 for "all"."""
    if choice == "motion":
        return None
    return 1 if choice == "all" else int(choice)


@dataclass
class MotionSelector:
    """Picks depth frames one at a time (module docstring). motion: translation as a
    fraction of the median depth; rotation: degrees; step: take every step-th frame
    instead (None: by motion); max_gap: by motion, also take a frame this many frames
    after the last one taken (None: motion alone). depth: the median depth of the last
    frame taken, metres (the scale of ``motion``; 1 m until a frame with depth was taken).
    ``by_gap`` counts the frames taken for the gap alone."""

    motion: float = 0.02
    rotation: float = 2.0
    step: int | None = None
    max_gap: int | None = None
    depth: float = 1.0
    by_gap: int = 0
    _last_pose: np.ndarray | None = None
    _last_position: int = 0
    _count: int = 0

    def __call__(self, pose: np.ndarray, median_depth: float | Callable[[], float] | None = None) -> bool:
        """Whether the next frame (camera-to-world ``pose``) is a depth frame; median_depth:
        its prior's median depth in metres, which becomes the scale when it is taken, or a
        function that gives it, called only then (None: not known yet, set ``depth`` once it
        is)."""
        position, self._count = self._count, self._count + 1
        if self.step is not None:
            return position % self.step == 0
        pose = np.asarray(pose, np.float64)
        if not np.isfinite(pose).all():
            return False
        if self._last_pose is None:
            take = True
        else:
            moved = float(np.linalg.norm(pose[:3, 3] - self._last_pose[:3, 3]))
            turned = rotation_angle(self._last_pose[:3, :3].T @ pose[:3, :3])
            take = moved >= self.motion * max(self.depth, 1e-3) or turned >= self.rotation
            if not take and self.max_gap is not None and position - self._last_position >= self.max_gap:
                take, self.by_gap = True, self.by_gap + 1
        if take:
            self._last_pose, self._last_position = pose, position
            if callable(median_depth):
                median_depth = median_depth()
            if median_depth is not None and median_depth > 0:
                self.depth = float(median_depth)
        return take


def select_later(poses: np.ndarray, median_depth: Callable[[int], float], motion: float, rotation: float,
                 step: int | None = None, max_gap: int | None = None) -> tuple[np.ndarray, int]:
    """The depth frames among frames whose poses came after them, chosen as MotionSelector
    would have chosen them in order (frames the front end buffered for its focal search).

    Args:
        poses: (N, 4, 4) camera-to-world, in order (NaN: no pose, not taken).
        median_depth: median_depth(k), the prior's median depth of the k-th frame in metres;
            asked for the frames taken only.
        motion, rotation, step, max_gap: as MotionSelector.

    Returns:
        ((N,) bool: the frames taken, the number taken for max_gap alone).
    """
    select = MotionSelector(motion, rotation, step, max_gap=max_gap)
    taken = np.array([select(pose, lambda k=k: median_depth(k)) for k, pose in enumerate(poses)], bool)
    return taken, select.by_gap


def depth_gap(count: int, min_frames: int) -> int | None:
    """The most frames between two depth frames such that an input of ``count`` frames gets at
    least ``min_frames`` of them (None: no bound, where ``min_frames`` is 0 or the count is not
    known)."""
    if min_frames <= 0 or count <= 0:
        return None
    return max(1, count // min_frames)


def rotation_angle(rotation: np.ndarray) -> float:
    """Angle in degrees of a 3x3 rotation."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return math.degrees(math.acos(cos))


@dataclass(frozen=True)
class Window:
    """Positions start:stop of the depth frames; those before ``new`` were finished by the
    previous window (context and scale anchor), those from ``new`` on are finished here."""

    start: int
    stop: int
    new: int

    @property
    def shared(self) -> int:
        return self.new - self.start


def plan_windows(count: int, window: int, overlap: int) -> list[Window]:
    """Windows over ``count`` depth frames: at most ``window`` frames each, consecutive ones
    sharing ``overlap``; the frames are spread evenly so that the last window is not a
    sliver. One window when everything fits."""
    if count <= window:
        return [Window(0, count, 0)]
    step = window - overlap
    windows_needed = math.ceil((count - overlap) / step)
    new_per_window = (count - overlap) / windows_needed
    bounds = [0] + [overlap + round(new_per_window * (k + 1)) for k in range(windows_needed)]
    bounds[-1] = count
    out = []
    for k in range(windows_needed):
        new = bounds[k]
        out.append(Window(max(0, new - overlap), bounds[k + 1], new))
    return out


def anchor_pixels(finished: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Pixels where both depths ((M, H, W) each) are valid: what an anchor is fitted on."""
    return (finished > 0) & (current > 0) & np.isfinite(finished) & np.isfinite(current)


def anchor_factor(finished: np.ndarray, current: np.ndarray, min_pixels: int = 100) -> float:
    """exp(median log ratio) of finished to current depth over pixels valid in both
    ((M, H, W) each, the shared frames); 1 when too few pixels are valid."""
    finished, current = np.asarray(finished, np.float32), np.asarray(current, np.float32)
    valid = anchor_pixels(finished, current)
    if int(valid.sum()) < min_pixels:
        return 1.0
    return float(np.exp(np.median(np.log(finished[valid] / current[valid]))))


__all__ = ["MotionSelector", "Window", "anchor_factor", "anchor_pixels", "depth_gap", "parse_depth_frames",
           "plan_windows", "rotation_angle"]
