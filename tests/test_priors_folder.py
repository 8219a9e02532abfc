"""User depth maps from a folder as a prior (recon.priors.folder): every file type, matching
files to frames by stem or natural order, resizing that keeps holes, one-line errors, and
disparity aligned to a metric reference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.priors import FolderDepthPrior, make_prior

from helpers import PRIOR_H as H
from helpers import PRIOR_W as W
from helpers import prior_depth, prior_error, prior_frames


def _write(path, depth: np.ndarray) -> None:
    suffix = path.suffix
    if suffix == ".npy":
        np.save(path, depth)
    elif suffix == ".npz":
        np.savez_compressed(path, depth=depth)
    elif suffix == ".png":
        assert cv2.imwrite(str(path), np.round(depth * 1000).astype(np.uint16))
    else:  # .pfm / .tiff / .exr: float32
        assert cv2.imwrite(str(path), depth.astype(np.float32))


@pytest.mark.parametrize("suffix", [".npy", ".npz", ".png", ".pfm", ".tiff"])
def test_folder_round_trip(tmp_path, suffix):
    depth = prior_depth(3)
    for k, d in enumerate(depth):
        _write(tmp_path / f"frame{k}{suffix}", d)
    out = make_prior("folder", path=tmp_path, progress=False, batch_size=2)(prior_frames(3))
    assert out.kind == "metric" and out.depth.dtype == np.float32
    np.testing.assert_allclose(out.depth, depth, atol=1e-6)


def test_natural_order_and_stem_matching(tmp_path):
    depth = prior_depth(11)
    for k, d in enumerate(depth):
        np.save(tmp_path / f"f{k}.npy", d)  # natural order: f2 before f10
    out = FolderDepthPrior(tmp_path, progress=False)(prior_frames(11))
    np.testing.assert_array_equal(out.depth, depth)
    # Matching by stem ignores role words and order.
    names = [f"f{k}.color.jpg" for k in (3, 10, 0)]
    out = FolderDepthPrior(tmp_path, frame_names=names, progress=False)(prior_frames(3))
    np.testing.assert_array_equal(out.depth, depth[[3, 10, 0]])


def test_stem_matching_with_role_suffix(tmp_path):
    depth = prior_depth(2)
    for k, d in enumerate(depth):
        np.save(tmp_path / f"frame-{k:06d}.depth.npy", d)
    names = [f"frame-{k:06d}.color.jpg" for k in range(2)]
    out = FolderDepthPrior(tmp_path, frame_names=names, progress=False)(prior_frames(2))
    np.testing.assert_array_equal(out.depth, depth)


def test_resize_keeps_holes(tmp_path):
    depth = np.ones((H // 2, W // 2), np.float32)
    depth[:2, :2] = 0
    np.save(tmp_path / "a.npy", depth)
    out = FolderDepthPrior(tmp_path, progress=False)(prior_frames(1))
    assert out.depth.shape == (1, H, W)
    assert (out.depth[0, :4, :4] == 0).all() and set(np.unique(out.depth)) == {0.0, 1.0}


def test_folder_errors(tmp_path):
    depth = prior_depth(2)
    np.save(tmp_path / "f0.npy", depth[0])
    np.save(tmp_path / "f1.npy", depth[1])
    # Frame without a file (by stem), and count mismatch (by order).
    prior_error(FolderDepthPrior(tmp_path, frame_names=["f0.png", "f7.png"], progress=False), prior_frames(2),
                    "no depth file for f7.png", "f7.npy", tmp_path)
    prior_error(FolderDepthPrior(tmp_path, progress=False), prior_frames(3), "2 depth files for 3 frames")
    # Wrong size with resizing disabled; wrong aspect even with resizing.
    np.save(tmp_path / "f1.npy", depth[1][:, :20])
    prior_error(FolderDepthPrior(tmp_path, resize=False, progress=False), prior_frames(2), "frame 1",
                    tmp_path / "f1.npy", "resizing disabled")
    prior_error(FolderDepthPrior(tmp_path, progress=False), prior_frames(2), "frame 1", "aspect")
    # Frames with names are named so, not by their place in a batch (the streamed run's).
    prior_error(FolderDepthPrior(tmp_path, frame_names=["f0", "f1"], resize=False, progress=False), prior_frames(2),
                "depth of frame f1 is", "resizing disabled")
    # All-zero and NaN maps.
    np.save(tmp_path / "f1.npy", np.zeros((H, W), np.float32))
    prior_error(FolderDepthPrior(tmp_path, progress=False), prior_frames(2), "frame 1", tmp_path / "f1.npy",
                    "no valid pixel")
    np.save(tmp_path / "f1.npy", np.full((H, W), np.nan, np.float32))
    prior_error(FolderDepthPrior(tmp_path, progress=False), prior_frames(2), "frame 1", tmp_path / "f1.npy",
                    "no valid pixel")
    # NaN is read as an invalid pixel unless the caller asks for strictness.
    nan = depth[1].copy()
    nan[5, 5] = np.nan
    np.save(tmp_path / "f1.npy", nan)
    prior_error(FolderDepthPrior(tmp_path, allow_nan=False, progress=False), prior_frames(2), "frame 1", "NaN")
    for prior in (FolderDepthPrior(tmp_path, progress=False), FolderDepthPrior(tmp_path, allow_nan=True,
                                                                                progress=False)):
        out = prior(prior_frames(2))
        assert out.depth[1, 5, 5] == 0 and out.info["nonfinite_pixels"] == 1
    with pytest.raises(ReconInputError, match="does not exist"):
        FolderDepthPrior(tmp_path / "missing")


@pytest.mark.parametrize("suffix", [".npy", ".pfm", ".tiff"])
def test_nan_and_inf_are_invalid_pixels_and_counted(tmp_path, suffix):
    """Depth tools write NaN (or inf) for "no depth": such pixels become 0 (invalid), and the
    output's info counts them per file, over every batch of the call."""
    maps = prior_depth(3)
    maps[0, 5, 5] = np.nan
    maps[0, 7, :5] = np.inf
    maps[2, :, 0] = -np.inf
    for k, d in enumerate(maps):
        _write(tmp_path / f"f{k}{suffix}", d)
    out = FolderDepthPrior(tmp_path, progress=False, batch_size=2)(prior_frames(3))
    np.testing.assert_allclose(out.depth, np.where(np.isfinite(maps), maps, 0.0), atol=1e-6)
    assert out.info["nonfinite_pixels"] == 6 + H
    assert out.info["nonfinite_files"] == {f"f0{suffix}": 6, f"f2{suffix}": H}
    # Disparity maps the same way; a clean folder counts nothing.
    out = FolderDepthPrior(tmp_path, kind="disparity", progress=False)(prior_frames(3))
    assert out.depth[0, 5, 5] == 0 and out.info["nonfinite_pixels"] == 6 + H
    for k, d in enumerate(prior_depth(3)):
        _write(tmp_path / f"f{k}{suffix}", d)
    out = FolderDepthPrior(tmp_path, progress=False)(prior_frames(3))
    assert out.info["nonfinite_pixels"] == 0 and out.info["nonfinite_files"] == {}


def test_folder_disparity_aligned_to_reference(tmp_path):
    true_depth = np.random.default_rng(3).uniform(1.0, 4.0, (2, H, W)).astype(np.float32)
    disparity = (1.0 / true_depth - 0.05) / 0.5
    for k in range(2):
        np.save(tmp_path / f"{k}.npy", disparity[k])
    raw = make_prior("folder", path=tmp_path, kind="disparity", progress=False)(prior_frames(2))
    assert raw.kind == "affine_disparity"
    sparse = np.where(np.random.default_rng(4).random(true_depth.shape) < 0.1, true_depth, 0.0)
    out = make_prior("folder", path=tmp_path, kind="disparity", align_to=sparse, progress=False)(prior_frames(2))
    assert out.kind == "metric" and out.info["aligned_to"] == "given reference depth"
    np.testing.assert_allclose(out.depth, true_depth, rtol=1e-3)
