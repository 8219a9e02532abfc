"""RGB-D dataset readers: one record type (:class:`RGBDDataset`) for several public layouts.

Owns layout detection (:func:`detect_kind`, :func:`detect_dataset`) and the single entry
point :func:`open_dataset`. Each layout has its own module (``tum``, ``sevenscenes``,
``scannet``, ``arkitscenes``, ``record3d``, ``kitti``, ``colmap_project`` of kind ``colmap``,
``redwood``). All readers return camera-to-world poses with OpenCV camera axes, depth in
metres (0 = invalid) and intrinsics in pixels of the images ``rgb(i)`` returns; KITTI and
COLMAP projects have no depth.
More: docs/input.md#dataset-layouts-in-detail
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from recon.errors import ReconInputError

from .arkitscenes import is_arkitscenes, open_arkitscenes
from .base import RGBDDataset
from .colmap_project import is_colmap, open_colmap
from .kitti import is_kitti, open_kitti
from .record3d import is_record3d, open_record3d
from .redwood import is_redwood, open_redwood
from .scannet import is_scannet, open_scannet
from .sevenscenes import is_7scenes, open_7scenes
from .tum import is_tum, open_tum

# Order matters: ScanNet's color/ + depth/ and Record3D's rgb/ + depth/ would also pass the
# generic Redwood test, so Redwood comes last.
READERS: dict[str, tuple[Callable[[Path], bool], Callable[..., RGBDDataset]]] = {
    "7scenes": (is_7scenes, open_7scenes),
    "scannet": (is_scannet, open_scannet),
    "arkitscenes": (is_arkitscenes, open_arkitscenes),
    "tum": (is_tum, open_tum),
    "record3d": (is_record3d, open_record3d),
    "kitti": (is_kitti, open_kitti),
    "colmap": (is_colmap, open_colmap),
    "redwood": (is_redwood, open_redwood),
}
KINDS = tuple(READERS)


def detect_kind(path) -> str | None:
    """Layout name of the dataset folder `path` (one of KINDS), or None when unrecognised."""
    path = Path(path)
    if not path.is_dir():
        return None
    return next((kind for kind, (test, _) in READERS.items() if test(path)), None)


def detect_dataset(path) -> RGBDDataset | None:
    """The dataset at `path` when its layout is recognised, else None.

    A recognised layout with broken content still raises ReconInputError: a wrong file is
    worth reporting, not silently treating the folder as something else.
    """
    kind = detect_kind(path)
    return None if kind is None else READERS[kind][1](Path(path))


def open_dataset(path, kind: str | None = None, **options) -> RGBDDataset:
    """Open the RGB-D dataset at `path`; `kind` (one of KINDS) skips auto-detection.

    `options` go to the layout's reader (e.g. ``max_diff`` for TUM, ``intrinsics_from``
    for ScanNet).
    """
    path = Path(path)
    if not path.exists():
        raise ReconInputError(f"{path}: no such folder")
    if not path.is_dir():
        raise ReconInputError(f"{path}: expected a dataset folder, got a file")
    if kind is None:
        kind = detect_kind(path)
        if kind is None:
            raise ReconInputError(
                f"{path}: not a recognised RGB-D dataset layout (expected one of: {', '.join(KINDS)})"
            )
    if kind not in READERS:
        raise ValueError(f"unknown dataset kind {kind!r}; expected one of {KINDS}")
    return READERS[kind][1](path, **options)


__all__ = [
    "KINDS",
    "RGBDDataset",
    "detect_dataset",
    "detect_kind",
    "open_7scenes",
    "open_arkitscenes",
    "open_colmap",
    "open_dataset",
    "open_kitti",
    "open_record3d",
    "open_redwood",
    "open_scannet",
    "open_tum",
]
