"""The checks a monocular front end makes of its own motion, beside the scale watch
(``recon.poses.checks.scale_watch``): whether the camera moved in a way its frames can measure.

* **Rotation only**: the share of the keyframes' flow their translation makes (f |t| / Z
  against f theta; ORB-SLAM refuses such pairs by Torr's model selection). Such a stretch
  is marked, not refused: its rotations are measured, its path is not.
* **Large motion**: frames farther apart than ``large_motion_share`` of the image width.
* **The lens at its bound**: k1 fitted on ``ba.MAX_K1``: the camera model does not explain the flow.
More: docs/poses.md#motion-checks
why: docs/decisions.md#the-checks-on-an-estimated-trajectory
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from recon.poses.checks.quality import runs
from recon.poses.result import frame_spans


@dataclass(frozen=True)
class MotionCheckConfig:
    """window: consecutive keyframe pairs judged together for rotation only;
    max_translation_share: below this share of the window's flow made by translation
        (against rotation), its keyframes are rotation only
        (why: docs/decisions.md#the-checks-on-an-estimated-trajectory);
    large_motion_share: neighbouring frames whose motion moves the image by more than this
        share of its width (median over the pixels) are farther apart than dense flow follows;
    min_large_motion_share: ... and a run is judged to move too fast when this share of its
        frame pairs do;
    min_rotation_only_share: a run whose rotation-only stretches hold this share of its
        frames is judged to turn on the spot (shorter stretches are marked, not judged: a
        hand-held walk pauses to look around)."""

    window: int = 6
    max_translation_share: float = 0.3
    large_motion_share: float = 0.1
    min_large_motion_share: float = 0.5
    min_rotation_only_share: float = 0.5


@dataclass
class MotionChecks:
    """What report.json says (frames by position in the run until :meth:`renumbered`):
    rotation_only: [first, last] frame ranges of rotation-only stretches; translation_share:
    the run's share of keyframe flow made by translation; large_motion: frames whose step from
    the frame before exceeds the large-motion share, and the run's median step (share of the
    width); moves_too_fast and turns_on_the_spot: the verdicts on the
    whole run; lens_k1 and lens_at_bound."""

    rotation_only: list[list[int]] = field(default_factory=list)
    translation_share: float = float("nan")
    large_motion: list[int] = field(default_factory=list)
    median_step_share: float = float("nan")
    moves_too_fast: bool = False
    turns_on_the_spot: bool = False
    lens_k1: float | None = None
    lens_at_bound: bool = False
    short_flow: list[list[int]] = field(default_factory=list)
    short_flow_slope: float = float("nan")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "MotionChecks":
        return cls(**d)

    def renumbered(self, names) -> "MotionChecks":
        """The same with frame positions replaced by names[i] (the video's frame numbers)."""
        return replace(self, rotation_only=[[int(names[a]), int(names[b])] for a, b in self.rotation_only],
                       large_motion=[int(names[i]) for i in self.large_motion],
                       short_flow=[[int(names[a]), int(names[b])] for a, b in self.short_flow])

    def joined(self, later: "MotionChecks") -> "MotionChecks":
        """The checks of a run followed by those of a later piece of it (``recon.poses.frontend.pieces``;
        frames numbered in the whole video): the frames and stretches of both, a verdict on
        the whole when either has it, the largest short-flow slope; the run's shares and lens."""
        return replace(self, rotation_only=self.rotation_only + later.rotation_only,
                       large_motion=self.large_motion + later.large_motion,
                       moves_too_fast=self.moves_too_fast or later.moves_too_fast,
                       turns_on_the_spot=self.turns_on_the_spot or later.turns_on_the_spot,
                       short_flow=self.short_flow + later.short_flow,
                       short_flow_slope=float(np.fmax(self.short_flow_slope, later.short_flow_slope)))

    def frame_verdicts(self, count: int) -> list[str]:
        """Per frame of a run of `count` frames: "ok", or what is wrong with its motion."""
        verdict = ["ok"] * count
        for i in self.large_motion:
            verdict[i] = "large motion"
        for a, b in self.short_flow:
            verdict[a:b + 1] = ["flow short"] * (b + 1 - a)
        for a, b in self.rotation_only:
            verdict[a:b + 1] = ["rotation only"] * (b + 1 - a)
        return verdict

    def short_said(self) -> str:
        """One sentence on the stretches whose steps the dense flow made short (empty: none)."""
        if not self.short_flow:
            return ""
        spans = frame_spans(self.short_flow, shown=4)  # already frame numbers
        # "or more": the edges see only part of such a stretch.
        # why: docs/decisions.md#the-short-flow-check
        return (f"frames {spans}: the dense flow made the camera's steps short; the images' edges put them at "
                f"x{self.short_flow_slope:.2f} longer or more (plain surfaces, where the flow sees only across "
                "edges), so the trajectory there is shorter than the camera's path and the mesh fused from it is "
                "squeezed along it")

    def turning_said(self) -> str:
        """One sentence on the stretches where the camera turns on the spot (empty: none).
        A mark, not a refusal: their rotations are measured (and with the focal length
        estimated, the focal length is, from the same rotations: ``rotation_focal``), their
        path and the map's scale are not."""
        if not self.rotation_only:
            return ""
        spans = frame_spans(self.rotation_only, shown=4)  # already frame numbers
        # The run's share speaks for the stretches only where they are most of it.
        share = "" if not (self.turns_on_the_spot and np.isfinite(self.translation_share)) else (
            f" (its translation makes {100 * self.translation_share:.0f} % of the keyframes' flow)")
        return (f"frames {spans}: the camera turns on the spot{share}: its rotations are measured, its path and "
                "the map's scale there are not (the positions are what the solver found, the depth there is the "
                "prior's as MEDeA adjusts it)")

    def untrusted(self, focal_estimated: bool = True) -> list[str]:
        """Why the trajectory as a whole is not to be trusted, one clause each (empty: nothing).
        A camera turned on the spot is not among them (:meth:`turning_said` marks it): its
        rotations are measured whether or not its focal length was given."""
        why = []
        if self.lens_at_bound:
            why.append(f"the lens term the trajectory was fitted with ended on its bound (k1 = {self.lens_k1:+.2f}): "
                       "the camera model does not explain the frames' flow")
        if self.moves_too_fast and focal_estimated:
            frames = self.large_motion
            why.append(f"neighbouring frames lie a median {100 * self.median_step_share:.0f} % of the image's width "
                       f"apart ({len(frames)} frames between {frames[0]} and {frames[-1]} moved more than "
                       "a tenth of it from the frame before), farther than the front end follows a camera it "
                       "does not know")
        return why


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """Rotation angles (radians) of rotation matrices R (..., 3, 3)."""
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def relative_motion(T_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(angles (M-1,) radians, translations (M-1,)) between consecutive world-to-camera
    poses T_cw (M, 4, 4): the motion of camera i+1 relative to camera i."""
    rel = T_cw[1:] @ np.linalg.inv(T_cw[:-1])
    return rotation_angles(rel[:, :3, :3]), np.linalg.norm(rel[:, :3, 3], axis=1)


def keyframe_motion(T_cw: np.ndarray, depth: np.ndarray, focal: float) -> tuple[np.ndarray, np.ndarray]:
    """(rotation flow, translation flow), pixels (K-1,), between consecutive keyframes:
    f theta for the turn and f |t| / Z for the translation, Z the median depth of the first
    of the pair (its valid pixels, > 0). T_cw: (K, 4, 4) world-to-camera; depth: (K, h, w)
    in the poses' units (the map's: the ratio does not depend on its scale)."""
    angles, distances = relative_motion(np.asarray(T_cw, np.float64))
    d = np.asarray(depth, np.float64)[:-1].reshape(len(angles), -1)
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
    median = np.nanmedian(d, axis=1)
    return focal * angles, focal * distances / median


def rotation_only_stretches(rot_px: np.ndarray, trans_px: np.ndarray, cfg: MotionCheckConfig) -> list[tuple[int, int]]:
    """[(first pair, last pair)] of consecutive keyframe pairs in windows of ``cfg.window``
    whose translation flow is under ``cfg.max_translation_share`` of their total flow (the
    pairs of such a window that turn more than they move).
    rot_px, trans_px: (K-1,) as from :func:`keyframe_motion` (NaN pairs count as moving)."""
    n = len(rot_px)
    if n < cfg.window:
        return []
    t = np.nan_to_num(trans_px, nan=np.inf)
    t_sum = np.lib.stride_tricks.sliding_window_view(t, cfg.window).sum(axis=1)
    r_sum = np.lib.stride_tricks.sliding_window_view(rot_px, cfg.window).sum(axis=1)
    flagged = t_sum < cfg.max_translation_share * (t_sum + r_sum)
    in_flagged_window = np.zeros(n, dtype=bool)
    for start in np.flatnonzero(flagged):
        in_flagged_window[start:start + cfg.window] = True
    # A window's verdict covers its own turning pairs, not the moving ones at its edges.
    turning = t < cfg.max_translation_share * (t + rot_px)
    return runs(np.flatnonzero(in_flagged_window & turning).tolist())


def large_motion_frames(T_cw: np.ndarray, depth: float, focal: float, width: int,
                        cfg: MotionCheckConfig) -> tuple[list[int], float]:
    """(frames whose step from the frame before moves the image by more than
    ``cfg.large_motion_share`` of `width`, the median step as a share of the width).
    T_cw: (N, 4, 4) world-to-camera poses of every frame; depth: the scene's median depth in
    their units. The step is f theta + f |t| / depth, the flow of the pixel at that depth."""
    if len(T_cw) < 2:
        return [], 0.0
    angles, distances = relative_motion(np.asarray(T_cw, np.float64))
    share = focal * (angles + distances / depth) / width
    return (np.flatnonzero(share > cfg.large_motion_share) + 1).tolist(), float(np.median(share))


def check_motion(keyframe_T_cw: np.ndarray, keyframe_depth: np.ndarray, keyframes, frame_T_cw: np.ndarray,
                 focal: float, width: int, lens_k1: float | None = None, k1_bound: float | None = None,
                 cfg: MotionCheckConfig | None = None) -> MotionChecks:
    """Every check of the module docstring on a front end's result.

    keyframe_T_cw: (K, 4, 4) world-to-camera poses of the keyframes, keyframe_depth: (K, h,
    w) their depth (the map's), keyframes: (K,) their frame positions; frame_T_cw: (N, 4, 4)
    every frame's pose; focal: pixels of frames `width` wide; lens_k1, k1_bound: the fitted
    radial term and its bound (None: the lens was not fitted)."""
    cfg = cfg or MotionCheckConfig()
    keyframes = np.asarray(keyframes, dtype=np.int64)
    out = MotionChecks(lens_k1=None if lens_k1 is None else float(lens_k1))
    if lens_k1 is not None and k1_bound is not None:
        out.lens_at_bound = bool(abs(lens_k1) >= k1_bound - 1e-6)
    if len(keyframes) >= 2:
        rot_px, trans_px = keyframe_motion(keyframe_T_cw, keyframe_depth, focal)
        t, r = np.nansum(trans_px), np.nansum(rot_px)
        out.translation_share = float(t / (t + r)) if t + r > 0 else float("nan")
        out.rotation_only = [[int(keyframes[a]), int(keyframes[b + 1])]
                             for a, b in rotation_only_stretches(rot_px, trans_px, cfg)]
        d = np.asarray(keyframe_depth, np.float64)
        scene_depth = float(np.median(d[np.isfinite(d) & (d > 0)]))
        out.large_motion, out.median_step_share = large_motion_frames(frame_T_cw, scene_depth, focal, width, cfg)
        out.moves_too_fast = len(out.large_motion) >= cfg.min_large_motion_share * max(len(frame_T_cw) - 1, 1)
        turning = sum(b - a + 1 for a, b in out.rotation_only)
        out.turns_on_the_spot = turning >= cfg.min_rotation_only_share * len(frame_T_cw)
    return out


__all__ = ["MotionCheckConfig", "MotionChecks", "check_motion", "keyframe_motion", "large_motion_frames",
           "relative_motion", "rotation_angles", "rotation_only_stretches"]
