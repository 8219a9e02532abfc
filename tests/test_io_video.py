"""Video files (recon.io.video): videos we write ourselves (mp4, avi, rotation metadata) read
back through open_source, selection (stride, max frames, time range, working width), every
bad-video error, and writing frames as an mp4."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.io.frames import open_source
from recon.io.video import VideoSource, write_video

from helpers import SOURCE_FPS as FPS
from helpers import SOURCE_H as H
from helpers import SOURCE_W as W
from helpers import grey_level, one_line, write_clip, write_images


@pytest.mark.parametrize("suffix, fourcc", [(".mp4", "mp4v"), (".avi", "MJPG")])
def test_video_read_back(tmp_path, suffix, fourcc):
    path = write_clip(tmp_path / f"clip{suffix}", 8, fourcc)
    source = open_source(path)
    assert isinstance(source, VideoSource)
    assert source.shape == (H, W) and source.native_shape == (H, W)
    assert source.fps == pytest.approx(FPS)
    assert source.count == 8 and not source.count_is_exact
    frames = list(source)
    assert [f.index for f in frames] == list(range(8))
    assert np.allclose([f.timestamp for f in frames], np.arange(8) / FPS, atol=1e-3)
    for f in frames:
        assert f.rgb.shape == (H, W, 3) and f.rgb.dtype == np.uint8
        assert abs(grey_level(f.rgb) - (20 + 20 * f.index)) < 8  # right frame, RGB not BGR-swapped grey
    # The moving square moved right by 4 px per frame.
    cols = [np.flatnonzero(f.rgb[16, :, 0] > 200).min() for f in frames[:3]]
    assert np.allclose(np.diff(cols), 4, atol=1)
    assert "video" in source.description and str(path) in source.description
    # A source can be iterated again.
    assert len(source.read_all()) == 8


def test_video_selection_and_resize(tmp_path):
    path = write_clip(tmp_path / "clip.mp4", 10)
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
    assert s.shape == (24, 32)
    first = next(iter(s))
    assert first.rgb.shape == (24, 32, 3)
    assert abs(grey_level(first.rgb) - 20) < 8


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
    plain = write_clip(tmp_path / "plain.mp4", 4)
    rotated = tmp_path / "portrait.mp4"
    _rotate_mp4(plain, rotated)
    cap = cv2.VideoCapture(str(rotated))
    meta = cap.get(cv2.CAP_PROP_ORIENTATION_META)
    cap.release()
    if meta != 90:
        pytest.skip(f"this OpenCV build does not report rotation metadata (got {meta})")
    s = open_source(rotated)
    assert s.rotation == 90
    assert s.native_shape == (W, H) and s.shape == (W, H)  # portrait now
    up = next(iter(open_source(plain))).rgb
    turned = next(iter(s)).rgb
    assert turned.shape == (W, H, 3)
    # Displayed frame = stored frame turned 90 degrees clockwise.
    expected = np.rot90(up, k=-1)
    assert np.abs(turned.astype(int) - expected.astype(int)).mean() < 6
    # Resizing applies to the rotated frame and keeps its aspect.
    s = open_source(rotated, width=24)
    assert s.shape == (32, 24) and next(iter(s)).rgb.shape == (32, 24, 3)


def test_not_a_video(tmp_path):
    fake = tmp_path / "fake.mp4"
    fake.write_text("this is a text file, not a video\n" * 20)
    with pytest.raises(ReconInputError) as exc:
        open_source(fake)
    assert "fake.mp4" in one_line(exc) and "video" in str(exc.value)


def test_damaged_video_decodes_without_ffmpeg_noise(tmp_path):
    """FFmpeg's complaints while decoding a damaged video ("header damaged") stay off stderr.
    A fresh process: FFmpeg writes them to file descriptor 2 from C, which capsys would miss."""
    rng = np.random.default_rng(0)
    path = write_video(rng.integers(0, 256, (30, 96, 128, 3), dtype=np.uint8), tmp_path / "damaged.mp4")
    data = bytearray(path.read_bytes())
    data[len(data) // 3: len(data) // 3 + 2000] = rng.bytes(2000)
    path.write_bytes(bytes(data))
    code = "import sys; from recon.io.video import VideoSource; print(sum(1 for _ in VideoSource(sys.argv[1])))"
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert int(proc.stdout) > 0


def test_video_without_frames(tmp_path):
    empty = tmp_path / "empty.avi"
    writer = cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    writer.release()
    with pytest.raises(ReconInputError) as exc:
        open_source(empty)
    assert "empty.avi" in one_line(exc) and "frames" in str(exc.value)


def test_too_few_frames(tmp_path):
    path = write_clip(tmp_path / "one.mp4", 1)
    assert open_source(path).count == 1
    with pytest.raises(ReconInputError) as exc:
        open_source(path, min_frames=2)
    assert "at least 2" in one_line(exc) and "one.mp4" in str(exc.value)
    path = write_clip(tmp_path / "five.mp4", 5)
    with pytest.raises(ReconInputError) as exc:
        open_source(path, start_time=3.0)  # past the end: nothing selected
    assert "no frames" in one_line(exc)
    write_images(tmp_path / "single", ["x.png"])
    with pytest.raises(ReconInputError) as exc:
        open_source(tmp_path / "single", min_frames=2)
    assert "at least 2" in one_line(exc)


def test_write_video(tmp_path, small_room):
    path = write_video(small_room.rgb, tmp_path / "clip.mp4", fps=10)
    assert path.is_file() and [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == len(small_room.rgb)
    assert frames[0].shape == small_room.rgb[0].shape
    assert np.abs(frames[0][..., ::-1].astype(float) - small_room.rgb[0]).mean() < 15
    with pytest.raises(ReconInputError):
        write_video(small_room.rgb[0], tmp_path / "bad.mp4")
