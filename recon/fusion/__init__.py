"""TSDF fusion of metric depth maps into a mesh: `sizing` (the voxel, the depth range and the
memory budget), `tsdf` (the whole-sequence fuse), `volume` (one growing volume, extraction
and clean-up), `decimate` (a mesh thinned to the triangle budget)."""

from .sizing import auto_max_depth, auto_voxel_size, estimate_block_count
from .tsdf import (
    FusionOptions,
    FusionResult,
    confidence_weight,
    fuse,
    fusion_device,
    o3d_device,
    remove_fragments,
    volume_size,
)
from .volume import TsdfVolume

__all__ = [
    "FusionOptions",
    "FusionResult",
    "auto_max_depth",
    "auto_voxel_size",
    "confidence_weight",
    "estimate_block_count",
    "fuse",
    "fusion_device",
    "o3d_device",
    "remove_fragments",
    "TsdfVolume",
    "volume_size",
]
