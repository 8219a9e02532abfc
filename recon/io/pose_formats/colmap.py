"""COLMAP sparse models as pose files: reading and writing ``cameras`` / ``images``.

COLMAP stores world-to-camera (``cam_from_world``) poses; everything here hands back and
takes camera-to-world (N, 4, 4) poses with OpenCV axes, like the other formats of
:mod:`recon.io.pose_formats.trajectories`. Binary models need pycolmap; text models do not.
Images are ordered by :func:`recon.io.naming.natural_key`. Camera parameters follow COLMAP's
``models.h``, distortion handed back in OpenCV's order; the principal point loses
:data:`~recon.io.pose_formats.base.PIXEL_CENTRE` as it is read and gains it as it is written.
More: docs/input.md#pose-files
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.rigid import matrix_to_quat, quat_to_matrix
from recon.io.naming import natural_key
from recon.io.pose_formats.base import (
    PIXEL_CENTRE,
    PoseData,
    check_poses,
    data_lines,
    input_error,
    move_files_into,
    normalise_intrinsics,
    parse_floats,
    read_text,
)
from recon.poses.result import invert_poses

# COLMAP camera models whose first parameters are (f, cx, cy) rather than (fx, fy, cx, cy).
_COLMAP_SINGLE_FOCAL = {"SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"}
# Parameter count of each COLMAP camera model (models.h).
COLMAP_PARAM_COUNTS = {
    "SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12, "FOV": 5, "SIMPLE_RADIAL_FISHEYE": 4, "RADIAL_FISHEYE": 5, "THIN_PRISM_FISHEYE": 12,
    "RAD_TAN_THIN_PRISM_FISHEYE": 16,
}
# Where a model's distortion terms go in OpenCV's (k1, k2, p1, p2, k3): parameter index -> slot.
# Models absent here (fisheye, FOV) distort differently from OpenCV's pinhole model.
_OPENCV_SLOTS = {
    "SIMPLE_PINHOLE": {},
    "PINHOLE": {},
    "SIMPLE_RADIAL": {3: 0},
    "RADIAL": {3: 0, 4: 1},
    "OPENCV": {4: 0, 5: 1, 6: 2, 7: 3},
    "FULL_OPENCV": {4: 0, 5: 1, 6: 2, 7: 3, 8: 4},
}


def _import_pycolmap(required: bool):
    """pycolmap module, or None (or a one-line error when `required`)."""
    try:
        import pycolmap
    except ImportError:
        if required:
            raise ReconInputError(
                "binary COLMAP models need pycolmap (optional dependency): pip install pycolmap"
            ) from None
        return None
    return pycolmap


def colmap_model_dir(path) -> Path | None:
    """The folder holding cameras.* and images.* for a COLMAP path (model, project or file)."""
    path = Path(path)
    if path.is_file():
        path = path.parent
    for cand in (path, path / "sparse" / "0", path / "sparse", path / "0"):
        for ext in (".bin", ".txt"):
            if (cand / f"cameras{ext}").is_file() and (cand / f"images{ext}").is_file():
                return cand
    return None


def opencv_distortion(model: str, params) -> tuple[float, ...] | None:
    """OpenCV's (k1, k2, p1, p2, k3) of a COLMAP camera's parameters; zeros for a pinhole
    model, None for one whose distortion OpenCV's pinhole model cannot express."""
    slots = _OPENCV_SLOTS.get(model)
    # FULL_OPENCV's k4..k6 are the rational model's denominator, which 5 terms cannot hold.
    if slots is None or (model == "FULL_OPENCV" and any(float(v) for v in params[9:12])):
        return None
    out = [0.0] * 5
    for index, slot in slots.items():
        out[slot] = float(params[index])
    return tuple(out)


def _colmap_intrinsics(model: str, width: int, height: int, params) -> dict:
    """fx fy cx cy width height, model and OpenCV distortion (see opencv_distortion) of a COLMAP camera."""
    p = [float(v) for v in params]
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if model in _COLMAP_SINGLE_FOCAL else (p[0], p[1], p[2], p[3])
    return {"fx": fx, "fy": fy, "cx": cx - PIXEL_CENTRE, "cy": cy - PIXEL_CENTRE,
            "width": int(width), "height": int(height), "model": model,
            "distortion": opencv_distortion(model, p)}


def _read_colmap_pycolmap(pycolmap, model_dir: Path):
    """(names, world-to-camera (N, 3, 4), camera ids, {id: intrinsics}) via pycolmap."""
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises bare RuntimeError/ValueError for corrupt models
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise input_error(model_dir, f"cannot read COLMAP model ({first})") from None
    names, w2c, cam_ids = [], [], []
    for _, img in sorted(rec.images.items(), key=lambda kv: natural_key(kv[1].name)):
        has_pose = getattr(img, "has_pose", getattr(img, "registered", True))
        cfw = img.cam_from_world
        # pycolmap >= 3.12 turned cam_from_world into a method (poses live on frames).
        cfw = cfw() if callable(cfw) and has_pose else cfw
        w2c.append(np.asarray(cfw.matrix(), np.float64) if has_pose else np.full((3, 4), np.nan))
        names.append(img.name)
        cam_ids.append(img.camera_id)
    cams = {}
    for cid, cam in rec.cameras.items():
        model = cam.model_name if hasattr(cam, "model_name") else str(cam.model).split(".")[-1]
        cams[cid] = _colmap_intrinsics(model, cam.width, cam.height, cam.params)
    return names, w2c, cam_ids, cams


def _read_colmap_text(model_dir: Path):
    """(names, world-to-camera (N, 3, 4), camera ids, {id: intrinsics}) from a text model."""
    cams = {}
    cam_path = model_dir / "cameras.txt"
    for lineno, tokens in data_lines(cam_path):
        if len(tokens) < 5:
            raise input_error(cam_path, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]", lineno)
        vals = parse_floats(cam_path, lineno, [tokens[0], *tokens[2:]])
        expected = COLMAP_PARAM_COUNTS.get(tokens[1])
        if expected is None:
            raise input_error(cam_path, f"unknown camera model {tokens[1]!r}", lineno)
        if len(vals) - 3 != expected:
            raise input_error(cam_path, f"{tokens[1]} has {expected} parameters, got {len(vals) - 3}", lineno)
        cams[int(vals[0])] = _colmap_intrinsics(tokens[1], vals[1], vals[2], vals[3:])
    img_path = model_dir / "images.txt"
    lines = read_text(img_path).splitlines()
    names, w2c, cam_ids = [], [], []
    k = 0
    while k < len(lines):
        line = lines[k].strip()
        if not line or line.startswith("#"):
            k += 1
            continue
        tokens = line.split()
        if len(tokens) < 10:
            raise input_error(img_path, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", k + 1)
        vals = parse_floats(img_path, k + 1, tokens[1:9])
        rot = quat_to_matrix(np.array([vals[1], vals[2], vals[3], vals[0]]), img_path, [k + 1])[0]
        w2c.append(np.column_stack([rot, vals[4:7]]))
        cam_ids.append(int(vals[7]))
        names.append(" ".join(tokens[9:]))
        k += 2  # the POINTS2D line follows, possibly empty
    return names, w2c, cam_ids, cams


def read_colmap(path) -> PoseData:
    """COLMAP sparse model (binary or text; project, sparse/ or sparse/0 folder) -> PoseData.

    Images are sorted by name; intrinsics are those of the first image's camera. When the
    images use more than one camera, ``frame_intrinsics`` and ``frame_distortion`` hold
    each image's.
    """
    path = Path(path)
    model_dir = colmap_model_dir(path)
    if model_dir is None:
        raise input_error(path, "no COLMAP model (cameras.bin/.txt and images.bin/.txt) found")
    binary = (model_dir / "images.bin").is_file()
    pycolmap = _import_pycolmap(required=binary)
    if pycolmap is not None:
        names, w2c, cam_ids, cams = _read_colmap_pycolmap(pycolmap, model_dir)
    else:
        names, w2c, cam_ids, cams = _read_colmap_text(model_dir)
    if not names:
        raise input_error(model_dir, "COLMAP model has no images")
    if pycolmap is None:
        order = sorted(range(len(names)), key=lambda i: natural_key(names[i]))
        names, w2c, cam_ids = [names[i] for i in order], [w2c[i] for i in order], [cam_ids[i] for i in order]
    w2c = np.stack([np.vstack([m, [0.0, 0.0, 0.0, 1.0]]) for m in w2c])
    valid = np.isfinite(w2c).all(axis=(1, 2))
    check_poses(w2c, model_dir, [f"image {n!r}" for n in names], valid)
    poses = np.full_like(w2c, np.nan)
    poses[valid] = invert_poses(w2c[valid])
    missing = [c for c in cam_ids if c not in cams]
    if missing:
        raise input_error(model_dir, f"image refers to camera {missing[0]} missing from cameras file")
    frame_intrinsics = frame_distortion = None
    if len(set(cam_ids)) > 1:
        frame_intrinsics = np.array([[cams[c][k] for k in ("fx", "fy", "cx", "cy")] for c in cam_ids])
        frame_distortion = np.array([cams[c]["distortion"] or (np.nan,) * 5 for c in cam_ids], dtype=np.float64)
    return PoseData(poses, "colmap", model_dir, names=names, intrinsics=dict(cams[cam_ids[0]]), valid=valid,
                    frame_intrinsics=frame_intrinsics, frame_distortion=frame_distortion)


def _colmap_params(intr: dict) -> list[float]:
    """PINHOLE parameters (fx, fy, cx, cy) in COLMAP's pixel convention (module docstring)."""
    return [intr["fx"], intr["fy"], intr["cx"] + PIXEL_CENTRE, intr["cy"] + PIXEL_CENTRE]


def _colmap_text_model(poses: np.ndarray, names: Sequence[str], intr: dict) -> dict[str, str]:
    """File name -> text of a single-PINHOLE-camera COLMAP text model."""
    w2c = invert_poses(poses)
    q = matrix_to_quat(w2c[:, :3, :3])
    params = " ".join(f"{v:.17g}" for v in _colmap_params(intr))
    cameras = f"# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n1 PINHOLE {intr['width']} {intr['height']} {params}\n"
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, qi, t) in enumerate(zip(names, q, w2c[:, :3, 3]), start=1):
        nums = " ".join(f"{v:.17g}" for v in (qi[3], qi[0], qi[1], qi[2], *t))
        lines.append(f"{i} {nums} 1 {name}")
        lines.append("")
    points = "# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
    return {"cameras.txt": cameras, "images.txt": "\n".join(lines) + "\n", "points3D.txt": points}


def _colmap_reconstruction(pycolmap, poses: np.ndarray, names: Sequence[str], intr: dict):
    """pycolmap.Reconstruction with one PINHOLE camera and one posed image per frame."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(
        model="PINHOLE",
        width=intr["width"],
        height=intr["height"],
        params=_colmap_params(intr),
        camera_id=1,
    )
    w2c = invert_poses(poses)
    with_rigs = hasattr(rec, "add_camera_with_trivial_rig")  # pycolmap >= 3.12 (rigs and frames)
    if with_rigs:
        rec.add_camera_with_trivial_rig(cam)
    else:
        rec.add_camera(cam)
    for i, (name, m) in enumerate(zip(names, w2c), start=1):
        rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(m[:3, :3]), m[:3, 3])
        img = pycolmap.Image(name=str(name), camera_id=1, image_id=i)
        if with_rigs:
            rec.add_image_with_trivial_frame(img, rigid)
        else:
            img.cam_from_world = rigid
            rec.add_image(img)
            rec.register_image(i)
    return rec


def write_colmap(
    path, poses: np.ndarray, names: Sequence[str] | None = None, intrinsics=None, binary: bool = False
) -> None:
    """Write a COLMAP model (one PINHOLE camera, no points) into folder `path`.

    Text by default (readable without pycolmap); binary needs pycolmap. Files are written to
    a temp folder beside `path` and renamed in.
    """
    path = Path(path)
    intr = normalise_intrinsics(intrinsics)
    if intr is None or "width" not in intr:
        raise ValueError("writing a COLMAP model needs intrinsics (fx, fy, cx, cy, width, height)")
    names = [f"frame_{i:06d}.png" for i in range(len(poses))] if names is None else [str(n) for n in names]
    pycolmap = _import_pycolmap(required=binary)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp", dir=path.parent))
    try:
        if pycolmap is not None:
            rec = _colmap_reconstruction(pycolmap, poses, names, intr)
            (rec.write_binary if binary else rec.write_text)(str(tmp))
        else:
            for fname, text in _colmap_text_model(poses, names, intr).items():
                (tmp / fname).write_text(text, encoding="utf-8")
        move_files_into(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
