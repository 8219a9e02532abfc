"""Where the front end parks per-frame arrays for finish (recon.poses.frontend.park)."""

from __future__ import annotations

import numpy as np

from recon.io.frame_store import FrameStore
from recon.poses.frontend.park import MemoryPark, ShiftedPark


def test_a_memory_park_keeps_copies_and_a_shifted_park_numbers_from_its_first_frame(tmp_path):
    """MemoryPark keeps a copy (the caller's buffer may change); ShiftedPark's frame 0 is
    its park's frame `first`, on a MemoryPark as on a FrameStore."""
    memory = MemoryPark()
    weight = np.ones((3, 4))
    memory.put(5, edge_weight=weight, nothing=None)
    weight[:] = 0
    assert memory.has(5, "edge_weight") and not memory.has(5, "nothing") and memory.get(5, "edge_weight").min() == 1
    with FrameStore(tmp_path) as store:
        for park in (memory, store):
            piece = ShiftedPark(park, 40)
            piece.put(2, edge_keyframe=np.array([7]))
            assert park.has(42, "edge_keyframe") and not park.has(2, "edge_keyframe")
            assert piece.has(2, "edge_keyframe") and int(piece.get(2, "edge_keyframe")[0]) == 7
