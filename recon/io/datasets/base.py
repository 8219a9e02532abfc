"""The common RGB-D dataset record and the file helpers every reader shares.

This module owns :class:`RGBDDataset` (frame list, intrinsics, poses, lazy image/depth
loading, frame selection) and the small checks that turn missing or unreadable files into
one-line :class:`~recon.errors.ReconInputError` messages. Layout-specific parsing lives in
the reader modules (``tum``, ``sevenscenes``, ``scannet``, ``arkitscenes``, ``record3d``,
``kitti``, ``colmap_project``, ``redwood``).

Depth files are 16-bit PNGs (raw units, ``depth_scale`` of them per metre) or float maps
(EXR, PFM, TIFF, .npy: metres times ``depth_scale``; non-finite and <= 0 are invalid).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from recon.errors import ReconInputError
from recon.io.depth_maps import read_depth_file
from recon.io.naming import natural_key

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass
class RGBDDataset:
    """An RGB-D sequence on disk: per-frame files, intrinsics, camera-to-world poses.

    Images are loaded lazily by :meth:`rgb` / :meth:`depth`; everything else is in memory.

    kind: layout name ("tum", "7scenes", "scannet", "arkitscenes", "record3d", "kitti",
        "colmap", "redwood").
    name: sequence name (usually the root folder name).
    root: the folder that was opened.
    frame_ids: (N,) frame identifiers (file stems or timestamps as text).
    intrinsics: (fx, fy, cx, cy) in pixels of the images as returned by ``rgb(i)``.
    width, height: size of the returned rgb/depth images.
    rgb_paths: (N,) colour image files.
    depth_paths: (N,) depth files (16-bit PNG, or float EXR/PFM/TIFF/.npy), or None when the
        dataset has no depth.
    poses: (N, 4, 4) float64 camera-to-world (OpenCV axes), NaN where pose_valid is False;
        None when the dataset has no poses.
    pose_valid: (N,) bool, or None with poses.
    timestamps: (N,) float64 seconds, or None.
    depth_scale: raw depth units per metre (1000 for millimetres, 5000 for TUM, 1 for float
        files in metres).
    depth_invalid: raw depth values that mark an invalid pixel (besides 0).
    frame_intrinsics: (N, 4) per-frame (fx, fy, cx, cy) when they vary (ARKit), else None.
    distortion: lens distortion (k1, k2, p1, p2, k3) of the colour images when known; the
        images are returned as stored (not undistorted).
    resize_rgb: resize colour images to ``shape`` on load (ScanNet colour -> depth size).
    depth_intrinsics: (fx, fy, cx, cy) of the depth camera when its images are not registered
        to the colour camera (7-Scenes); ``depth(i)`` then re-registers them into the colour
        camera (:func:`register_depth`). None: depth is already pixel-aligned with colour.
    depth_resize: depth is stored on a coarser grid covering the same field of view as the
        colour image (Record3D's LiDAR depth); ``depth(i)`` scales it up to ``shape`` by
        nearest neighbour (:func:`upscale_nearest`), so it agrees with ``intrinsics``.
    """

    kind: str
    name: str
    root: Path
    frame_ids: list[str]
    intrinsics: tuple[float, float, float, float]
    width: int
    height: int
    rgb_paths: list[Path]
    depth_paths: list[Path] | None = None
    poses: np.ndarray | None = None
    pose_valid: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    depth_scale: float = 1000.0
    depth_invalid: tuple[int, ...] = ()
    frame_intrinsics: np.ndarray | None = None
    distortion: tuple[float, ...] | None = None
    resize_rgb: bool = False
    depth_intrinsics: tuple[float, float, float, float] | None = None
    depth_resize: bool = False

    def __post_init__(self) -> None:
        n = len(self.frame_ids)
        if self.poses is not None and self.pose_valid is None:
            self.pose_valid = np.isfinite(self.poses).all(axis=(1, 2))
        for label, seq in (
            ("rgb_paths", self.rgb_paths),
            ("depth_paths", self.depth_paths),
            ("poses", self.poses),
            ("timestamps", self.timestamps),
            ("frame_intrinsics", self.frame_intrinsics),
        ):
            if seq is not None and len(seq) != n:
                raise ValueError(f"{label} has {len(seq)} entries for {n} frames")

    # ---------------------------------------------------------------- basic facts

    def __len__(self) -> int:
        return len(self.frame_ids)

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the returned images."""
        return self.height, self.width

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (float64) of ``intrinsics``."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def has_depth(self) -> bool:
        return self.depth_paths is not None

    @property
    def has_poses(self) -> bool:
        return self.poses is not None

    def intrinsics_of(self, i: int) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of frame i (per-frame values when the dataset has them)."""
        if self.frame_intrinsics is not None:
            return tuple(float(v) for v in self.frame_intrinsics[i])
        return self.intrinsics

    # ---------------------------------------------------------------- loading

    def rgb(self, i: int) -> np.ndarray:
        """Colour image of frame i: (H, W, 3) uint8 RGB."""
        image = read_rgb(self.rgb_paths[i])
        if self.resize_rgb and image.shape[:2] != (self.height, self.width):
            # INTER_AREA averages when shrinking, avoiding the aliasing of nearest/linear.
            image = cv2.resize(image, (self.width, self.height), interpolation=cv2.INTER_AREA)
        if image.shape[:2] != (self.height, self.width):
            raise ReconInputError(
                f"{self.rgb_paths[i]}: image is {image.shape[1]}x{image.shape[0]}, "
                f"expected {self.width}x{self.height} like the first frame"
            )
        return image

    def depth(self, i: int) -> np.ndarray | None:
        """Depth of frame i: (H, W) float32 metres, 0 = invalid; None without depth."""
        if self.depth_paths is None:
            return None
        depth = read_depth(self.depth_paths[i], self.depth_scale, self.depth_invalid)
        if self.depth_resize and depth.shape != (self.height, self.width):
            depth = upscale_nearest(depth, (self.height, self.width), self.depth_paths[i])
        if depth.shape != (self.height, self.width):
            raise ReconInputError(
                f"{self.depth_paths[i]}: depth is {depth.shape[1]}x{depth.shape[0]}, "
                f"expected {self.width}x{self.height}"
            )
        if self.depth_intrinsics is not None and tuple(self.depth_intrinsics) != tuple(self.intrinsics):
            depth = register_depth(depth, self.depth_intrinsics, self.intrinsics)
        return depth

    def load_rgb_batch(self, indices: Sequence[int] | None = None) -> np.ndarray:
        """Colour images (B, H, W, 3) uint8 of `indices` (all frames when None)."""
        indices = range(len(self)) if indices is None else indices
        return np.stack([self.rgb(int(i)) for i in indices])

    def load_depth_batch(self, indices: Sequence[int] | None = None) -> np.ndarray | None:
        """Depths (B, H, W) float32 metres of `indices` (all frames when None); None without depth."""
        if self.depth_paths is None:
            return None
        indices = range(len(self)) if indices is None else indices
        return np.stack([self.depth(int(i)) for i in indices])

    # ---------------------------------------------------------------- selection

    def subset(self, indices: Sequence[int]) -> "RGBDDataset":
        """A dataset of the frames at `indices` (in that order); files stay lazy."""
        idx = np.asarray(indices, dtype=np.int64).ravel()
        if idx.size and (idx.min() < -len(self) or idx.max() >= len(self)):
            raise IndexError(f"frame index out of range for {len(self)} frames")

        def take(seq):
            if seq is None:
                return None
            if isinstance(seq, np.ndarray):
                return seq[idx].copy()
            return [seq[i] for i in idx]

        return dataclasses.replace(
            self,
            frame_ids=take(self.frame_ids),
            rgb_paths=take(self.rgb_paths),
            depth_paths=take(self.depth_paths),
            poses=take(self.poses),
            pose_valid=take(self.pose_valid),
            timestamps=take(self.timestamps),
            frame_intrinsics=take(self.frame_intrinsics),
        )

    def select(self, start: int = 0, stride: int = 1, max_frames: int | None = None) -> "RGBDDataset":
        """Every `stride`-th frame from `start`, at most `max_frames` of them."""
        if stride < 1 or start < 0:
            raise ValueError("stride must be >= 1 and start >= 0")
        idx = np.arange(start, len(self), stride)
        return self.subset(idx if max_frames is None else idx[:max_frames])

    def with_valid_poses(self) -> "RGBDDataset":
        """The frames whose pose is valid (all frames when the dataset has no poses)."""
        if self.pose_valid is None:
            return self
        return self.subset(np.flatnonzero(self.pose_valid))

    def __repr__(self) -> str:
        poses = "none" if self.poses is None else f"{int(self.pose_valid.sum())}/{len(self)} valid"
        return (
            f"RGBDDataset(kind={self.kind!r}, name={self.name!r}, frames={len(self)}, "
            f"size={self.width}x{self.height}, intrinsics={tuple(round(v, 3) for v in self.intrinsics)}, "
            f"depth={'yes' if self.has_depth else 'no'}, poses={poses})"
        )


def upscale_nearest(depth: np.ndarray, shape: tuple[int, int], path: Path | None = None) -> np.ndarray:
    """Depth (h, w) -> (H, W) by nearest neighbour with pixel centres aligned, the field of
    view unchanged: output pixel u takes input pixel floor((u + 0.5) * w / W). Nearest keeps
    holes as holes and never blends a foreground and a background depth."""
    (h, w), (big_h, big_w) = depth.shape, shape
    # Another aspect ratio would mean another field of view: scaling could not register it.
    if h > big_h or w > big_w or abs(h - w * big_h / big_w) > 0.5:
        where = f"{path}: " if path is not None else ""
        raise ReconInputError(f"{where}depth is {w}x{h}, not a smaller copy of the {big_w}x{big_h} colour image "
                              "(larger, or another aspect ratio)")
    rows, cols = _nearest_index((h, w), (big_h, big_w))
    return depth[rows[:, None], cols[None, :]]


@functools.lru_cache(maxsize=8)
def _nearest_index(small: tuple[int, int], large: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(rows (H,), cols (W,)): the source index of each output row and column of upscale_nearest."""
    # cv2.INTER_NEAREST takes floor(u * w / W), which shifts the map by up to half an input pixel.
    rows = ((np.arange(large[0]) + 0.5) * small[0] / large[0]).astype(np.int64)
    cols = ((np.arange(large[1]) + 0.5) * small[1] / large[1]).astype(np.int64)
    return rows, cols


def register_depth(depth: np.ndarray, depth_k, colour_k) -> np.ndarray:
    """Depth (..., H, W) seen by the depth camera -> the same z-depth on the colour camera's pixels.

    depth_k, colour_k: (fx, fy, cx, cy) of the two cameras. Both are taken to share the pose
    (on a Kinect v1 they are ~2.5 cm apart, which is ignored); only the intrinsics differ.
    Nearest-neighbour lookup keeps holes as holes; pixels the depth camera does not see are 0.
    """
    inside, dv, du = _registration_lookup(depth.shape[-2:], tuple(map(float, depth_k)), tuple(map(float, colour_k)))
    out = np.zeros_like(depth)
    out[..., inside] = depth[..., dv, du]
    return out


@functools.lru_cache(maxsize=8)
def _registration_lookup(shape, depth_k, colour_k) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inside (H, W) bool, dv (M,), du (M,)): the depth-camera pixel of each colour pixel
    that has one. The same for every frame of a sequence, so it is computed once."""
    height, width = shape
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    # Colour pixel -> viewing ray -> depth-camera pixel on the same ray (z-depth is unchanged).
    du = np.rint((u - colour_k[2]) / colour_k[0] * depth_k[0] + depth_k[2]).astype(np.int64)
    dv = np.rint((v - colour_k[3]) / colour_k[1] * depth_k[1] + depth_k[3]).astype(np.int64)
    inside = (du >= 0) & (du < width) & (dv >= 0) & (dv < height)
    return inside, dv[inside], du[inside]


# ------------------------------------------------------------------------------------
# Shared file helpers
# ------------------------------------------------------------------------------------


def require_dir(path: Path, what: str = "folder") -> Path:
    """`path` if it is a folder, else a one-line error."""
    if not path.is_dir():
        raise ReconInputError(f"{path}: {what} not found")
    return path


def require_file(path: Path, what: str = "file") -> Path:
    """`path` if it is a file, else a one-line error."""
    if not path.is_file():
        raise ReconInputError(f"{path}: {what} not found")
    return path


def list_images(folder: Path, suffixes: Sequence[str] = IMAGE_SUFFIXES) -> list[Path]:
    """Image files of `folder` with one of `suffixes`, naturally sorted."""
    require_dir(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes and not p.name.startswith(".")]
    return sorted(files, key=lambda p: natural_key(p.name))


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB image from a file; one-line error when missing or unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise ReconInputError(f"{path}: cannot read colour image (missing or corrupt)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth_png(path: Path, scale: float, invalid: Sequence[int] = ()) -> np.ndarray:
    """(H, W) float32 metres from a 16-bit depth PNG (raw / `scale`); 0 and `invalid` raw values -> 0."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ReconInputError(f"{path}: cannot read depth image (missing or corrupt)")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ReconInputError(
            f"{path}: expected a single-channel 16-bit depth PNG, got {raw.dtype} with shape {raw.shape}"
        )
    depth = raw.astype(np.float32) / np.float32(scale)
    if len(invalid):
        depth[np.isin(raw, np.asarray(invalid, dtype=np.uint16))] = 0.0
    return depth


def read_depth(path: Path, scale: float, invalid: Sequence[int] = ()) -> np.ndarray:
    """(H, W) float32 metres of a depth file: a 16-bit PNG (read_depth_png) or a float map
    (EXR, PFM, TIFF, .npy) in units of 1 / `scale` metres, its non-finite and <= 0 values -> 0."""
    if path.suffix.lower() == ".png":
        return read_depth_png(path, scale, invalid)
    if not path.is_file():
        raise ReconInputError(f"{path}: depth file not found")
    depth = read_depth_file(path)
    if scale != 1.0:
        depth = depth / np.float32(scale)
    # Float maps mark "no measurement" with NaN, inf or 0 (and sometimes negative values).
    depth[~((depth > 0) & np.isfinite(depth))] = 0.0
    return depth


def image_shape(path: Path) -> tuple[int, int]:
    """(H, W) of an image file (reads it; used once per dataset)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ReconInputError(f"{path}: cannot read image (missing or corrupt)")
    return image.shape[0], image.shape[1]


def check_exist(paths: Sequence[Path], listing: Path | None = None) -> None:
    """One-line error naming the first missing file (and the list file that named it)."""
    for p in paths:
        if not p.is_file():
            src = f" (listed in {listing})" if listing is not None else ""
            raise ReconInputError(f"{p}: file not found{src}")


def read_matrix_txt(path: Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Whitespace-separated matrix from a text file (float64); one-line error on bad content."""
    require_file(path)
    rows = []
    for lineno, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), start=1):
        tokens = line.replace(",", " ").split()
        if not tokens or tokens[0].startswith("#"):
            continue
        try:
            rows.append([float(t) for t in tokens])
        except ValueError:
            raise ReconInputError(f"{path}:{lineno}: non-numeric value in matrix") from None
        if len(rows[-1]) != len(rows[0]):
            raise ReconInputError(f"{path}:{lineno}: expected {len(rows[0])} numbers, got {len(rows[-1])}")
    matrix = np.asarray(rows, dtype=np.float64)
    if shape is not None and matrix.shape != shape:
        got = "x".join(map(str, matrix.shape)) if matrix.size else "nothing"
        raise ReconInputError(f"{path}: expected a {shape[0]}x{shape[1]} matrix, got {got}")
    return matrix


def intrinsics_from_K(K: np.ndarray) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from a 3x3 (or 4x4) intrinsic matrix."""
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
