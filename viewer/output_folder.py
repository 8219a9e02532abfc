"""Logging a finished output folder of `recon run` to Rerun (for `recon view` when the run
saved no recording): the mesh, the camera trajectory with intrinsics, and the depth maps.

Reads the files :mod:`recon.export.writers` writes (mesh.ply, trajectory.txt,
intrinsics.json, depth/*.npy or depth/*.png, report.json for the frame numbers).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError

RECORDING = "recording.rrd"


def recording_of(target: Path) -> Path | None:
    """The .rrd to open for `target` (an .rrd file, or a folder holding recording.rrd), or None."""
    target = Path(target)
    if target.is_file():
        if target.suffix != ".rrd":
            raise ReconInputError(f"{target}: not an .rrd recording or an output folder")
        return target
    candidate = target / RECORDING
    return candidate if candidate.is_file() else None


def _depth_files(folder: Path) -> list[Path]:
    from recon.io.frames import natural_key

    files = sorted(folder.glob("*.npy"), key=lambda p: natural_key(p.name))
    return files or sorted(folder.glob("*.png"), key=lambda p: natural_key(p.name))


def _read_depth(path: Path) -> np.ndarray:
    from recon.export import read_depth_png_mm

    return np.load(path, mmap_mode="r") if path.suffix == ".npy" else read_depth_png_mm(path)


def log_output_folder(folder, logger, progress: bool = True) -> str:
    """Log mesh, cameras and depth of an output folder; returns a one-line summary."""
    import open3d as o3d
    from tqdm.auto import tqdm

    from recon.poses.formats import read_poses

    folder = Path(folder)
    if not folder.is_dir():
        raise ReconInputError(f"{folder}: not an output folder")
    mesh_path, traj_path = folder / "mesh.ply", folder / "trajectory.txt"
    if not mesh_path.is_file() and not traj_path.is_file():
        raise ReconInputError(f"{folder}: no mesh.ply or trajectory.txt (not an output folder of `recon run`)")
    poses = read_poses(traj_path, "tum").poses if traj_path.is_file() else None
    intrinsics = None
    if (folder / "intrinsics.json").is_file():
        k = json.loads((folder / "intrinsics.json").read_text())
        intrinsics = (k["fx"], k["fy"], k["cx"], k["cy"])
    indices = None
    if (folder / "report.json").is_file():
        indices = json.loads((folder / "report.json").read_text()).get("frames", {}).get("indices")
    depth_files = _depth_files(folder / "depth") if (folder / "depth").is_dir() else []
    count = len(poses) if poses is not None else len(depth_files)
    if depth_files and poses is not None and len(depth_files) != len(poses):
        raise ReconInputError(f"{folder}: {len(depth_files)} depth maps for {len(poses)} poses in trajectory.txt")
    if indices is None or len(indices) != count:
        indices = list(range(count))
    for k in tqdm(range(count), desc="rerun logging", unit="frame", disable=not progress, leave=False):
        depth = _read_depth(depth_files[k]) if depth_files else None
        pose = poses[k] if poses is not None else None
        logger.log_frame(int(indices[k]), None, adjusted_depth=depth, pose=pose,
                         intrinsics=intrinsics if depth is not None else None)
    triangles = 0
    if mesh_path.is_file():
        mesh = o3d.io.read_triangle_mesh(str(mesh_path))
        triangles = len(mesh.triangles)
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colors)
    return f"{count} cameras, {len(depth_files)} depth maps, mesh of {triangles} triangles from {folder}"


__all__ = ["RECORDING", "log_output_folder", "recording_of"]
