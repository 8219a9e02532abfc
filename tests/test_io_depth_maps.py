"""Reading one depth map file (recon.io.depth_maps): 16-bit PNG scale and invalid markers, and
EXR (or a one-line error saying what to do when OpenCV has no EXR codec)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.io.depth_maps import read_depth_file

from helpers import PRIOR_H as H
from helpers import PRIOR_W as W
from helpers import prior_depth


def test_png_depth_scale_and_invalid_marker(tmp_path):
    raw = np.full((H, W), 5000, np.uint16)
    raw[0, 0], raw[0, 1] = 0, 65535
    cv2.imwrite(str(tmp_path / "a.png"), raw)
    tum = read_depth_file(tmp_path / "a.png", depth_scale=1 / 5000)
    assert tum[5, 5] == pytest.approx(1.0) and tum[0, 0] == 0 and tum[0, 1] == 0
    assert read_depth_file(tmp_path / "a.png")[5, 5] == pytest.approx(5.0)  # millimetres by default


def test_exr(tmp_path):
    path = tmp_path / "frame0.exr"
    try:
        written = cv2.imwrite(str(path), prior_depth(1)[0])
    except cv2.error:
        written = False
    if written:
        np.testing.assert_allclose(read_depth_file(path), prior_depth(1)[0], atol=1e-6)
    else:
        # No EXR codec in this OpenCV build: the user gets one line saying what to do.
        path.write_bytes(b"v/1\x01not really exr")
        with pytest.raises(ReconInputError) as info:
            read_depth_file(path)
        assert "\n" not in str(info.value) and "EXR" in str(info.value)
