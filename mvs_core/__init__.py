"""Multi-view stereo refinement of consistent depth, in pure torch.

MEDeA (``medea_core``) makes a video's depth maps agree with each other, but its 8x10
log-scale grid per frame cannot give them per-pixel shape. This package owns the step after
it: per-pixel depth from the images themselves, searched in a narrow band around MEDeA's
depth, with a per-pixel confidence from multi-view agreement, and MEDeA's depth kept where
the images say nothing. No file IO, no OpenCV, no open3d. See :func:`refine_depth`.
"""

from .config import MvsConfig
from .consistency import consistent_views
from .fill import propagate_log_ratio
from .refine import RefineResult, refine_depth
from .sweep import patch_statistics, select_winner, sweep_cost
from .views import select_sources

__all__ = [
    "MvsConfig",
    "RefineResult",
    "consistent_views",
    "patch_statistics",
    "propagate_log_ratio",
    "refine_depth",
    "select_sources",
    "select_winner",
    "sweep_cost",
]
