"""Per-frame arrays parked on disk while a long video streams through the pipeline.

The streamed pipeline (:mod:`recon.drivers.streamed`) tracks every frame first and works on depth
window by window afterwards; what it needs again later (the frame at working size, the
prior's depth and features of the frames that get depth) waits here, one ``.npy`` file per
frame and kind, so that memory does not grow with the length of the video. Files are read
back with ordinary reads (not memory maps, whose pages would count as resident memory).
The folder is a temporary one, removed by ``close`` (or leaving the ``with`` block).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np


class FrameStore:
    """Arrays by (frame position, kind) in a temporary folder (under ``parent`` if given)."""

    def __init__(self, parent: Path | None = None):
        self.folder = Path(tempfile.mkdtemp(prefix="recon-frames-", dir=parent))
        self.bytes_written = 0

    def _path(self, position: int, kind: str) -> Path:
        return self.folder / f"{int(position):07d}.{kind}.npy"

    def put(self, position: int, **arrays: np.ndarray | None) -> None:
        """Keep each given array (None skipped) of the frame at ``position``."""
        for kind, array in arrays.items():
            if array is None:
                continue
            array = np.ascontiguousarray(array)
            np.save(self._path(position, kind), array, allow_pickle=False)
            self.bytes_written += array.nbytes

    def has(self, position: int, kind: str) -> bool:
        return self._path(position, kind).is_file()

    def get(self, position: int, kind: str) -> np.ndarray:
        """The array kept for (position, kind); KeyError when there is none."""
        path = self._path(position, kind)
        if not path.is_file():
            raise KeyError(f"no {kind} kept for frame {position}")
        return np.load(path, allow_pickle=False)

    def stack(self, positions, kind: str) -> np.ndarray:
        """(len(positions), ...) of one kind."""
        return np.stack([self.get(p, kind) for p in positions])

    def close(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)

    def __enter__(self) -> FrameStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["FrameStore"]
