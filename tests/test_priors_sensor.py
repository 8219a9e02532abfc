"""Sensor depth as a prior (recon.priors.sensor): holes stay holes, one-line errors naming the
frame and file, and the depth of a real RGB-D recording (needs ../shared)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.priors import SensorDepthPrior, make_prior

from helpers import PRIOR_H as H
from helpers import PRIOR_W as W
from helpers import prior_depth, prior_error, prior_frames


def test_sensor_prior_keeps_holes():
    raw = np.round(prior_depth(2) * 1000).astype(np.uint16)
    raw[0, 10, 10] = 65535
    out = SensorDepthPrior(raw, depth_scale=0.001, invalid_values=(65535,))(prior_frames(2))
    assert out.kind == "metric"
    assert (out.depth[:, :3, :4] == 0).all() and out.depth[0, 10, 10] == 0
    np.testing.assert_allclose(out.depth[1, 5:, 5:], prior_depth(2)[1, 5:, 5:], atol=1e-6)
    metres = prior_depth(1)
    metres[0, 7, 7] = np.nan
    metres[0, 8, 8] = -1
    out = make_prior("sensor", depth=metres)(prior_frames(1, 2 * H, 2 * W))
    assert out.depth.shape == (1, 2 * H, 2 * W)
    assert out.depth[0, 14, 14] == 0 and out.depth[0, 16, 16] == 0 and np.isfinite(out.depth).all()
    with pytest.raises(ReconInputError, match="1 depth maps for 2 frames"):
        SensorDepthPrior(metres)(prior_frames(2))


def test_sensor_prior_names_empty_frame_and_file():
    depth = prior_depth(3)
    depth[2] = np.nan
    files = [f"depth/{k:03d}.png" for k in range(3)]
    prior_error(SensorDepthPrior(depth, files=files, batch_size=2), prior_frames(3), "frame 2", "depth/002.png",
                    "no valid pixel")
    prior_error(SensorDepthPrior(depth, source="rec/"), prior_frames(3), "rec/", "frame 2")
    # A map of another aspect cannot be this frame's depth.
    prior_error(SensorDepthPrior(depth[:, :, :20], source="rec/"), prior_frames(3), "rec/", "aspect")


def test_sensor_prior_from_dataset(shared_dir):
    from recon.io.datasets import open_dataset
    from recon.io.datasets.base import register_depth

    dataset = open_dataset(shared_dir / "data" / "7scenes-redkitchen").select(stride=200)
    out = SensorDepthPrior.from_dataset(dataset)(dataset.load_rgb_batch())
    raw = cv2.imread(str(dataset.depth_paths[1]), cv2.IMREAD_UNCHANGED)
    # 7-Scenes depth is re-registered into the colour camera by the reader: compare with that.
    raw = register_depth(raw, dataset.depth_intrinsics, dataset.intrinsics)
    holes = (raw == 0) | (raw == 65535)
    assert out.kind == "metric" and out.depth.shape == (2, 480, 640) and holes.any()
    assert (out.depth[1][holes] == 0).all()
    np.testing.assert_allclose(out.depth[1][~holes], raw[~holes] / 1000.0, rtol=1e-6)
