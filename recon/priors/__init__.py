"""Per-frame depth priors D0 (and encoder features F) for MEDeA.

``make_prior(name, **options)`` builds one of: "fastdepth" (default, metric, CPU-fast),
"folder" (user depth/disparity maps), "sensor" (RGB-D depth arrays), "hf" (local Hugging
Face depth models, optional ``transformers``). Every prior is called as
``prior(frames (N, H, W, 3) uint8, intrinsics) -> PriorOutput``.
"""

from .align import align_affine_disparity, fit_affine_disparity
from .base import PRIOR_KINDS, DepthPrior, PriorOutput
from .fastdepth import FEATURE_LAYERS, FastDepthPrior, load_fastdepth
from .folder import FolderDepthPrior, read_depth_file
from .hf import HFDepthPrior, model_kind
from .registry import available_priors, make_prior, register_prior
from .sensor import SensorDepthPrior
from .weights import find_weights, weight_roots

DEFAULT_PRIOR = "fastdepth"

__all__ = [
    "DEFAULT_PRIOR",
    "FEATURE_LAYERS",
    "PRIOR_KINDS",
    "DepthPrior",
    "FastDepthPrior",
    "FolderDepthPrior",
    "HFDepthPrior",
    "PriorOutput",
    "SensorDepthPrior",
    "align_affine_disparity",
    "available_priors",
    "find_weights",
    "fit_affine_disparity",
    "load_fastdepth",
    "make_prior",
    "model_kind",
    "read_depth_file",
    "register_prior",
    "weight_roots",
]
