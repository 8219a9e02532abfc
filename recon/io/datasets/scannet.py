"""ScanNet exports (SensReader output): ``color/N.jpg``, ``depth/N.png``, ``pose/N.txt``, ``intrinsic/``.

Owns the ScanNet layout. Depth is uint16 millimetres, usually 640x480, while colour is
usually 1296x968. Frames are returned at the *depth* size: colour is resized to it
(INTER_AREA) and the intrinsics are those of ``intrinsic_depth.txt``, so depth and the
intrinsics agree exactly; the resized colour is registered to depth only as well as ScanNet's
colour-to-depth calibration allows (about a pixel). With ``intrinsics_from="color"`` the
colour intrinsics scaled to the depth size are used instead. Pose files holding -inf/nan
(lost tracking) give ``pose_valid`` False and NaN poses.
"""

from __future__ import annotations

from pathlib import Path

from recon.errors import ReconInputError
from recon.io.pose_formats.trajectories import read_matrix_folder

from .base import RGBDDataset, image_shape, intrinsics_from_K, list_images, read_matrix_txt


def is_scannet(root: Path) -> bool:
    """True when `root` looks like a ScanNet export."""
    frames = (root / "color").is_dir() and (root / "depth").is_dir()
    return frames and ((root / "pose").is_dir() or (root / "intrinsic").is_dir())


def open_scannet(root, intrinsics_from: str = "depth") -> RGBDDataset:
    """Open a ScanNet export folder (e.g. ``scene0000_00``); see the module docstring for sizes."""
    root = Path(root)
    if intrinsics_from not in ("depth", "color"):
        raise ValueError("intrinsics_from must be 'depth' or 'color'")
    color = {p.stem: p for p in list_images(root / "color")}
    depth = {p.stem: p for p in list_images(root / "depth", (".png",))}
    if not color:
        raise ReconInputError(f"{root / 'color'}: no colour images")
    ids = [p for p in color]  # list_images sorted naturally: 0, 1, ..., 10
    missing = [i for i in ids if i not in depth]
    if missing or len(depth) != len(color):
        first = (root / "depth" / f"{missing[0]}.png") if missing else (root / "depth")
        raise ReconInputError(f"{first}: {len(color)} colour images but {len(depth)} depth images")

    poses = valid = None
    if (root / "pose").is_dir():
        data = read_matrix_folder(root / "pose", allow_invalid=True)
        by_name = dict(zip(data.names, range(len(data))))
        lacking = [i for i in ids if i not in by_name]
        if lacking:
            first = root / "pose" / f"{lacking[0]}.txt"
            raise ReconInputError(f"{first}: file not found ({len(lacking)} frames lack a pose)")
        order = [by_name[i] for i in ids]
        poses, valid = data.poses[order], data.valid[order]

    height, width = image_shape(depth[ids[0]])
    ch, cw = image_shape(color[ids[0]])
    intr_dir = root / "intrinsic"
    if intrinsics_from == "depth" and (intr_dir / "intrinsic_depth.txt").is_file():
        intrinsics = intrinsics_from_K(read_matrix_txt(intr_dir / "intrinsic_depth.txt", (4, 4)))
    elif (intr_dir / "intrinsic_color.txt").is_file():
        fx, fy, cx, cy = intrinsics_from_K(read_matrix_txt(intr_dir / "intrinsic_color.txt", (4, 4)))
        sx, sy = width / cw, height / ch
        # Pixel centres sit at +0.5: scale the corner-based coordinate, then shift back.
        intrinsics = (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)
    else:
        raise ReconInputError(f"{intr_dir / 'intrinsic_color.txt'}: file not found")
    return RGBDDataset(
        kind="scannet",
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
        resize_rgb=(ch, cw) != (height, width),
    )
