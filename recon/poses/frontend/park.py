"""Where the front end parks per-frame arrays it needs again only at ``finish``: tracking's
flow to each frame's keyframe, pooled to the BA grid, which the filler would otherwise make
again (``filler.align_to_keyframes``'s known frames).

A park has :class:`~recon.io.frame_store.FrameStore`'s interface (``put``, ``has``, ``get``
by frame position and kind), so that the streamed pipeline parks on disk with the frames it
already keeps there; :class:`MemoryPark` keeps them in memory (a one-shot run, which holds
every frame anyway); :class:`ShiftedPark` numbers a piece's frames from its first
(``pieces``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class FramePark(Protocol):
    """Arrays by (frame position, kind)."""

    def put(self, position: int, **arrays: np.ndarray | None) -> None: ...

    def has(self, position: int, kind: str) -> bool: ...

    def get(self, position: int, kind: str) -> np.ndarray: ...


class MemoryPark:
    """A FramePark in a dict (each array copied in)."""

    def __init__(self):
        self._arrays: dict[tuple[int, str], np.ndarray] = {}

    def put(self, position: int, **arrays: np.ndarray | None) -> None:
        for kind, array in arrays.items():
            if array is not None:
                self._arrays[int(position), kind] = np.array(array)

    def has(self, position: int, kind: str) -> bool:
        return (int(position), kind) in self._arrays

    def get(self, position: int, kind: str) -> np.ndarray:
        return self._arrays[int(position), kind]


class ShiftedPark:
    """The FramePark ``park`` with position 0 at its position ``first``."""

    def __init__(self, park: FramePark, first: int):
        self.park, self.first = park, int(first)

    def put(self, position: int, **arrays: np.ndarray | None) -> None:
        self.park.put(self.first + int(position), **arrays)

    def has(self, position: int, kind: str) -> bool:
        return self.park.has(self.first + int(position), kind)

    def get(self, position: int, kind: str) -> np.ndarray:
        return self.park.get(self.first + int(position), kind)


__all__ = ["FramePark", "MemoryPark", "ShiftedPark"]
