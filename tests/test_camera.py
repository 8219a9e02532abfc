"""Camera intrinsics (recon.camera) under resizing: pixel centres stay where they were."""

from __future__ import annotations

import pytest

from recon.camera import resize_intrinsics, scale_intrinsics


def test_scale_intrinsics_pixel_centres():
    # The centre of a 640x480 image stays the centre of the 320x240 one.
    assert scale_intrinsics((500.0, 500.0, 319.5, 239.5), 0.5) == pytest.approx((250.0, 250.0, 159.5, 119.5))
    resized = resize_intrinsics((100.0, 90.0, 10.0, 20.0), (48, 64), (96, 128))
    assert resized == pytest.approx((200.0, 180.0, 20.5, 40.5))
