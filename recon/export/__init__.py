"""Writing results into an output folder: meshes (PLY, GLB in glTF axes), TUM trajectory,
intrinsics JSON, depth maps (16-bit PNG mm + float32 .npy), report (`writers`). The
folder's layout and atomic writing are :mod:`recon.io.output_folder`'s."""

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
    "export_reconstruction",
    "glb_bytes",
    "to_gltf_axes",
    "write_depth_frame",
    "write_depth_maps",
    "write_intrinsics_json",
    "write_mesh_glb",
    "write_mesh_ply",
    "write_point_cloud_ply",
    "write_trajectory_tum",
]
