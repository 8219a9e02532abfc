"""Exports of a finished output folder for other tools: a COLMAP text model, a nerfstudio dataset.

This module owns ``recon export OUT --to colmap|nerfstudio`` (and ``recon run --export``):
which exports are written where (``OUT/colmap/``, ``OUT/nerfstudio/``, one per segment
folder), their options, the images they share (decoded once for all formats) and writing
each one atomically: into a hidden folder beside its destination, renamed into place when
complete; an existing export is replaced only with ``overwrite``. The formats are in
:mod:`recon.export.colmap_export` and :mod:`recon.export.nerfstudio_export`, reading the
folder back in :mod:`recon.export.run_folder`.
More: docs/export.md#what-is-written
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from recon.errors import ReconInputError

from .colmap_export import write_colmap_model
from .nerfstudio_export import write_nerfstudio_dataset
from .run_folder import (
    DEFAULT_MAX_POINTS,
    decoded_frames,
    mesh_points,
    read_run,
    read_run_report,
    run_input,
    segment_folders,
)

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("colmap", "nerfstudio")
IMAGE_FORMATS = ("jpg", "png")
JPEG_QUALITY = 95
IMAGES_DIR = "images"


@dataclass(frozen=True)
class ExportOptions:
    """max_points: most points in points3D.txt / points.ply (a uniform random subset of the
    mesh's vertices, seed run_folder.POINTS_SEED, when it has more; 0: none); image_format: "jpg"
    (quality JPEG_QUALITY) or "png"; overwrite: replace an existing export; input: where the
    run's input is now (default: report.json's input.path); progress: a progress bar."""

    max_points: int = DEFAULT_MAX_POINTS
    image_format: str = "jpg"
    overwrite: bool = False
    input: Path | None = None
    progress: bool = True

    def validate(self) -> None:
        if int(self.max_points) != self.max_points or self.max_points < 0:
            raise ReconInputError(f"max points must be a whole number >= 0, got {self.max_points}")
        if self.image_format not in IMAGE_FORMATS:
            raise ReconInputError(f"image format must be one of {', '.join(IMAGE_FORMATS)}, got "
                                  f"{self.image_format!r}")


@dataclass(frozen=True)
class ExportResult:
    """One export written: its format, folder, and how many images, depth maps and points."""

    format: str
    path: Path
    images: int
    points: int
    depth_maps: int = 0

    def __str__(self) -> str:
        depth = f", {self.depth_maps} depth maps" if self.format == "nerfstudio" else ""
        return f"{self.format}: {self.path} ({self.images} images{depth}, {self.points} points)"


def parse_formats(values: str | Iterable[str]) -> tuple[str, ...]:
    """The export formats of ``--to``/``--export`` values ("colmap", "colmap,nerfstudio", or a
    list of those), in order, each once; one-line ReconInputError for an unknown one."""
    values = [values] if isinstance(values, str) else list(values)
    formats: list[str] = []
    for value in values:
        for name in str(value).split(","):
            name = name.strip().lower()
            if not name:
                continue
            if name not in EXPORT_FORMATS:
                raise ReconInputError(f"unknown export format {name!r} (expected {', '.join(EXPORT_FORMATS)})")
            if name not in formats:
                formats.append(name)
    if not formats:
        raise ReconInputError(f"no export format given (expected {', '.join(EXPORT_FORMATS)})")
    return tuple(formats)


# --------------------------------------------------------------------------- writing


def _encoded(rgb: np.ndarray, image_format: str) -> bytes:
    """An RGB frame (H, W, 3) uint8 as a JPEG (quality JPEG_QUALITY) or a PNG file's bytes."""
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if image_format == "jpg" else []
    ok, buf = cv2.imencode(f".{image_format}", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise OSError(f"OpenCV could not encode a {image_format} image")
    return buf.tobytes()


def _check_free(dest: Path, overwrite: bool) -> None:
    """ReconInputError when `dest` holds something and `overwrite` is off."""
    if dest.exists() and not overwrite and not (dest.is_dir() and not any(dest.iterdir())):
        raise ReconInputError(f"{dest}: already exists (--overwrite replaces it)")


@contextmanager
def staged_folder(dest, overwrite: bool = False) -> Iterator[Path]:
    """A hidden temporary folder beside `dest`, renamed to `dest` when the block succeeds (an
    existing `dest` is only replaced with `overwrite`, once the new folder is complete); the
    temporary folder is removed whatever happens."""
    dest = Path(dest)
    _check_free(dest, overwrite)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp = dest.with_name(f".{dest.name}.tmp-{tag}")
    tmp.mkdir()
    try:
        yield tmp
        _check_free(dest, overwrite)
        if dest.exists() and not (dest.is_dir() and not any(dest.iterdir())):
            old = dest.with_name(f".{dest.name}.old-{tag}")
            os.replace(dest, old)
            os.replace(tmp, dest)
            if old.is_dir():
                shutil.rmtree(old)
            else:
                old.unlink()
        else:
            os.replace(tmp, dest)  # an empty folder is replaced by the rename itself
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _export(folder: Path, dests: dict[str, Path], options: ExportOptions) -> list[ExportResult]:
    """Every format of `dests` (format -> destination folder) of one output folder, the frames
    decoded once for all of them."""
    run = read_run(folder)
    for dest in dests.values():
        _check_free(dest, options.overwrite)
    input_path = run_input(run, options.input)
    xyz, rgb = mesh_points(folder, options.max_points)
    xyz = run.to_world(xyz)
    if not len(xyz):
        log.warning("%s: no mesh.ply or point_cloud.ply with points: the exports have no 3D points", folder)
    images = [f"{run.stem(k)}.{options.image_format}" for k in range(len(run.indices))]
    with ExitStack() as stack:
        staged = {fmt: stack.enter_context(staged_folder(dest, options.overwrite)) for fmt, dest in dests.items()}
        for tmp in staged.values():
            (tmp / IMAGES_DIR).mkdir()
        for row, frame in decoded_frames(run, input_path, options.progress):
            data = _encoded(frame, options.image_format)
            for tmp in staged.values():
                (tmp / IMAGES_DIR / images[row]).write_bytes(data)
        results = []
        for fmt, tmp in staged.items():
            depth_maps = 0
            if fmt == "colmap":
                write_colmap_model(tmp, run, images, xyz, rgb)
            else:
                depth_maps = write_nerfstudio_dataset(tmp, run, [f"{IMAGES_DIR}/{name}" for name in images], xyz, rgb)
            results.append(ExportResult(fmt, dests[fmt], len(images), len(xyz), depth_maps))
    return results


def export_folder(folder, formats: str | Iterable[str] = EXPORT_FORMATS, dest=None,
                  options: ExportOptions | None = None) -> list[ExportResult]:
    """Export output folder `folder` in each of `formats` into ``DEST/<format>/`` (DEST:
    `dest`, default the output folder itself). A run written as segments is exported segment
    by segment, into ``DEST/segment_NN/<format>/``. Every destination is checked before any
    work: one that exists is refused unless ``options.overwrite``."""
    folder, options = Path(folder), options or ExportOptions()
    formats = parse_formats(formats)
    options.validate()
    root = folder if dest is None else Path(dest)
    segments = segment_folders(folder, read_run_report(folder))
    jobs = ([(folder / name, {fmt: root / name / fmt for fmt in formats}) for name in segments] if segments
            else [(folder, {fmt: root / fmt for fmt in formats})])
    for _, dests in jobs:
        for path in dests.values():
            _check_free(path, options.overwrite)
    return [result for part, dests in jobs for result in _export(part, dests, options)]


def _export_one(fmt: str, folder, dest, options: ExportOptions | None) -> ExportResult:
    """Format `fmt` of output folder `folder` (not one written as segments) in `dest`
    (default OUT/<fmt>/)."""
    folder, options = Path(folder), options or ExportOptions()
    options.validate()
    return _export(folder, {fmt: Path(dest) if dest is not None else folder / fmt}, options)[0]


def export_colmap(folder, dest=None, options: ExportOptions | None = None) -> ExportResult:
    """A COLMAP text model of output folder `folder` in `dest` (default OUT/colmap/): images/
    and sparse/0/ (:mod:`recon.export.colmap_export`)."""
    return _export_one("colmap", folder, dest, options)


def export_nerfstudio(folder, dest=None, options: ExportOptions | None = None) -> ExportResult:
    """A nerfstudio dataset of output folder `folder` in `dest` (default OUT/nerfstudio/):
    transforms.json, images/, depth/, points.ply (:mod:`recon.export.nerfstudio_export`)."""
    return _export_one("nerfstudio", folder, dest, options)


__all__ = [
    "DEFAULT_MAX_POINTS",
    "EXPORT_FORMATS",
    "ExportOptions",
    "ExportResult",
    "export_colmap",
    "export_folder",
    "export_nerfstudio",
    "parse_formats",
    "staged_folder",
]
