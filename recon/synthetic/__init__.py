"""Synthetic ground truth for tests, the demo and benchmarks: a rendered textured room with
exact depth, poses and mesh, and a simulated monocular depth prior.

Modules: `room` (layout, materials, mesh), `textures` (procedural texture stack),
`camera` (intrinsics, hand-held path), `render` (ray casting, render_sequence and the
SyntheticSequence it returns), `prior` (the simulated prior).
"""

from .camera import camera_path, intrinsics_for
from .prior import SimulatedPrior, add_shape_errors, simulate_prior, simulate_prior_with_truth
from .render import SyntheticSequence, render_sequence

__all__ = [
    "SimulatedPrior",
    "SyntheticSequence",
    "add_shape_errors",
    "camera_path",
    "intrinsics_for",
    "render_sequence",
    "simulate_prior",
    "simulate_prior_with_truth",
]
