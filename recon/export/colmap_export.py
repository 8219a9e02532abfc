"""The COLMAP export's model: ``sparse/0/cameras.txt``, ``images.txt`` and ``points3D.txt``.

This module owns the text of the model in COLMAP's text format (the images beside it,
``images/``, are written by :mod:`recon.export.tools`): PINHOLE cameras, cam_from_world poses,
empty 2D-point lines and tracks. Pixel centres: recon puts them at integer coordinates,
COLMAP the first pixel's at (0.5, 0.5): the principal point gains
:data:`recon.io.pose_formats.base.PIXEL_CENTRE` here, and loses it again when
:mod:`recon.io.pose_formats.colmap` reads the model back.
More: docs/export.md#colmaps-text-model
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.geometry.rigid import matrix_to_quat
from recon.io.pose_formats.base import PIXEL_CENTRE
from recon.poses.result import invert_poses

from .run_folder import RunFiles

COLMAP_MODEL_DIR = "sparse/0"


def colmap_text_model(poses: np.ndarray, names: list[str], intrinsics: np.ndarray, size: tuple[int, int],
                      xyz: np.ndarray, rgb: np.ndarray) -> dict[str, str]:
    """File name -> text of a COLMAP text model: a PINHOLE camera per distinct intrinsics
    (N, 4) (recon's pixel convention, shifted here to COLMAP's), images `names` with
    camera-to-world `poses` (N, 4, 4) written as cam_from_world, points xyz (M, 3) with
    colours rgb (M, 3) uint8 and empty tracks."""
    height, width = size
    camera_of: dict[tuple[float, ...], int] = {}
    ids = [camera_of.setdefault(tuple(float(v) for v in k), len(camera_of) + 1) for k in intrinsics]
    cameras = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
               f"# Number of cameras: {len(camera_of)}"]
    for (fx, fy, cx, cy), cid in camera_of.items():
        params = (fx, fy, cx + PIXEL_CENTRE, cy + PIXEL_CENTRE)  # COLMAP's pixel centres (module docstring)
        cameras.append(f"{cid} PINHOLE {width} {height} " + " ".join(f"{v:.17g}" for v in params))
    w2c = invert_poses(poses)
    quats = matrix_to_quat(w2c[:, :3, :3])  # qx qy qz qw
    images = ["# Image list with two lines of data per image:",
              "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)",
              f"# Number of images: {len(names)}, mean observations per image: 0"]
    for image_id, (name, q, t, cid) in enumerate(zip(names, quats, w2c[:, :3, 3], ids), start=1):
        numbers = " ".join(f"{v:.17g}" for v in (q[3], q[0], q[1], q[2], *t))
        images += [f"{image_id} {numbers} {cid} {name}", ""]  # no 2D points, but the line is there
    points = ["# 3D point list with one line of data per point:",
              "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
              f"# Number of points: {len(xyz)}, mean track length: 0"]
    points += [f"{k} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {c[0]} {c[1]} {c[2]} 0"
               for k, (p, c) in enumerate(zip(xyz, rgb), start=1)]
    return {name: "\n".join(lines) + "\n" for name, lines in
            (("cameras.txt", cameras), ("images.txt", images), ("points3D.txt", points))}


def write_colmap_model(folder: Path, run: RunFiles, images: list[str], xyz: np.ndarray, rgb: np.ndarray) -> None:
    """The model of `run` in ``folder/sparse/0/``: its poses in the exported world, the images
    `images` (names inside ``images/``), the points xyz (M, 3) (exported world) with colours rgb."""
    model = folder / COLMAP_MODEL_DIR
    model.mkdir(parents=True)
    for name, text in colmap_text_model(run.world_poses, images, run.intrinsics, run.size, xyz, rgb).items():
        (model / name).write_text(text, encoding="utf-8")


__all__ = ["COLMAP_MODEL_DIR", "colmap_text_model", "write_colmap_model"]
