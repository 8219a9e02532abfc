"""Synthetic ground truth for tests, the demo and benchmarks: a rendered textured room with
exact depth, poses and mesh, and a simulated monocular depth prior.

Modules: `room` (layout, materials, mesh), `textures` (procedural texture stack),
`camera` (intrinsics, hand-held path), `render` (ray casting, render_sequence and the
SyntheticSequence it returns), `prior` (the simulated prior), `floorplan` (rooms joined by
corridors and doorways: their closed shell) and `walkthrough` (three rooms and a plain
corridor walked through, with a textureless stretch and a fast blurred turn at known
frames: render_walkthrough and the Walkthrough it returns).
"""

from .camera import camera_path, intrinsics_for
from .prior import SimulatedPrior, add_shape_errors, simulate_prior, simulate_prior_with_truth
from .render import SyntheticSequence, render_sequence
from .walkthrough import Walkthrough, render_walkthrough, walkthrough_plan

__all__ = [
    "SimulatedPrior",
    "SyntheticSequence",
    "Walkthrough",
    "add_shape_errors",
    "camera_path",
    "intrinsics_for",
    "render_sequence",
    "render_walkthrough",
    "simulate_prior",
    "simulate_prior_with_truth",
    "walkthrough_plan",
]
