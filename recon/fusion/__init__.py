"""TSDF fusion of metric depth maps into a mesh (`tsdf`)."""

from .tsdf import (
    FusionOptions,
    FusionResult,
    auto_max_depth,
    auto_voxel_size,
    estimate_block_count,
    fuse,
    o3d_device,
    remove_fragments,
)

__all__ = [
    "FusionOptions",
    "FusionResult",
    "auto_max_depth",
    "auto_voxel_size",
    "estimate_block_count",
    "fuse",
    "o3d_device",
    "remove_fragments",
]
