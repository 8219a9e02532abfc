"""The nerfstudio export's dataset: ``transforms.json``, ``depth/`` and ``points.ply``.

This module owns those files (the images, ``images/``, are written by
:mod:`recon.export.tools`), after nerfstudio's data conventions and its ``Nerfstudio``
dataparser: camera-to-world ``transform_matrix`` in OpenGL camera axes, millimetre depth
maps on every frame (all zero where a frame got none), ``applied_transform`` when the run was
turned upright. The principal point gains :data:`recon.io.pose_formats.base.PIXEL_CENTRE`
here (nerfstudio casts pixel (0, 0) through (0.5, 0.5)), and loses it again when
:mod:`recon.io.pose_formats.trajectories` reads transforms.json back.
More: docs/export.md#nerfstudios-transformsjson
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import opencv_to_opengl
from recon.io.depth_maps import PNG_DEPTH_SCALE, depth_png_bytes
from recon.io.output_folder import (
    DEPTH_DIR,
    DEPTH_PNG,
    depth_name,
    json_bytes,
    read_depth,
)
from recon.io.pose_formats.base import PIXEL_CENTRE

from .run_folder import RunFiles

TRANSFORMS_JSON = "transforms.json"
POINTS_PLY = "points.ply"
DEPTH_UNIT_SCALE_FACTOR = PNG_DEPTH_SCALE  # depth PNG units (mm) -> metres


def points_ply_bytes(xyz: np.ndarray, rgb: np.ndarray) -> bytes:
    """Binary little-endian PLY of points (M, 3) as float x y z with uchar red green blue
    (written here: Open3D's writer truncates colours, 255 * (k / 255) can come out k - 1)."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    rows = np.empty(len(xyz), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    rows["xyz"], rows["rgb"] = xyz, rgb
    return header.encode("ascii") + rows.tobytes()


def nerfstudio_transforms(poses: np.ndarray, files: list[str], intrinsics: np.ndarray, size: tuple[int, int],
                          depth_paths: list[str] | None = None, ply: str | None = None,
                          applied: np.ndarray | None = None) -> dict:
    """transforms.json's content: camera-to-world `poses` (N, 4, 4) in OpenCV axes (written in
    OpenGL's), image paths `files`, intrinsics (N, 4) in recon's pixel convention (shifted
    here to nerfstudio's), depth map paths (or None), the point cloud's path (or None) and
    the transform applied to the original world (4, 4) or None."""
    height, width = size
    keys = ("fl_x", "fl_y", "cx", "cy")
    # nerfstudio's pixel centres (module docstring).
    shifted = np.asarray(intrinsics, np.float64) + [0.0, 0.0, PIXEL_CENTRE, PIXEL_CENTRE]
    shared = bool((shifted == shifted[0]).all())
    data: dict = {"camera_model": "OPENCV"}
    if shared:
        data.update(zip(keys, map(float, shifted[0])))
    data.update(w=int(width), h=int(height), k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    if depth_paths is not None:
        data["depth_unit_scale_factor"] = DEPTH_UNIT_SCALE_FACTOR
    if ply is not None:
        data["ply_file_path"] = ply
    if applied is not None:
        data["applied_transform"] = np.asarray(applied, np.float64)[:3].tolist()
    frames = []
    for k, (name, matrix) in enumerate(zip(files, opencv_to_opengl(poses))):
        frame = {"file_path": name, "transform_matrix": matrix.tolist()}
        if not shared:
            frame.update(zip(keys, map(float, shifted[k])))
        if depth_paths is not None:
            frame["depth_file_path"] = depth_paths[k]
        frames.append(frame)
    data["frames"] = frames
    return data


def _png_size(data: bytes) -> tuple[int, int] | None:
    """(H, W) from a PNG's header, None when it is not a PNG."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or len(data) < 24:
        return None
    width, height = struct.unpack(">II", data[16:24])
    return height, width


def _depth_png(run: RunFiles, row: int, empty: bytes) -> bytes:
    """The row-th frame's depth map as a 16-bit millimetre PNG: the run's own PNG, encoded
    from its .npy when there is no PNG, `empty` for a frame without depth."""
    path = run.depth.get(int(run.indices[row]))
    if path is None:
        return empty
    png = path.with_suffix(DEPTH_PNG)
    data = png.read_bytes() if png.is_file() else depth_png_bytes(read_depth(path))
    if _png_size(data) != tuple(run.size):
        raise ReconInputError(f"{png}: not a {run.size[1]}x{run.size[0]} depth PNG like the run's intrinsics say")
    return data


def write_nerfstudio_dataset(folder: Path, run: RunFiles, files: list[str], xyz: np.ndarray, rgb: np.ndarray) -> int:
    """transforms.json, depth/ and points.ply of `run` in `folder`: its poses in the exported
    world, the images `files` (paths inside `folder`), the points xyz (M, 3) (exported world)
    with colours rgb; returns how many frames have a depth map."""
    depth = None
    if run.depth:
        (folder / DEPTH_DIR).mkdir()
        empty = depth_png_bytes(np.zeros(run.size, np.float32))
        depth = [depth_name(run.stem(k), DEPTH_PNG) for k in range(len(files))]
        for k, name in enumerate(depth):
            (folder / name).write_bytes(_depth_png(run, k, empty))
    if len(xyz):
        (folder / POINTS_PLY).write_bytes(points_ply_bytes(xyz, rgb))
    data = nerfstudio_transforms(run.world_poses, files, run.intrinsics, run.size, depth,
                                 POINTS_PLY if len(xyz) else None, run.transform)
    (folder / TRANSFORMS_JSON).write_bytes(json_bytes(data))
    return sum(int(index) in run.depth for index in run.indices) if depth else 0

__all__ = [
    "DEPTH_UNIT_SCALE_FACTOR",
    "POINTS_PLY",
    "TRANSFORMS_JSON",
    "nerfstudio_transforms",
    "points_ply_bytes",
    "write_nerfstudio_dataset",
]
