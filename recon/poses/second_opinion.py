"""A second opinion on an estimated trajectory: the dense front end and SfM, two independent
estimators, compared where the front end's own checks doubt its result.

Flow follows small steps and slides along plain surfaces; SIFT needs texture and parallax
but no small steps. Where the front end refuses or marks its trajectory, SfM estimates the
same frames and the two are compared under a Sim(3) (:func:`trajectory_agreement`: centre
RMSE as a share of the path). :func:`second_opinion` gives the verdict (report.json
``poses.second_opinion``) and the estimator kept; :func:`on_views` does it for a streamed
run's depth frames. More: docs/poses.md#a-second-opinion-the-front-end-and-sfm-compared
why: docs/decisions.md#the-second-opinion
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from recon.geometry.rigid import polyline_length, umeyama
from recon.poses.result import FrameNumbers, by_position, frame_spans

# Two trajectories whose centres differ by at most this share of the path after a Sim(3)
# agree: the bar a right trajectory meets against the truth. why: docs/decisions.md#the-second-opinion
MAX_DISAGREEMENT = 0.02


@dataclass
class SecondOpinion:
    """What report.json says (``poses.second_opinion``): why it was asked (the front end's
    doubt), the frames both estimators posed, their disagreement (centres' RMSE after a
    Sim(3), as a share of SfM's path; NaN where not compared), the verdict
    ("agree", "disagree", or "one only" where SfM gave nothing), which estimator is kept, and
    why; by_stretch: per stretch of the front end's trajectory compared, its first and last
    frame, the frames compared and their disagreement (:func:`stretch_agreement`)."""

    asked: str
    compared: int
    disagreement: float
    verdict: str
    kept: str
    why: str
    by_stretch: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SecondOpinion":
        return cls(**d)

    @property
    def trusted(self) -> bool:
        return self.verdict == "agree"

    def said(self) -> str:
        """One sentence for the run's warning."""
        if self.verdict == "agree":
            return (f"the front end and SfM agree within {100 * self.disagreement:.1f} % of the path on "
                    f"{self.compared} frames ({self.asked}); the {self.kept} trajectory is kept")
        if self.verdict == "one only":
            return f"{self.asked}; SfM gave no second opinion ({self.why}): the {self.kept} trajectory is kept, marked"
        return (f"the front end and SfM disagree by {100 * self.disagreement:.1f} % of the path on {self.compared} "
                f"frames ({self.asked}): the {self.kept} trajectory is kept ({self.why}), and is not to be trusted "
                f"to better than that")


def stretch_agreement(reference: np.ndarray, other: np.ndarray, stretch: np.ndarray | None = None,
                      frames: np.ndarray | None = None) -> list[dict]:
    """How far two estimates of the same frames differ, stretch by stretch, whatever their
    world frame and scale.

    reference, other: (N, 4, 4) camera-to-world poses (non-finite: no pose); stretch: (N,)
    int, the stretch of `other` each frame belongs to (pieces of a trajectory in worlds of
    their own: each compared on its own; None: one); frames: (N,) how the rows are named
    (default: positions). Returns per stretch with 3 frames both posed and a path: its
    label, first and last frame, the frames compared and the RMSE of the reference's centres
    against the other's after the Sim(3) that best takes the other onto the reference
    (Umeyama), as a share of the reference's path over those frames."""
    both = np.isfinite(reference).all(axis=(1, 2)) & np.isfinite(other).all(axis=(1, 2))
    stretch = np.zeros(len(reference), np.int64) if stretch is None else np.asarray(stretch)
    frames = np.arange(len(reference)) if frames is None else np.asarray(frames)
    out = []
    for label in np.unique(stretch[both]):
        mine = both & (stretch == label)
        a, b = reference[mine, :3, 3], other[mine, :3, 3]
        path = polyline_length(a)
        if len(a) < 3 or path <= 0 or np.ptp(b, axis=0).max() <= 0:
            continue
        rot, trans, scale = umeyama(b, a, with_scale=True)
        moved = scale * b @ rot.T + trans
        share = float(np.sqrt(np.mean(np.sum((moved - a) ** 2, axis=1))) / path)
        rows = np.flatnonzero(stretch == label)
        out.append({"stretch": int(label), "frames": [int(frames[rows[0]]), int(frames[rows[-1]])],
                    "compared": int(mine.sum()), "disagreement": share})
    return out


def trajectory_agreement(reference: np.ndarray, other: np.ndarray, stretch: np.ndarray | None = None
                         ) -> tuple[int, float]:
    """(frames both posed, the largest disagreement over stretches of
    :func:`stretch_agreement`; NaN where no stretch has 3 frames and a path)."""
    return _overall(reference, other, stretch_agreement(reference, other, stretch))


def _overall(reference: np.ndarray, other: np.ndarray, by_stretch: list[dict]) -> tuple[int, float]:
    """:func:`trajectory_agreement` from the stretches :func:`stretch_agreement` compared."""
    both = np.isfinite(reference).all(axis=(1, 2)) & np.isfinite(other).all(axis=(1, 2))
    shares = [s["disagreement"] for s in by_stretch]
    return int(both.sum()), (max(shares) if shares else float("nan"))


def doubts(diagnostics: dict, number: FrameNumbers = by_position) -> str:
    """What in a front end's result (its diagnostics) asks for a second opinion, in words
    ("" for nothing): stretches whose steps the flow made short (``motion_checks``) and
    breaks of the map's scale or of tracking (``scale_watch``). number: position -> the
    frame number said (recon.poses.result.FrameNumbers)."""
    from recon.poses.checks.scale_watch import ScaleWatch

    said = []
    short = diagnostics.get("motion_checks", {}).get("short_flow", [])
    if short:
        said.append("the dense flow made the camera's steps short at frames " + frame_spans(short, number))
    if "scale_watch" in diagnostics:
        watch = ScaleWatch.from_dict(diagnostics["scale_watch"])
        if watch.breaks:
            said.append("the trajectory breaks at frames "
                        + frame_spans(((b.before, b.after) for b in watch.breaks), number))
    return "; ".join(said)


def stretches(diagnostics: dict, count: int) -> np.ndarray:
    """(count,) int: the stretch of a front end's trajectory each frame belongs to (0 before
    the first break of its scale watch, n after break n)."""
    from recon.poses.checks.scale_watch import ScaleWatch

    if "scale_watch" not in diagnostics:
        return np.zeros(count, np.int64)
    verdicts = ScaleWatch.from_dict(diagnostics["scale_watch"]).frame_verdicts(count)
    return np.array([0 if v == "ok" else int(v.rsplit(" ", 1)[-1]) for v in verdicts], dtype=np.int64)


def second_opinion(frontend: np.ndarray, sfm: np.ndarray | None, asked: str, frontend_refused: bool,
                   stretch: np.ndarray | None = None, sfm_doubt: str = "", sfm_failure: str = "",
                   max_disagreement: float = MAX_DISAGREEMENT, sfm_covers: bool = True,
                   frames: np.ndarray | None = None) -> SecondOpinion:
    """The verdict on the frames both estimators had (module docstring).

    frontend, sfm: (N, 4, 4) camera-to-world poses of the same frames (sfm None: SfM gave
    nothing, ``sfm_failure`` says why); asked: the front end's doubt, in words;
    frontend_refused: whether the front end refused its result (else it only marked part
    of it); stretch: (N,) the front end's stretches (:func:`stretches`); sfm_doubt: what
    SfM's own checks hold against its map ("" for nothing); sfm_covers: whether SfM posed
    every frame (False: only some of them, :func:`on_views`, so SfM can
    judge the front end's trajectory but not replace it); frames: (N,) the rows' positions
    in the run, for ``by_stretch`` (default: 0 .. N-1)."""
    if sfm is None:
        return SecondOpinion(asked, 0, float("nan"), "one only", "front end", sfm_failure)
    by_stretch = stretch_agreement(sfm, frontend, stretch, frames)
    compared, disagreement = _overall(sfm, frontend, by_stretch)
    keep_sfm = sfm_covers and (frontend_refused or not sfm_doubt)
    kept = "SfM" if keep_sfm else "front end"
    if np.isfinite(disagreement) and disagreement <= max_disagreement:
        return SecondOpinion(asked, compared, disagreement, "agree", kept, "both estimators", by_stretch)
    if not sfm_covers:
        why = "SfM posed some frames only"
    elif frontend_refused:
        why = "the front end refused its own" + (f", and SfM's own check doubts its map: {sfm_doubt}" if sfm_doubt
                                                 else "; SfM's checks hold nothing against its map")
    elif keep_sfm:
        why = "SfM's checks hold nothing against its map, the front end's marked part of its own"
    else:
        why = f"SfM's own check doubts its map: {sfm_doubt}"
    return SecondOpinion(asked, compared, disagreement, "disagree", kept, why, by_stretch)


def on_views(poses: np.ndarray, views: np.ndarray, frame, intrinsics, asked: str,
             stretch: np.ndarray | None = None, max_views: int = 100) -> SecondOpinion:
    """SfM's opinion of a front end's trajectory from some of its frames alone (a streamed
    run, which keeps its memory bound and the colour of its depth frames only): COLMAP's
    model of at most ``max_views`` of them, evenly apart (``sfm.views_model``), compared with
    the front end's poses of the same frames; the front end is kept either way.

    poses: (N, 4, 4) the front end's camera-to-world poses; views: (V,) positions of the
    frames to use, in order; frame(position) -> (H, W, 3) uint8 RGB, one size; intrinsics:
    (fx, fy, cx, cy) held fixed, or None for COLMAP to estimate the focal length; asked: the
    doubt, in words; stretch: (N,) the front end's stretches (:func:`stretches`)."""
    from recon.poses.result import evenly_apart
    from recon.poses.sfm.mapper import views_model

    views = np.asarray(views, np.int64)
    views = views[np.isfinite(poses[views]).all(axis=(1, 2))]
    views = views[evenly_apart(len(views), max_views)]
    in_model = views_model([frame(int(p)) for p in views], intrinsics) if len(views) >= 3 else {}
    if len(in_model) < 3:
        return second_opinion(poses[views], None, asked, False,
                              sfm_failure=f"COLMAP registered {len(in_model)} of {len(views)} frames")
    sfm = np.full((len(views), 4, 4), np.nan)
    for i, pose in in_model.items():
        sfm[i] = pose
    labels = None if stretch is None else np.asarray(stretch)[views]
    return second_opinion(poses[views], sfm, asked, False, labels, sfm_covers=False, frames=views)


__all__ = ["MAX_DISAGREEMENT", "SecondOpinion", "doubts", "on_views", "second_opinion", "stretch_agreement",
           "stretches", "trajectory_agreement"]
