"""Frame sources for image folders and RGB-D dataset folders (recon.io.frames): natural order,
selection and working width, a dataset's depth, poses and intrinsics at working size, and
every bad-input error of open_source (which picks the source for a path)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.io.frames import DatasetSource, ImageFolderSource, open_source
from recon.io.naming import natural_key

from helpers import SHARED_DATA, grey_level, one_line, source_frame, write_clip, write_images
from helpers import SOURCE_H as H
from helpers import SOURCE_W as W


def test_image_folder_natural_order(tmp_path):
    names = [f"frame{i}.png" for i in (0, 1, 2, 10, 11, 20)]
    # Write in natural order (grey level encodes the position), list in scrambled order.
    write_images(tmp_path / "imgs", names)
    (tmp_path / "imgs" / "notes.txt").write_text("not an image")
    (tmp_path / "imgs" / ".hidden.png").write_bytes(b"junk")
    source = open_source(tmp_path / "imgs", fps=5)
    assert isinstance(source, ImageFolderSource)
    assert [p.name for p in source.files] == names
    assert source.count == 6 and source.count_is_exact and source.fps == 5
    frames = list(source)
    assert [f.index for f in frames] == list(range(6))
    assert np.allclose([f.timestamp for f in frames], np.arange(6) / 5)
    assert [round((grey_level(f.rgb) - 20) / 20) for f in frames] == list(range(6))
    assert sorted(["f10", "f2", "f1"], key=natural_key) == ["f1", "f2", "f10"]
    s = open_source(tmp_path / "imgs", stride=2, max_frames=2, width=32)
    batch = s.read_all()
    assert list(batch.indices) == [0, 2] and batch.rgb.shape == (2, 24, 32, 3)


def test_jpeg_folder(tmp_path):
    write_images(tmp_path / "j", ["a1.jpg", "a2.jpeg", "a3.JPG"])
    s = open_source(tmp_path / "j")
    assert s.count == 3 and s.shape == (H, W)


def _tiny_7scenes(root: Path, n: int = 4, w: int = 40, h: int = 30) -> None:
    root.mkdir()
    for i in range(n):
        stem = root / f"frame-{i:06d}"
        cv2.imwrite(f"{stem}.color.png", cv2.cvtColor(source_frame(i, w, h), cv2.COLOR_RGB2BGR))
        cv2.imwrite(f"{stem}.depth.png", np.full((h, w), 1000 + 100 * i, np.uint16))
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        np.savetxt(f"{stem}.pose.txt", pose)
    np.savetxt(root / "camera-intrinsics.txt", [[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])


def test_dataset_folder(tmp_path):
    _tiny_7scenes(tmp_path / "seq")
    s = open_source(tmp_path / "seq", width=20, stride=2)
    assert isinstance(s, DatasetSource)
    assert s.shape == (15, 20) and s.count == 2
    # The file holds the depth camera's 50 px; colour = 50 x 525/585; pixel-centre scaling.
    assert s.intrinsics == pytest.approx((25.0 * 525 / 585, 25.0 * 525 / 585, 9.5, 7.0))
    assert s.intrinsics_of(1) == pytest.approx(s.intrinsics)
    frames = list(s)
    assert [f.index for f in frames] == [0, 2]
    assert frames[1].rgb.shape == (15, 20, 3)
    depth = s.load_depth()
    # Registered into the wider colour view: the border the depth camera misses is invalid.
    assert depth.shape == (2, 15, 20) and np.allclose(depth[1][depth[1] > 0], 1.2) and (depth[1] > 0).mean() > 0.6
    assert s.poses.shape == (2, 4, 4) and s.poses[1][0, 3] == pytest.approx(0.2)


@pytest.mark.skipif(not (SHARED_DATA / "7scenes-redkitchen").is_dir(), reason="../shared is not present")
def test_real_7scenes_source():
    s = open_source(SHARED_DATA / "7scenes-redkitchen", width=320, stride=50, max_frames=3)
    assert isinstance(s, DatasetSource) and s.count == 3
    assert s.intrinsics == pytest.approx((262.5, 262.5, 159.75, 119.75))  # colour camera, 525 px at 640
    batch = s.read_all()
    assert batch.rgb.shape == (3, 240, 320, 3) and list(batch.indices) == [0, 50, 100]
    depth = s.load_depth()
    valid = depth[depth > 0]
    assert depth.shape == (3, 240, 320) and 0.5 < np.median(valid) < 4.5


def test_missing_path(tmp_path):
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "nope.mp4")
    assert "nope.mp4" in one_line(exc)


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images here")
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "empty")
    assert "no images" in one_line(exc)


def test_mixed_image_sizes(tmp_path):
    folder = tmp_path / "mixed"
    write_images(folder, ["f1.png", "f2.png"])
    write_images(folder, ["f3.png"], size=(32, 24))
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    message = one_line(exc)
    assert "f3.png" in message and "32x24" in message and f"{W}x{H}" in message
    # Same for JPEG headers.
    folder = tmp_path / "mixedjpg"
    write_images(folder, ["a1.jpg"])
    write_images(folder, ["a2.jpg"], size=(W, H + 2))
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    assert "a2.jpg" in one_line(exc) and f"{W}x{H + 2}" in str(exc.value)


def test_unreadable_images(tmp_path):
    folder = tmp_path / "bad"
    write_images(folder, ["f1.png", "f2.png"])
    (folder / "f3.png").write_text("not a png")
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    assert "f3.png" in one_line(exc)
    # A valid header over a corrupt body passes the quick check and fails when read.
    folder = tmp_path / "corrupt"
    write_images(folder, ["f1.png", "f2.png"])
    data = (folder / "f2.png").read_bytes()
    (folder / "f2.png").write_bytes(data[:33] + b"\0" * (len(data) - 33))
    source = open_source(folder)
    with pytest.raises(ReconInputError) as exc:
        list(source)
    assert "f2.png" in one_line(exc)


def test_single_image_and_bad_options(tmp_path):
    write_images(tmp_path, ["only.png"])
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "only.png")
    assert "only.png" in one_line(exc)
    path = write_clip(tmp_path / "c.mp4", 3)
    bad_options = ({"stride": 0}, {"max_frames": 0}, {"start_time": -1.0}, {"start_time": 2.0, "end_time": 1.0},
                   {"width": 2})
    for kwargs in bad_options:
        with pytest.raises(ReconInputError) as exc:
            open_source(path, **kwargs)
        one_line(exc)
