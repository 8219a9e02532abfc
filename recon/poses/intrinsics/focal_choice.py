"""The focal length of a camera nobody calibrated: the choice between the estimates, the
range they leave open, and what the user is told.

:func:`choose_focal` owns the rule between the flow-based search (``calib``), the vanishing
points (``vanishing``) and the homographies of a turning camera (``rotation_focal``):
vanishing points on which at least ``FrontendConfig.vanishing_min_share`` of the frames agree;
otherwise the rotation's value where trusted; otherwise the search's. The range the evidence
leaves open is given in the warning when its ends differ by more than ``DISAGREEMENT``
(report.json: ``poses.diagnostics.focal``). More: docs/poses.md#the-focal-length-from-nothing
why: docs/decisions.md#the-focal-length-from-nothing
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from recon.poses.intrinsics.calib import FocalSearch
from recon.poses.intrinsics.rotation_focal import RotationFocal
from recon.poses.intrinsics.vanishing import VanishingFocal

# A range whose ends differ by more than this factor is said in the warning.
DISAGREEMENT = 1.10
# Focal lengths whose search score is within this factor of the best one are not ruled out.
FLAT_SCORE = 1.02
# As an end of the range the vanishing points' value stands for this much either side (their
# accuracy where taken). why: docs/decisions.md#the-focal-length-from-nothing
VANISHING_ACCURACY = 1.04
# An estimate that takes over (the SfM fallback's bundle adjustment) and lies further than
# this factor from the vanishing points' value is not taken.
# why: docs/decisions.md#the-focal-length-from-nothing
TAKEOVER_TOLERANCE = 1.25


@dataclass(frozen=True)
class FocalChoice:
    """focal: the value tracking starts from (pixels); source: which estimate it is; low,
    high: the range the estimates leave open (pixels); candidates: {estimate: focal} of
    every estimate made (the vanishing points' also when not trusted); bracketed: whether the
    search's minimum lay inside its candidates."""

    focal: float
    source: str
    low: float
    high: float
    candidates: dict
    bracketed: bool = True

    @property
    def found(self) -> bool:
        """False when the focal length is the search's and its best score lay at an end of its
        candidates: a value the frames did not fix (TUM fr1/rpy's second segment: 300 px for
        a 517 px camera), so a trajectory built on it is not to be trusted either."""
        return self.source != "flow" or self.bracketed

    @property
    def disagree(self) -> bool:
        return self.high > DISAGREEMENT * self.low

    def to_dict(self) -> dict:
        return {**asdict(self), "disagree": self.disagree, "found": self.found}

    def with_estimate(self, source: str, focal: float) -> "FocalChoice":
        """The choice of another estimator that took over (the SfM fallback's bundle
        adjustment): its focal length, the range widened to hold it, the others kept."""
        return FocalChoice(float(focal), source, min(self.low, focal), max(self.high, focal),
                           {**self.candidates, source: float(focal)})

    def contradicted(self) -> str:
        """Why the chosen focal length cannot be taken, or "": the vanishing points' value
        (when measured, agreed on or not) lies further than TAKEOVER_TOLERANCE from it. For an
        estimate that took over from the flow search (``with_estimate``)."""
        vp = self.candidates.get("vanishing points")
        if not vp or self.source == "vanishing points":
            return ""
        ratio = self.focal / vp
        if 1 / TAKEOVER_TOLERANCE <= ratio <= TAKEOVER_TOLERANCE:
            return ""
        return (f"its focal length ({self.source}, {self.focal:.0f} px) and the vanishing points' ({vp:.0f} px) "
                f"disagree by x{max(ratio, 1 / ratio):.2f}; pass --fov or --intrinsics")

    def not_found(self) -> str:
        """Why the trajectory is not trusted when the focal length was not found."""
        return (f"the focal length was not found: the search's best score lay at an end of its candidates "
                f"({self.focal:.0f} px of {self.low:.0f}-{self.high:.0f}) and no vanishing points were agreed on; "
                f"pass --fov or --intrinsics")

    def warning(self, width: int) -> str:
        """The one warning a run with an estimated focal length gives (frames `width` px wide)."""
        def fov(f: float) -> float:
            return math.degrees(2 * math.atan(width / (2 * f)))

        text = (f"focal length estimated from the video ({self.source}): {self.focal:.1f} px (horizontal field of "
                f"view {fov(self.focal):.1f} deg)")
        if self.disagree:
            text += (f"; the estimates leave {self.low:.0f}-{self.high:.0f} px open ({fov(self.high):.0f}-"
                     f"{fov(self.low):.0f} deg), and the frames do not tell where in it the camera is")
        return (text + ". The mesh's size and shape follow the focal length: pass --fov or --intrinsics if the "
                "camera is known")


def flat_range(search: FocalSearch, flat: float = FLAT_SCORE) -> tuple[float, float]:
    """(low, high): the focal lengths the search scored within `flat` times its best score;
    every focal length it scored when its minimum was not bracketed."""
    if not search.bracketed and search.evaluations:
        scored = [f for f, _ in search.evaluations]
        return min(scored), max(scored)
    best = min(score for _, score in search.evaluations) if search.evaluations else math.inf
    near = [f for f, score in search.evaluations if score <= flat * best] or [search.focal]
    return min(near), max(near)


def agreed_on(vp: VanishingFocal | None, cfg) -> bool:
    """Whether the vanishing points' value is taken (trusted, and agreed on by at least
    ``cfg.vanishing_min_share`` of the frames): then no other estimate can change the choice."""
    return vp is not None and vp.focal > 0 and vp.trusted and vp.share >= cfg.vanishing_min_share


def choose_focal(search: FocalSearch | None, vp: VanishingFocal | None, cfg, rotation: RotationFocal | None = None
                 ) -> FocalChoice:
    """The focal length to track with (module docstring), from the flow search's result, the
    vanishing points' estimate `vp` and the rotation's `rotation` (None when not made; the
    search is not made where the vanishing points are ``agreed_on``); cfg: the FrontendConfig
    (``vanishing_min_share``)."""
    candidates = {} if search is None else {"flow": float(search.focal)}
    if rotation is not None and rotation.trusted:
        candidates["rotation"] = float(rotation.focal)
    if vp is not None and vp.focal > 0:
        candidates["vanishing points"] = float(vp.focal)
        if agreed_on(vp, cfg):
            values = candidates.values()
            return FocalChoice(float(vp.focal), "vanishing points", min(values), max(values), candidates)
    if search is None:
        raise ValueError("choose_focal: the flow search is needed where the vanishing points are not agreed on")
    if "rotation" in candidates:
        # The search's own value is no evidence against it where its minimum was not bracketed.
        values = [rotation.low, rotation.high] + ([search.focal] if search.bracketed else [])
        if "vanishing points" in candidates:
            vp_focal = candidates["vanishing points"]
            values += [vp_focal / VANISHING_ACCURACY, vp_focal * VANISHING_ACCURACY]
        return FocalChoice(float(rotation.focal), "rotation", float(min(values)), float(max(values)), candidates)
    low, high = flat_range(search)
    values = [low, high, search.focal]
    if "vanishing points" in candidates:
        vp_focal = candidates["vanishing points"]
        values += [vp_focal / VANISHING_ACCURACY, vp_focal * VANISHING_ACCURACY]
    return FocalChoice(float(search.focal), "flow", float(min(values)), float(max(values)), candidates,
                       search.bracketed)


__all__ = ["DISAGREEMENT", "FLAT_SCORE", "TAKEOVER_TOLERANCE", "VANISHING_ACCURACY", "FocalChoice", "agreed_on",
           "choose_focal", "flat_range"]
