"""Per-frame arrays parked on disk by the streamed pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from recon.io.frame_store import FrameStore


def test_arrays_come_back_exactly_and_the_folder_goes(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 255, (4, 6, 8, 3), dtype=np.uint8)
    depth = np.random.default_rng(1).random((4, 6, 8), dtype=np.float32)
    with FrameStore(tmp_path) as store:
        for k in range(4):
            store.put(k, rgb=rgb[k], prior=depth[k] if k % 2 == 0 else None)
        assert np.array_equal(store.stack([0, 1, 2, 3], "rgb"), rgb)
        assert np.array_equal(store.get(2, "prior"), depth[2]) and store.get(2, "prior").dtype == np.float32
        assert store.has(0, "prior") and not store.has(1, "prior")
        with pytest.raises(KeyError, match="prior kept for frame 1"):
            store.get(1, "prior")
        folder = store.folder
        assert folder.parent == tmp_path and store.bytes_written == rgb.nbytes + 2 * depth[0].nbytes
    assert not folder.exists()
