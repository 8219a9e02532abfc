"""Camera intrinsics (recon.geometry.camera) under resizing: pixel centres stay where they were; the
lens model that resamples recorded frames into the pinhole camera."""

from __future__ import annotations

import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.geometry.camera import resize_intrinsics, scale_intrinsics


def test_scale_intrinsics_pixel_centres():
    # The centre of a 640x480 image stays the centre of the 320x240 one.
    assert scale_intrinsics((500.0, 500.0, 319.5, 239.5), 0.5) == pytest.approx((250.0, 250.0, 159.5, 119.5))
    resized = resize_intrinsics((100.0, 90.0, 10.0, 20.0), (48, 64), (96, 128))
    assert resized == pytest.approx((200.0, 180.0, 20.5, 40.5))


def test_undistortion_maps_are_opencvs_undistortion():
    """Resampling with undistortion_maps is cv2.undistort with the same camera matrix, and the
    largest shift is where the lens moves the corners."""
    import cv2

    from recon.geometry.camera import check_distortion, largest_lens_shift, undistortion_maps

    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (60, 80)).astype(np.float32), (0, 0), 2.0)
    intrinsics, coefficients = (70.0, 72.0, 40.2, 29.7), check_distortion([0.26, -0.95, -0.005, 0.003, 1.16])
    maps = undistortion_maps(intrinsics, coefficients, image.shape)
    K = np.array([[70.0, 0, 40.2], [0, 72.0, 29.7], [0, 0, 1]])
    expected = cv2.undistort(image, K, np.asarray(coefficients))
    got = cv2.remap(image, *maps, cv2.INTER_LINEAR)
    np.testing.assert_allclose(got[5:-5, 5:-5], expected[5:-5, 5:-5], atol=0.5)
    assert 1.0 < largest_lens_shift(maps) < 20.0
    assert largest_lens_shift(undistortion_maps(intrinsics, (0.0, 0.0, 0.0, 0.0), image.shape)) < 1e-3


def test_distortion_coefficients_are_checked():
    from recon.geometry.camera import check_distortion, is_pinhole

    assert check_distortion(["0.1", 0, 0, 0]) == (0.1, 0.0, 0.0, 0.0)
    for bad in ([0.1, 0.0], [0.1] * 6, [float("nan"), 0, 0, 0]):
        with pytest.raises(ReconInputError):
            check_distortion(bad)
    assert is_pinhole(None) and is_pinhole((0, 0, 0, 0)) and not is_pinhole((0, 0, 0.001, 0))
