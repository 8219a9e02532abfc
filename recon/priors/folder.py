"""User-supplied depth (or disparity) maps from a folder, as a prior.

This module owns matching depth files to frames (by file stem, else by natural sorted
order) and the checks that turn a bad map into a one-line ReconInputError naming the frame
and file. Reading the files is :mod:`recon.io.depth_maps`.
NaN and inf mark invalid pixels like 0 does (depth tools commonly write NaN for "no
depth"): they become 0, and the output's info counts them per file (``nonfinite_pixels``,
``nonfinite_files``); only a map with no valid pixel at all is an error.
Affine-invariant disparity is aligned to metric depth by :mod:`recon.priors.align` when an
``align_to`` reference is given (see DepthPrior).
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import ReconInputError
from ..io.depth_maps import DEPTH_SUFFIXES, list_depth_files, read_depth_file
from .base import DepthPrior, PriorOutput
from .resample import resize_nearest

# Role words that name the same frame differently in colour and depth files
# ("frame-000001.color.jpg" <-> "frame-000001.depth.png").
_ROLE_SUFFIX = re.compile(r"[._-](colou?r|rgb|image|img|depth|disp|disparity|pred|prediction)$", re.IGNORECASE)


def stem_keys(name: str) -> tuple[str, ...]:
    """Keys a file is matched by: its stem, and the stem without a role word."""
    stem = Path(name).stem
    bare = _ROLE_SUFFIX.sub("", stem)
    return (stem,) if bare == stem else (stem, bare)


def match_depth_files(files: list[Path], frame_names: list[str] | None, count: int, folder: Path) -> list[Path]:
    """One depth file per frame: by stem when frame names are known, else in sorted order.

    Raises:
        ReconInputError: a frame without a depth file, or (by order) a count mismatch.
    """
    if frame_names is None:
        if len(files) != count:
            raise ReconInputError(
                f"{folder}: {len(files)} depth files for {count} frames (matching by sorted order needs one per"
                " frame; pass frame names to match by file stem)"
            )
        return list(files)
    index: dict[str, Path] = {}
    for path in files:
        for key in stem_keys(path.name):
            index.setdefault(key, path)
    matched = []
    for k, name in enumerate(frame_names):
        path = next((index[key] for key in stem_keys(name) if key in index), None)
        if path is None:
            raise ReconInputError(f"{folder}: no depth file for {name} (expected e.g. {Path(name).stem}.npy)")
        matched.append(path)
    return matched


def check_map(values: np.ndarray, kind: str, frame, path: Path, allow_nan: bool = True) -> tuple[np.ndarray, int]:
    """Validate one map and mark invalid pixels 0: zero, NaN and inf ones (depth: also
    negative ones). frame: how the error names the frame (its index or name).

    Returns:
        The map (float32) and its number of NaN and inf pixels.

    Raises:
        ReconInputError: no valid pixel at all, or NaN present with ``allow_nan`` False.
    """
    finite = np.isfinite(values)
    if not allow_nan and np.isnan(values).any():
        raise ReconInputError(
            f"{path}: {kind} of frame {frame} contains NaN ({int(np.isnan(values).sum())} pixels)"
            " and NaN is not allowed (allow_nan=False)"
        )
    valid = finite & (values > 0) if kind == "depth" else finite & (values != 0)
    if not valid.any():
        raise ReconInputError(f"{path}: {kind} of frame {frame} has no valid pixel (all zero, NaN or inf)")
    return np.where(valid, values, 0.0).astype(np.float32), int(finite.size - np.count_nonzero(finite))


class FolderDepthPrior(DepthPrior):
    """Depth or disparity maps the user computed elsewhere.

    Args:
        path: folder of depth files.
        frame_names: names of the frames (e.g. their image file names), to match depth files
            by stem (role words like ".color"/".depth" ignored); None: sorted natural order,
            one file per frame.
        kind: "depth" (metric, metres after ``depth_scale``) or "disparity" (affine-invariant;
            output kind "affine_disparity", or "metric" when ``align_to`` is given).
        depth_scale: metres per stored unit; default 0.001 for 16-bit PNG, 1 otherwise.
        resize: resize maps of another size (same aspect) to the frame size with nearest
            neighbours; False makes a size mismatch an error.
        allow_nan: read NaN (like inf) as an invalid pixel; False makes a map with NaN an
            error instead.

    The output's ``info`` counts the NaN and inf pixels read as invalid:
    ``nonfinite_pixels`` (all maps of the call) and ``nonfinite_files`` ({file name: pixels},
    only the files that have any).
    """

    name = "folder"

    def __init__(self, path, frame_names=None, kind: str = "depth", depth_scale: float | None = None,
                 resize: bool = True, allow_nan: bool = True, batch_size: int = 16, device: str = "cpu",
                 progress: bool = True, align_to=None):
        super().__init__(batch_size=batch_size, device=device, progress=progress, align_to=align_to)
        if kind not in ("depth", "disparity"):
            raise ValueError(f"folder prior kind must be 'depth' or 'disparity', got {kind!r}")
        self.folder = Path(path)
        if not self.folder.is_dir():
            raise ReconInputError(f"{self.folder}: depth folder does not exist")
        self.files = list_depth_files(self.folder)
        if not self.files:
            raise ReconInputError(f"{self.folder}: no depth files ({', '.join(DEPTH_SUFFIXES)})")
        self.frame_names = None if frame_names is None else [str(n) for n in frame_names]
        self.kind = kind
        self.depth_scale = depth_scale
        self.resize = resize
        self.allow_nan = allow_nan
        self.nonfinite: dict[str, int] = {}  # of the current call: file name -> NaN/inf pixels

    def plan(self, frames, intrinsics) -> list[Path]:
        if self.frame_names is not None and len(self.frame_names) != len(frames):
            raise ReconInputError(f"{self.folder}: {len(self.frame_names)} frame names for {len(frames)} frames")
        self.nonfinite = {}
        return match_depth_files(self.files, self.frame_names, len(frames), self.folder)

    def load(self, frame: int, path: Path, size: tuple[int, int]) -> np.ndarray:
        """One checked map (H, W) float32 at the frame size; its NaN/inf pixels are counted."""
        # By name when known: the streamed pipeline calls the prior batch by batch, so the
        # index is only the frame's place in the batch.
        label = frame if self.frame_names is None else self.frame_names[frame]
        values, nonfinite = check_map(read_depth_file(path, self.depth_scale), self.kind, label, path,
                                      self.allow_nan)
        if nonfinite:
            self.nonfinite[path.name] = nonfinite
        if values.shape != size:
            if not self.resize:
                raise ReconInputError(
                    f"{path}: depth of frame {label} is {values.shape[0]}x{values.shape[1]},"
                    f" the frame is {size[0]}x{size[1]} (resizing disabled)"
                )
            try:
                values = resize_nearest(values, size)
            except ValueError as exc:
                raise ReconInputError(f"{path}: frame {label}: {exc}") from None
        return values

    def predict_batch(self, frames, intrinsics, indices, plan=None) -> PriorOutput:
        files = plan if plan is not None else self.plan(frames, intrinsics)
        size = tuple(frames.shape[1:3])
        maps = np.stack([self.load(k, files[k], size) for k in indices])
        kind = "metric" if self.kind == "depth" else "affine_disparity"
        return PriorOutput(depth=maps, kind=kind, info={"model": "folder", "folder": str(self.folder),
                                                        "stored": self.kind})

    def finalize(self, output: PriorOutput) -> PriorOutput:
        """The NaN/inf counts of every batch of the call go into ``info``."""
        counts = dict(self.nonfinite)
        return replace(output, info={**output.info, "nonfinite_pixels": sum(counts.values()),
                                     "nonfinite_files": counts})
