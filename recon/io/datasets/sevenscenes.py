"""Microsoft 7-Scenes sequences (``frame-NNNNNN.color.png|jpg``, ``.depth.png``, ``.pose.txt``).

Owns the 7-Scenes layout: frames keyed by their ``frame-NNNNNN`` stem, depth uint16
millimetres with 0 and 65535 invalid, per-frame 4x4 camera-to-world poses. The published
intrinsics (fx = fy = 585, or ``camera-intrinsics.txt``) are the *depth* camera's: the reader
reports the colour camera's (focal length scaled by 525/585 unless given) and re-registers
the sensor depth into it, so that colour, depth and intrinsics agree.
More: docs/input.md#7-scenes
"""

from __future__ import annotations

from pathlib import Path

from recon.errors import ReconInputError
from recon.io.naming import natural_key
from recon.io.pose_formats.trajectories import read_matrix_folder

from .base import RGBDDataset, image_shape, intrinsics_from_K, read_matrix_txt

DEPTH_INTRINSICS = (585.0, 585.0, 320.0, 240.0)
# Kinect v1: colour focal / depth focal (525 px / 585 px at 640x480).
COLOUR_FOCAL_RATIO = 525.0 / 585.0
INVALID_DEPTH = (65535,)


def _frames(root: Path, tag: str) -> dict[str, Path]:
    """stem ('frame-000000') -> file, for files named ``<stem>.<tag>``."""
    return {p.name.split(".", 1)[0]: p for p in root.glob(f"frame-*.{tag}") if p.is_file()}


def is_7scenes(root: Path) -> bool:
    """True when `root` holds 7-Scenes frame files."""
    return any(root.glob("frame-*.color.*")) or any(root.glob("frame-*.depth.png"))


def open_7scenes(root, colour_intrinsics=None) -> RGBDDataset:
    """Open a 7-Scenes sequence folder (e.g. ``redkitchen/seq-01``).

    colour_intrinsics: (fx, fy, cx, cy) of the colour camera; None: the depth camera's with
    the focal lengths scaled by COLOUR_FOCAL_RATIO. Passing the depth camera's intrinsics
    gives the raw, unregistered depth.
    """
    root = Path(root)
    if not root.is_dir():
        raise ReconInputError(f"{root}: folder not found")
    color = _frames(root, "color.png") | _frames(root, "color.jpg")
    depth = _frames(root, "depth.png")
    if not color:
        seqs = sorted(p.name for p in root.glob("seq-*") if p.is_dir())
        hint = f" (open one sequence folder: {seqs[0]} ...)" if seqs else ""
        raise ReconInputError(f"{root}: no frame-*.color.png/jpg files{hint}")
    ids = sorted(color, key=natural_key)
    missing_depth = [i for i in ids if i not in depth]
    if missing_depth:
        first = root / f"{missing_depth[0]}.depth.png"
        raise ReconInputError(f"{first}: file not found ({len(missing_depth)} of {len(ids)} colour frames lack depth)")
    extra_depth = sorted(set(depth) - set(color), key=natural_key)
    if extra_depth:
        raise ReconInputError(f"{root / (extra_depth[0] + '.color.png')}: file not found (depth without colour)")

    poses = valid = None
    pose_files = [root / f"{i}.pose.txt" for i in ids]
    have = [p.is_file() for p in pose_files]
    if any(have):
        if not all(have):
            raise ReconInputError(f"{pose_files[have.index(False)]}: file not found (other frames have poses)")
        # read_matrix_folder validates rotations and reads the files in natural order == ids.
        data = read_matrix_folder(root)
        if data.names != [f"{i}.pose" for i in ids]:
            raise ReconInputError(f"{root}: pose files do not match the colour frames")
        poses, valid = data.poses, data.valid

    intr_path = root / "camera-intrinsics.txt"
    depth_intrinsics = (intrinsics_from_K(read_matrix_txt(intr_path, (3, 3))) if intr_path.is_file()
                        else DEPTH_INTRINSICS)
    if colour_intrinsics is None:
        fx, fy, cx, cy = depth_intrinsics
        colour_intrinsics = (fx * COLOUR_FOCAL_RATIO, fy * COLOUR_FOCAL_RATIO, cx, cy)
    intrinsics = tuple(float(v) for v in colour_intrinsics)
    height, width = image_shape(color[ids[0]])
    return RGBDDataset(
        kind="7scenes",
        name=root.resolve().name,
        root=root,
        frame_ids=ids,
        intrinsics=intrinsics,
        width=width,
        height=height,
        rgb_paths=[color[i] for i in ids],
        depth_paths=[depth[i] for i in ids],
        poses=poses,
        pose_valid=valid,
        depth_scale=1000.0,
        depth_invalid=INVALID_DEPTH,
        depth_intrinsics=depth_intrinsics,
    )
