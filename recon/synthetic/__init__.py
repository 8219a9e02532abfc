"""Synthetic ground truth for tests, the demo and benchmarks: a rendered textured room with
exact depth, poses and mesh (`scene`), and a simulated monocular depth prior (`prior`).
"""

from .prior import SimulatedPrior, add_shape_errors, simulate_prior, simulate_prior_with_truth
from .scene import SyntheticSequence, camera_path, intrinsics_for, render_sequence

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
