"""recon.core.sequence: the per-frame bundle stays in step through take and undistort."""

import numpy as np
import pytest

from recon.core.sequence import Sequence

N, H, W = 5, 24, 32
K = (30.0, 30.0, (W - 1) / 2, (H - 1) / 2)


def _sequence(with_everything=True):
    rng = np.random.default_rng(0)
    extra = {}
    if with_everything:
        poses = np.repeat(np.eye(4)[None], N, 0)
        poses[:, 0, 3] = np.arange(N)
        extra = dict(prior_depth=rng.uniform(1, 3, (N, H, W)).astype(np.float32),
                     features=rng.normal(size=(N, 4, H // 4, W // 4)).astype(np.float32), poses=poses)
    return Sequence(np.arange(N) * 3, np.arange(N) / 10.0, rng.integers(0, 255, (N, H, W, 3), dtype=np.uint8),
                    [f"f{i}" for i in range(N)], K, **extra)


def test_take_keeps_every_per_frame_field_in_step():
    seq = _sequence()
    for keep in ([1, 3, 4], np.array([False, True, False, True, True])):
        part = seq.take(keep)
        assert part.indices.tolist() == [3, 9, 12]
        assert part.names == ["f1", "f3", "f4"]
        assert np.array_equal(part.rgb, seq.rgb[[1, 3, 4]])
        assert np.array_equal(part.prior_depth, seq.prior_depth[[1, 3, 4]])
        assert np.array_equal(part.features, seq.features[[1, 3, 4]])
        assert part.poses[:, 0, 3].tolist() == [1, 3, 4]
        assert part.timestamps.tolist() == pytest.approx([0.1, 0.3, 0.4])
        assert part.intrinsics == K


def test_take_leaves_missing_fields_missing():
    part = _sequence(with_everything=False).take([0, 2])
    assert part.prior_depth is None and part.features is None and part.poses is None
    assert len(part) == 2 and part.size == (H, W)


def test_a_field_of_the_wrong_length_is_refused():
    seq = _sequence()
    with pytest.raises(ValueError, match="5 frames got 4 prior_depth"):
        seq.with_(prior_depth=seq.prior_depth[:4])


def test_undistort_resamples_frames_depth_and_features_together():
    seq = _sequence()
    out = seq.undistort(-0.2)
    assert out.rgb.shape == seq.rgb.shape and out.features.shape == seq.features.shape
    assert not np.array_equal(out.rgb, seq.rgb)
    # Depth is resampled without interpolation: every value is one of the frame's own (or 0 outside).
    for k in range(N):
        assert np.isin(out.prior_depth[k][out.prior_depth[k] > 0], seq.prior_depth[k]).all()
    # Pixels next to the principal point hardly move under radial distortion: same depth.
    cy, cx = H // 2, W // 2
    assert np.array_equal(out.prior_depth[:, cy, cx], seq.prior_depth[:, cy, cx])
    assert np.array_equal(out.poses, seq.poses) and out.names == seq.names


def test_undistort_needs_the_intrinsics():
    seq = _sequence().with_(intrinsics=None)
    with pytest.raises(ValueError, match="intrinsics"):
        seq.undistort(0.1)
