"""`recon view`'s work: which recording to open, and logging a finished output folder to
Rerun when the run saved no recording (the mesh, every frame's camera with its intrinsics,
the trajectory, and the depth maps).

The folder is read through :mod:`recon.io.output_folder`; logging goes through a
:class:`viewer.RerunLogger` the caller opens.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.io.output_folder import (
    INTRINSICS_JSON,
    MESH_PLY,
    RECORDING,
    TRAJECTORY,
    depth_files,
    read_depth,
    read_intrinsics,
    read_mesh,
    read_report,
    read_trajectory,
)


def recording_of(target: Path) -> Path | None:
    """The .rrd to open for `target` (an .rrd file, or a folder holding recording.rrd), or None."""
    target = Path(target)
    if target.is_file():
        if target.suffix != ".rrd":
            raise ReconInputError(f"{target}: not an .rrd recording or an output folder")
        return target
    candidate = target / RECORDING
    return candidate if candidate.is_file() else None


def _frame_numbers(report: dict | None, count: int) -> list[int]:
    # The source frame numbers when the report has one per camera, else 0..count-1.
    indices = report.get("frames", {}).get("indices") if report is not None else None
    return list(range(count)) if indices is None or len(indices) != count else indices


def _camera(folder: Path, intrinsics, depth_paths: list[Path]) -> tuple | None:
    """(fx, fy, cx, cy, width, height) of the depth maps (intrinsics.json's size, else the first
    map's), or None without intrinsics or a size."""
    if intrinsics is None:
        return None
    saved = json.loads((folder / INTRINSICS_JSON).read_text())
    if "width" in saved and "height" in saved:
        return (*intrinsics, int(saved["width"]), int(saved["height"]))
    if depth_paths:
        height, width = read_depth(depth_paths[0], mmap=True).shape[:2]
        return (*intrinsics, width, height)
    return None


def log_output_folder(folder, logger, progress: bool = True) -> str:
    """Log mesh, cameras and depth of an output folder to `logger`; returns a one-line summary."""
    from tqdm.auto import tqdm

    folder = Path(folder)
    if not folder.is_dir():
        raise ReconInputError(f"{folder}: not an output folder")
    if not (folder / MESH_PLY).is_file() and not (folder / TRAJECTORY).is_file():
        raise ReconInputError(f"{folder}: no {MESH_PLY} or {TRAJECTORY} (not an output folder of `recon run`)")
    poses = read_trajectory(folder)
    intrinsics = read_intrinsics(folder)
    depth_paths = depth_files(folder)
    report = read_report(folder)
    count = len(poses) if poses is not None else len(depth_paths)
    indices = _frame_numbers(report, count)
    depth_of = dict(zip(indices, depth_paths))
    if depth_paths and poses is not None and len(depth_paths) != len(poses):
        # A streamed run tracks every frame and gives some of them depth (report.json says which).
        depth_indices = (report or {}).get("frames", {}).get("depth_indices")
        if depth_indices is None or len(depth_indices) != len(depth_paths):
            raise ReconInputError(f"{folder}: {len(depth_paths)} depth maps for {len(poses)} poses in {TRAJECTORY}, "
                                  "and report.json does not say which frames they belong to")
        depth_of = dict(zip(depth_indices, depth_paths))
    # Every camera with its pinhole, the frames without depth too (a streamed run gives depth to
    # some): the pinhole carries the size of the image it is in pixels of.
    camera = _camera(folder, intrinsics, depth_paths)
    for k in tqdm(range(count), desc="rerun logging", unit="frame", disable=not progress, leave=False):
        depth = read_depth(depth_of[indices[k]], mmap=True) if indices[k] in depth_of else None
        pose = poses[k] if poses is not None else None
        logger.log_frame(int(indices[k]), None, adjusted_depth=depth, pose=pose, intrinsics=camera)
    mesh = read_mesh(folder)
    triangles = 0
    if mesh is not None:
        triangles = len(mesh.triangles)
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
        logger.log_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), colors)
    return f"{count} cameras, {len(depth_paths)} depth maps, mesh of {triangles} triangles from {folder}"


__all__ = ["log_output_folder", "recording_of"]
