"""The FastDepth prior (recon.priors.fastdepth): the authors' reference output matched, encoder
features from the same pass, any frame size, the network size from the training focal,
a real frame, and disparity aligned to FastDepth.

Needs ../shared/weights/fastdepth (conftest: fastdepth_weights; skipped cleanly when absent).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from recon.priors import FastDepthPrior, load_fastdepth, make_prior
from recon.priors.fastdepth import TRAIN_FOCAL_AT_INPUT, feature_tensor, kept_channels, network_size

from helpers import FASTDEPTH_WEIGHTS


@pytest.fixture(scope="module")
def reference(fastdepth_weights):
    rgb = np.load(fastdepth_weights / "reference" / "rgb.npy")
    pred = np.load(fastdepth_weights / "reference" / "pred.npy")
    gt = np.load(fastdepth_weights / "reference" / "depth.npy")
    # Layout facts the comparison relies on: HWC float64 RGB in [0, 1] (exact 8-bit
    # levels), prediction NCHW (1, 1, 224, 224), ground truth HW with no holes.
    assert rgb.shape == (224, 224, 3) and rgb.dtype == np.float64
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0 and np.allclose(rgb * 255, np.round(rgb * 255))
    assert pred.shape == (1, 1, 224, 224) and gt.shape == (224, 224)
    return rgb, pred[0, 0], gt


def test_matches_authors_output(reference):
    rgb, pred, gt = reference
    net, _ = load_fastdepth()
    with torch.inference_mode():
        ours, _ = net(torch.from_numpy(rgb).float().permute(2, 0, 1)[None])
    ours = ours[0, 0].numpy()
    rel = np.abs(ours - pred) / pred
    assert np.median(rel) < 1e-3
    assert np.percentile(rel, 95) < 5e-3
    assert np.corrcoef(ours.ravel(), pred.ravel())[0, 1] > 0.9999
    # Ground truth is dense here (no zeros), so every pixel is scored, as in the authors' eval.
    valid = gt > 0
    abs_rel = np.mean(np.abs(ours - gt)[valid] / gt[valid])
    assert abs(abs_rel - 0.1405) < 0.003


def test_prior_on_uint8_reference_matches(reference):
    rgb, pred, _ = reference
    prior = FastDepthPrior(resize="224x224", progress=False)
    out = prior((rgb * 255).round().astype(np.uint8))
    assert out.kind == "metric" and out.depth.shape == (1, 224, 224) and out.depth.dtype == np.float32
    assert np.median(np.abs(out.depth[0] - pred) / pred) < 1e-3


def test_features_from_same_pass(reference):
    rgb = (reference[0] * 255).round().astype(np.uint8)
    frame = np.repeat(np.repeat(rgb, 2, axis=0), 2, axis=1)[None]  # 448x448 frame
    intrinsics = [TRAIN_FOCAL_AT_INPUT[0] * 2, TRAIN_FOCAL_AT_INPUT[1] * 2, 224, 224]
    plain = FastDepthPrior(progress=False)(frame, intrinsics)
    for layer, channels, stride in (("stride8", 256, 8), ("stride4", 120, 4)):
        prior = FastDepthPrior(features=True, feature_layer=layer, progress=False)
        out = prior(frame, intrinsics)
        kept = kept_channels(prior.base_net, prior.tap)
        assert out.info["network_input"] == (224, 224)
        assert out.features.shape == (1, len(kept), 224 // stride, 224 // stride)
        assert 0 < channels - len(kept) < channels // 3  # pruned channels dropped, most kept
        assert out.feature_stride == (448 / (224 // stride), 448 / (224 // stride))
        np.testing.assert_array_equal(out.depth, plain.depth)
    # Dropped channels are constant on real input too (they are proven constant for all inputs).
    net, _ = load_fastdepth()
    tap = feature_tensor(net, "stride8")
    with torch.inference_mode():
        _, maps = net(torch.from_numpy(reference[0]).float().permute(2, 0, 1)[None], (tap,))
    dropped = np.setdiff1d(np.arange(256), kept_channels(net, tap))
    assert torch.all(maps[tap][0, dropped] == maps[tap][0, dropped].flatten(1)[:, :1, None])


def test_full_frame_any_size_and_layouts():
    if not (FASTDEPTH_WEIGHTS / "model.json").is_file():
        pytest.skip("no FastDepth weights")
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (3, 90, 120, 3), dtype=np.uint8)
    a = FastDepthPrior(resize="64x96", channels_last=True, batch_size=2, progress=False)(frames)
    b = FastDepthPrior(resize="64x96", channels_last=False, batch_size=3, progress=False)(frames)
    assert a.depth.shape == (3, 90, 120)
    np.testing.assert_allclose(a.depth, b.depth, rtol=1e-4, atol=1e-5)
    net, _ = load_fastdepth()
    with pytest.raises(ValueError, match="multiple of 32"):
        net(torch.zeros(1, 3, 100, 96))


def test_network_size_matches_training_focal():
    # 7-Scenes (fx = 585) and TUM fr1 (fx = 525) at 640x480.
    assert network_size(480, 640, np.array([585.0, 585, 320, 240]), "focal") == (224, 224)
    assert network_size(480, 640, np.array([525.0, 525, 319.5, 239.5]), "focal") == (256, 256)
    assert network_size(480, 640, np.array([585.0, 585, 320, 240]), "256x320") == (256, 320)
    with pytest.raises(ValueError):
        network_size(480, 640, np.array([585.0, 585, 320, 240]), "250x320")


def test_real_frame_is_dense_and_plausible(shared_dir):
    import cv2

    root = shared_dir / "data" / "7scenes-redkitchen"
    rgb = cv2.imread(str(root / "frame-000000.color.jpg"))[:, :, ::-1][None]
    raw = cv2.imread(str(root / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    gt = np.where((raw == 0) | (raw == 65535), 0, raw / 1000.0)
    out = make_prior("fastdepth", progress=False)(rgb, [585.0, 585.0, 320.0, 240.0])
    assert out.depth.shape == (1, 480, 640)
    assert (out.depth > 0).mean() > 0.99
    valid = gt > 0
    assert np.mean(np.abs(out.depth[0] - gt)[valid] / gt[valid]) < 0.4


def test_disparity_folder_aligned_to_fastdepth(reference, tmp_path):
    """align_to="fastdepth": relative disparity gets FastDepth's metric scale, and says so."""
    frame = (reference[0] * 255).round().astype(np.uint8)[None]
    metric = FastDepthPrior(progress=False)(frame).depth
    np.save(tmp_path / "0.npy", np.where(metric > 0, 3.0 / np.maximum(metric, 1e-6) + 0.5, 0.0)[0])
    out = make_prior("folder", path=tmp_path, kind="disparity", align_to="fastdepth", progress=False)(frame)
    assert out.kind == "metric" and out.info["aligned_to"] == "prior:fastdepth"
    np.testing.assert_allclose(out.depth, metric, rtol=1e-3)
