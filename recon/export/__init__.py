"""Writing results into an output folder: meshes (PLY, GLB in glTF axes), TUM trajectory,
intrinsics JSON, depth maps (16-bit PNG mm + float32 .npy), report (`writers`). The
folder's layout and atomic writing are :mod:`recon.io.output_folder`'s.

Exports of a finished output folder for other tools (``recon export``): a COLMAP text
model (images/, sparse/0/) and a nerfstudio dataset (transforms.json, images/, depth/,
points.ply). `tools` runs them (options, layout, images, atomic folders); `run_folder`
reads the output folder back and decodes the frames again from the run's input;
`colmap_export` and `nerfstudio_export` write each format's own files."""

from .tools import (
    EXPORT_FORMATS,
    ExportOptions,
    ExportResult,
    export_colmap,
    export_folder,
    export_nerfstudio,
    parse_formats,
)
from .writers import (
    export_reconstruction,
    glb_bytes,
    to_gltf_axes,
    write_depth_frame,
    write_depth_maps,
    write_intrinsics_json,
    write_mesh_glb,
    write_mesh_ply,
    write_point_cloud_ply,
    write_trajectory_tum,
)

__all__ = [
    "EXPORT_FORMATS",
    "ExportOptions",
    "ExportResult",
    "export_colmap",
    "export_folder",
    "export_nerfstudio",
    "export_reconstruction",
    "glb_bytes",
    "parse_formats",
    "to_gltf_axes",
    "write_depth_frame",
    "write_depth_maps",
    "write_intrinsics_json",
    "write_mesh_glb",
    "write_mesh_ply",
    "write_point_cloud_ply",
    "write_trajectory_tum",
]
