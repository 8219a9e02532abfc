"""What pose estimators return and accept: :class:`PoseResult`, :class:`TrackingLostError`, and
the validation of user inputs (frames, depth prior, intrinsics) shared by the DROID-style
front end (``recon.poses.frontend.streaming``) and the SfM fallback (``recon.poses.sfm.mapper``).

Conventions: poses camera-to-world (N, 4, 4) float64, OpenCV axes, metres; intrinsics
``(fx, fy, cx, cy)`` in pixels of the input frames; depth z in metres, 0 = invalid.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np

from recon.errors import ReconInputError

# Estimators count the frames they are given by position (0, 1, ...). What they say (errors,
# log lines) names frames as the user counts them, the video's own frame numbers under
# --start, --stride or a dataset's selection, through a map from position to number that the
# caller gives; without one, positions. The data they return stays by position: the caller
# renumbers it (recon.core.stages.gate_estimate).
FrameNumbers = Callable[[int], int]


def by_position(position: int) -> int:
    """The frame numbers of a caller that gives none: positions."""
    return int(position)


def numbered(frame_numbers=None) -> FrameNumbers:
    """A position -> frame number map from a sequence of frame numbers (one per frame given),
    or None (positions)."""
    if frame_numbers is None:
        return by_position
    numbers = [int(i) for i in frame_numbers]
    return numbers.__getitem__


def frame_spans(spans: Iterable[tuple[int, int]], number: FrameNumbers = by_position,
                shown: int | None = None) -> str:
    """'a-b, c' of [first, last] position spans, by frame number; with `shown`, the first
    `shown` of them and how many more ('a-b, c and 2 more')."""
    spans = list(spans)
    more = f" and {len(spans) - shown} more" if shown is not None and len(spans) > shown else ""
    return ", ".join(f"{number(a)}-{number(b)}" if a != b else f"{number(a)}" for a, b in spans[:shown]) + more


class TrackingLostError(ReconInputError):
    """The video could not be tracked: names the frame where it failed and why.

    A subclass of ReconInputError (the CLI prints it on one line) so that callers can catch
    it specifically and fall back to SfM (``recon.poses.sfm.mapper.estimate_poses_sfm``).
    """

    def __init__(self, message: str, frame: int | None = None, sfm_may_help: bool = True, lost: bool = False):
        super().__init__(message)
        self.frame = frame  # by position; the message names its frame number (FrameNumbers)
        # True where the camera was lost at `frame` (frames before it tracked), rather than a
        # trajectory refused as a whole: tracking may start again there (recon.poses.frontend.pieces).
        self.lost = lost
        # False where SfM has nothing more to go on (a camera that turns on the spot: no
        # parallax for either method), so that no fallback is tried.
        self.sfm_may_help = sfm_may_help
        # The front end's focal-length estimates (recon.poses.intrinsics.focal_choice.FocalChoice) when it
        # searched one before it failed: the range a fallback's own estimate is said within.
        self.focal_choice = None
        # The trajectory the estimator refused as a whole (a PoseResult of the frames before
        # any loss), for a second estimator to be compared with (recon.poses.second_opinion).
        self.untrusted_result = None

    @classmethod
    def at_the_end(cls, frame: int, number: FrameNumbers = by_position) -> "TrackingLostError":
        """The camera lost at position `frame` and not found again before the video ends."""
        return cls(f"tracking lost at frame {number(frame)} and not recovered before the end of the video",
                   frame=frame, lost=True)


# Per-frame tracking states (``PoseResult.diagnostics["frame_status"]``), shared by every
# estimator so that one quality gate (``recon.poses.checks.quality``) reads them all:
#   keyframe     optimised in the map (front end BA; SfM: registered in COLMAP's model)
#   tracked      aligned to keyframes by its own flow (SfM: registered densely)
#   relocalised  tracked after a loss, against an older keyframe
#   recovered    lost while tracking, aligned at the end against its final neighbours
#   interpolated no reliable evidence: the pose is a guess between its neighbours
FRAME_STATES = ("keyframe", "tracked", "relocalised", "recovered", "interpolated")
# States whose pose rests on the frame's own image evidence.
TRUSTED_STATES = frozenset({"keyframe", "tracked", "relocalised", "recovered"})


@dataclass
class PoseResult:
    """Camera poses for every input frame.

    poses: (N, 4, 4) float64 camera-to-world, metres (metric scale from the depth prior).
    intrinsics: (fx, fy, cx, cy) in pixels of the input frames (estimated when not given).
    keyframes: (K,) int64 indices of the frames the poses were optimised on.
    seconds: wall time of the estimate.
    diagnostics: method name, focal-length search, scale factor, per-frame status and
        whatever the estimator reports (see each estimator's docstring).
    keyframe_depth: (K, h, w) float32 metric depth of the keyframes on the BA grid
        (front end only; None for SfM).
    """

    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    keyframes: np.ndarray
    seconds: float
    diagnostics: dict = field(default_factory=dict)
    keyframe_depth: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.poses)


# --------------------------------------------------------------------------- inputs


def parse_intrinsics(intrinsics) -> tuple[float, float, float, float] | None:
    """(fx, fy, cx, cy) from a 4-sequence or a 3x3 matrix; None passes through."""
    if intrinsics is None:
        return None
    arr = np.asarray(intrinsics, dtype=np.float64)
    if arr.shape == (3, 3):
        arr = np.array([arr[0, 0], arr[1, 1], arr[0, 2], arr[1, 2]])
    if arr.shape != (4,):
        raise ReconInputError(f"intrinsics must be (fx, fy, cx, cy) or a 3x3 matrix, got shape {arr.shape}")
    if not np.isfinite(arr).all() or arr[0] <= 0 or arr[1] <= 0:
        raise ReconInputError(f"intrinsics must be finite with positive focal lengths, got {tuple(arr)}")
    return tuple(float(v) for v in arr)


def check_frame(frame, index: int, shape: tuple[int, int] | None) -> np.ndarray:
    """An (H, W, 3) uint8 RGB frame, or a one-line error naming frame `index`."""
    frame = np.asarray(frame)
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ReconInputError(f"frame {index}: expected an (H, W, 3) RGB image, got shape {frame.shape}")
    if frame.dtype != np.uint8:
        raise ReconInputError(f"frame {index}: expected uint8 pixels, got {frame.dtype}")
    if shape is not None and frame.shape[:2] != shape:
        raise ReconInputError(
            f"frame {index}: size {frame.shape[1]}x{frame.shape[0]} "
            f"differs from the first frame's {shape[1]}x{shape[0]}"
        )
    if min(frame.shape[:2]) < 16:
        raise ReconInputError(f"frame {index}: {frame.shape[1]}x{frame.shape[0]} is too small to track")
    return frame


def iterate_frames(frames) -> Iterator[tuple[int, np.ndarray]]:
    """(index, frame) pairs of an (N, H, W, 3) array or any iterable of (H, W, 3) uint8 frames, validated."""
    if isinstance(frames, np.ndarray) and frames.ndim != 4:
        raise ReconInputError(f"frames must be (N, H, W, 3) uint8, got shape {frames.shape}")
    if not isinstance(frames, (np.ndarray, Iterable)):
        raise ReconInputError(
            f"frames must be an (N, H, W, 3) array or an iterable of frames, got {type(frames).__name__}"
        )
    shape = None
    for i, frame in enumerate(frames):
        frame = check_frame(frame, i, shape)
        shape = frame.shape[:2]
        yield i, frame


def num_frames_hint(frames) -> int | None:
    """len(frames) when it is known without consuming it."""
    try:
        return len(frames)
    except TypeError:
        return None


class PriorSource:
    """Uniform access to a depth prior given as an (N, H, W) array or a callable.

    A callable is called as ``prior(index, frame)`` -> (H', W') depth in metres and only for
    the frames that need it (keyframes), which saves running a network on every frame.
    """

    def __init__(self, prior):
        self.is_callable = callable(prior) and not isinstance(prior, np.ndarray)
        if prior is None:
            raise ReconInputError("a metric depth prior is required (an (N, H, W) array in metres or a callable)")
        if not self.is_callable:
            if not isinstance(prior, np.ndarray) and hasattr(prior, "__len__"):
                prior = np.asarray(prior)
            if getattr(prior, "ndim", 0) != 3:
                raise ReconInputError(
                    f"prior depth must be (N, H, W) metres, got shape {getattr(prior, 'shape', None)}"
                )
        self.prior = prior

    def __len__(self) -> int:
        return -1 if self.is_callable else len(self.prior)

    def has(self, index: int) -> bool:
        return self.is_callable or index < len(self.prior)

    def get(self, index: int, frame: np.ndarray | None) -> np.ndarray:
        """(H', W') float32 metres of frame `index`, validated (finite, >= 0, not all invalid)."""
        if self.is_callable:
            depth = self.prior(index, frame)
        else:
            if index >= len(self.prior):
                raise ReconInputError(f"prior depth has {len(self.prior)} frames but frame {index} was requested")
            depth = self.prior[index]
        depth = np.asarray(depth, dtype=np.float32)
        if depth.ndim != 2:
            raise ReconInputError(f"prior depth of frame {index}: expected (H, W), got shape {depth.shape}")
        if not np.isfinite(depth).all():
            raise ReconInputError(f"prior depth of frame {index} contains NaN or inf (use 0 for invalid pixels)")
        if (depth < 0).any():
            raise ReconInputError(f"prior depth of frame {index} has negative values (use 0 for invalid pixels)")
        if not (depth > 0).any():
            raise ReconInputError(f"prior depth of frame {index} has no valid pixel")
        return depth


def pool_depth(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Depth (H, W) metres area-resized to `shape` (h, w) ignoring invalid zeros; 0 where no valid pixel."""
    valid = (depth > 0).astype(np.float32)
    if depth.shape[:2] == tuple(shape):
        return depth.astype(np.float32)
    dsize = (shape[1], shape[0])
    num = cv2.resize(depth * valid, dsize, interpolation=cv2.INTER_AREA)
    den = cv2.resize(valid, dsize, interpolation=cv2.INTER_AREA)
    return np.where(den > 0.25, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def robust_log_mean(values: np.ndarray, trim: float = 0.2) -> float:
    """exp of the trimmed mean of log(values) (values > 0); NaN when empty.

    Per-frame scale ratios of a network prior are roughly log-normal, so their log mean is
    the efficient estimate; trimming keeps frames with a broken prior out.
    """
    v = np.log(np.asarray(values, dtype=np.float64))
    v = np.sort(v[np.isfinite(v)])
    if v.size == 0:
        return float("nan")
    cut = int(np.floor(trim * v.size))
    core = v[cut : v.size - cut] if v.size - 2 * cut > 0 else v
    return float(np.exp(core.mean()))


def invert_poses(T: np.ndarray) -> np.ndarray:
    """Inverses (N, 4, 4) of rigid transforms (N, 4, 4) (NaN rows stay NaN)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


Prior = np.ndarray | Callable[[int, np.ndarray], np.ndarray]


def evenly_apart(count: int, most: int) -> np.ndarray:
    """Indices (M,) int64 of at most `most` of `count` items in order, evenly apart, the
    first and last among them (all of them when count <= most; none when count is 0)."""
    if count <= 0:
        return np.zeros(0, np.int64)
    return np.unique(np.linspace(0, count - 1, min(most, count)).round().astype(np.int64))
