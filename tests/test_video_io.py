"""Frame sources: videos we write ourselves (mp4, avi, rotation metadata), image folders,
dataset folders, selection (stride, max frames, time range, working width) and every
bad-input error."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.io.frames import (
    DatasetSource,
    ImageFolderSource,
    natural_key,
    open_source,
    resize_intrinsics,
    scale_intrinsics,
)
from recon.io.video import VideoSource

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
W, H, FPS = 64, 48, 10.0


def _frame(i: int, w: int = W, h: int = H) -> np.ndarray:
    """RGB frame i: flat grey level 20 + 20 i (survives lossy codecs) and a white square moving right."""
    img = np.full((h, w, 3), 20 + 20 * i, np.uint8)
    x = 4 + 4 * i
    img[8:24, x : x + 16] = 255
    return img


def _write_video(path: Path, n: int, fourcc: str = "mp4v", w: int = W, h: int = H, fps: float = FPS) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened(), f"cannot write {path} with {fourcc}"
    for i in range(n):
        writer.write(cv2.cvtColor(_frame(i, w, h), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def _grey(rgb: np.ndarray) -> float:
    """Grey level of the frame's bottom rows (away from the moving square)."""
    return float(rgb[-10:].mean())


def _one_line(exc: pytest.ExceptionInfo) -> str:
    message = str(exc.value)
    assert "\n" not in message and message
    return message


# --------------------------------------------------------------------------- videos


@pytest.mark.parametrize("suffix, fourcc", [(".mp4", "mp4v"), (".avi", "MJPG")])
def test_video_read_back(tmp_path, suffix, fourcc):
    path = _write_video(tmp_path / f"clip{suffix}", 8, fourcc)
    source = open_source(path)
    assert isinstance(source, VideoSource)
    assert source.size == (W, H) and source.native_size == (W, H)
    assert source.fps == pytest.approx(FPS)
    assert source.count == 8 and not source.count_is_exact
    frames = list(source)
    assert [f.index for f in frames] == list(range(8))
    assert np.allclose([f.timestamp for f in frames], np.arange(8) / FPS, atol=1e-3)
    for f in frames:
        assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
        assert abs(_grey(f.rgb) - (20 + 20 * f.index)) < 8  # right frame, RGB not BGR-swapped grey
    # The moving square moved right by 4 px per frame.
    cols = [np.flatnonzero(f.rgb[16, :, 0] > 200).min() for f in frames[:3]]
    assert np.allclose(np.diff(cols), 4, atol=1)
    assert "video" in source.description and str(path) in source.description
    # A source can be iterated again.
    assert len(source.read_all()) == 8


def test_video_selection_and_resize(tmp_path):
    path = _write_video(tmp_path / "clip.mp4", 10)
    s = open_source(path, stride=3)
    assert [f.index for f in s] == [0, 3, 6, 9] and s.count == 4
    s = open_source(path, stride=2, max_frames=3)
    assert [f.index for f in s] == [0, 2, 4] and s.count == 3
    s = open_source(path, start_time=0.3, end_time=0.7)
    batch = s.read_all()
    assert list(batch.indices) == [3, 4, 5, 6] and s.count == 4
    assert np.allclose(batch.timestamps, [0.3, 0.4, 0.5, 0.6], atol=1e-3)
    s = open_source(path, start_time=0.25, stride=2)
    assert [f.index for f in s] == [3, 5, 7, 9]
    s = open_source(path, width=32)
    assert s.size == (32, 24)
    first = next(iter(s))
    assert first.rgb.shape == (24, 32, 3)
    assert abs(_grey(first.rgb) - 20) < 8


def _rotate_mp4(src: Path, dst: Path) -> None:
    """Copy of an mp4 whose video track header says 'display rotated 90 degrees'.

    OpenCV cannot write rotation metadata, so patch the tkhd box's 3x3 display matrix
    (16.16 fixed point, as a phone would write it) to [[0, 1], [-1, 0]].
    """
    data = bytearray(src.read_bytes())
    i = data.find(b"tkhd")
    assert i > 0
    version = data[i + 4]
    offset = i + 8 + (20 if version == 0 else 32) + 16  # times, ids, duration; reserved, layer, group, volume
    data[offset : offset + 36] = struct.pack(">9i", 0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000)
    dst.write_bytes(bytes(data))


def test_video_rotation_metadata(tmp_path):
    plain = _write_video(tmp_path / "plain.mp4", 4)
    rotated = tmp_path / "portrait.mp4"
    _rotate_mp4(plain, rotated)
    cap = cv2.VideoCapture(str(rotated))
    meta = cap.get(cv2.CAP_PROP_ORIENTATION_META)
    cap.release()
    if meta != 90:
        pytest.skip(f"this OpenCV build does not report rotation metadata (got {meta})")
    s = open_source(rotated)
    assert s.rotation == 90
    assert s.native_size == (H, W) and s.size == (H, W)  # portrait now
    up = next(iter(open_source(plain))).rgb
    turned = next(iter(s)).rgb
    assert turned.shape == (W, H, 3)
    # Displayed frame = stored frame turned 90 degrees clockwise.
    expected = np.rot90(up, k=-1)
    assert np.abs(turned.astype(int) - expected.astype(int)).mean() < 6
    # Resizing applies to the rotated frame and keeps its aspect.
    s = open_source(rotated, width=24)
    assert s.size == (24, 32) and next(iter(s)).rgb.shape == (32, 24, 3)


# --------------------------------------------------------------------------- image folders


def _write_images(folder: Path, names, size=(W, H)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), cv2.cvtColor(_frame(i, *size), cv2.COLOR_RGB2BGR))


def test_image_folder_natural_order(tmp_path):
    names = [f"frame{i}.png" for i in (0, 1, 2, 10, 11, 20)]
    # Write in natural order (grey level encodes the position), list in scrambled order.
    _write_images(tmp_path / "imgs", names)
    (tmp_path / "imgs" / "notes.txt").write_text("not an image")
    (tmp_path / "imgs" / ".hidden.png").write_bytes(b"junk")
    source = open_source(tmp_path / "imgs", fps=5)
    assert isinstance(source, ImageFolderSource)
    assert [p.name for p in source.files] == names
    assert source.count == 6 and source.count_is_exact and source.fps == 5
    frames = list(source)
    assert [f.index for f in frames] == list(range(6))
    assert np.allclose([f.timestamp for f in frames], np.arange(6) / 5)
    assert [round((_grey(f.rgb) - 20) / 20) for f in frames] == list(range(6))
    assert sorted(["f10", "f2", "f1"], key=natural_key) == ["f1", "f2", "f10"]
    s = open_source(tmp_path / "imgs", stride=2, max_frames=2, width=32)
    batch = s.read_all()
    assert list(batch.indices) == [0, 2] and batch.rgb.shape == (2, 24, 32, 3)


def test_jpeg_folder(tmp_path):
    _write_images(tmp_path / "j", ["a1.jpg", "a2.jpeg", "a3.JPG"])
    s = open_source(tmp_path / "j")
    assert s.count == 3 and s.size == (W, H)


# --------------------------------------------------------------------------- datasets


def _tiny_7scenes(root: Path, n: int = 4, w: int = 40, h: int = 30) -> None:
    root.mkdir()
    for i in range(n):
        stem = root / f"frame-{i:06d}"
        cv2.imwrite(f"{stem}.color.png", cv2.cvtColor(_frame(i, w, h), cv2.COLOR_RGB2BGR))
        cv2.imwrite(f"{stem}.depth.png", np.full((h, w), 1000 + 100 * i, np.uint16))
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        np.savetxt(f"{stem}.pose.txt", pose)
    np.savetxt(root / "camera-intrinsics.txt", [[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])


def test_dataset_folder(tmp_path):
    _tiny_7scenes(tmp_path / "seq")
    s = open_source(tmp_path / "seq", width=20, stride=2)
    assert isinstance(s, DatasetSource)
    assert s.size == (20, 15) and s.count == 2
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


def test_scale_intrinsics_pixel_centres():
    # The centre of a 640x480 image stays the centre of the 320x240 one.
    assert scale_intrinsics((500.0, 500.0, 319.5, 239.5), 0.5) == pytest.approx((250.0, 250.0, 159.5, 119.5))
    assert resize_intrinsics((100.0, 90.0, 10.0, 20.0), (64, 48), (128, 96)) == pytest.approx((200.0, 180.0, 20.5, 40.5))


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


# --------------------------------------------------------------------------- bad input


def test_missing_path(tmp_path):
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "nope.mp4")
    assert "nope.mp4" in _one_line(exc)


def test_not_a_video(tmp_path):
    fake = tmp_path / "fake.mp4"
    fake.write_text("this is a text file, not a video\n" * 20)
    with pytest.raises(ReconInputError) as exc:
        open_source(fake)
    assert "fake.mp4" in _one_line(exc) and "video" in str(exc.value)


def test_video_without_frames(tmp_path):
    empty = tmp_path / "empty.avi"
    writer = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    writer.release()
    with pytest.raises(ReconInputError) as exc:
        open_source(empty)
    assert "empty.avi" in _one_line(exc) and "frames" in str(exc.value)


def test_too_few_frames(tmp_path):
    path = _write_video(tmp_path / "one.mp4", 1)
    assert open_source(path).count == 1
    with pytest.raises(ReconInputError) as exc:
        open_source(path, min_frames=2)
    assert "at least 2" in _one_line(exc) and "one.mp4" in str(exc.value)
    path = _write_video(tmp_path / "five.mp4", 5)
    with pytest.raises(ReconInputError) as exc:
        open_source(path, start_time=3.0)  # past the end: nothing selected
    assert "no frames" in _one_line(exc)
    _write_images(tmp_path / "single", ["x.png"])
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "single", min_frames=2)
    assert "at least 2" in _one_line(exc)


def test_empty_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("no images here")
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "empty")
    assert "no images" in _one_line(exc)


def test_mixed_image_sizes(tmp_path):
    folder = tmp_path / "mixed"
    _write_images(folder, ["f1.png", "f2.png"])
    _write_images(folder, ["f3.png"], size=(32, 24))
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    message = _one_line(exc)
    assert "f3.png" in message and "32x24" in message and f"{W}x{H}" in message
    # Same for JPEG headers.
    folder = tmp_path / "mixedjpg"
    _write_images(folder, ["a1.jpg"])
    _write_images(folder, ["a2.jpg"], size=(W, H + 2))
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    assert "a2.jpg" in _one_line(exc) and f"{W}x{H + 2}" in str(exc.value)


def test_unreadable_images(tmp_path):
    folder = tmp_path / "bad"
    _write_images(folder, ["f1.png", "f2.png"])
    (folder / "f3.png").write_text("not a png")
    with pytest.raises(ReconInputError) as exc:
        open_source(folder)
    assert "f3.png" in _one_line(exc)
    # A valid header over a corrupt body passes the quick check and fails when read.
    folder = tmp_path / "corrupt"
    _write_images(folder, ["f1.png", "f2.png"])
    data = (folder / "f2.png").read_bytes()
    (folder / "f2.png").write_bytes(data[:33] + b"\0" * (len(data) - 33))
    source = open_source(folder)
    with pytest.raises(ReconInputError) as exc:
        list(source)
    assert "f2.png" in _one_line(exc)


def test_single_image_and_bad_options(tmp_path):
    _write_images(tmp_path, ["only.png"])
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "only.png")
    assert "only.png" in _one_line(exc)
    path = _write_video(tmp_path / "c.mp4", 3)
    for kwargs in ({"stride": 0}, {"max_frames": 0}, {"start_time": -1.0}, {"start_time": 2.0, "end_time": 1.0}, {"width": 2}):
        with pytest.raises(ReconInputError) as exc:
            open_source(path, **kwargs)
        _one_line(exc)
