"""MEDeA (Multi-view Efficient Depth Adjustment, Artemyev et al., ICIP 2024) in pure torch.

Per-frame prior depth D0 is corrected by a small per-frame log-scale grid, optimised so
that colour, depth and features agree when reprojected between frames. This package
owns the method only: no file IO, no open3d. See `run_medea`.
"""

from .config import MedeaConfig, StageConfig
from .geometry import depth_in_view_i, pair_transforms, reproject, sample, scale_intrinsics
from .grid import adjust_depth, median_pool_to_grid, scale_field
from .optimize import MedeaResult, StageHistory, optimise_stage, run_medea
from .pairs import hierarchical_pairs, nearest_keyframe, stage_pairs
from .propagate import propagate_scales

__all__ = [
    "MedeaConfig",
    "MedeaResult",
    "StageConfig",
    "StageHistory",
    "adjust_depth",
    "depth_in_view_i",
    "hierarchical_pairs",
    "median_pool_to_grid",
    "nearest_keyframe",
    "optimise_stage",
    "pair_transforms",
    "propagate_scales",
    "reproject",
    "run_medea",
    "sample",
    "scale_field",
    "scale_intrinsics",
    "stage_pairs",
]
