"""Dataset readers for Record3D exports, KITTI odometry and COLMAP projects (recon.io.datasets):
tiny generated examples (detection, values read back exactly, one-line errors), the EXR
decoder, and slices of the real recordings (skipped when absent)."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import recon.io.pose_formats.colmap
from recon.errors import ReconInputError
from recon.eval.trajectory import path_length
from recon.geometry.rigid import make_poses, matrix_to_quat
from recon.io.datasets import detect_kind, open_dataset
from recon.io.datasets.base import upscale_nearest
from recon.io.exr import read_exr
from recon.io.pose_formats.trajectories import read_poses, write_poses
from recon.poses.result import invert_poses

from helpers import SHARED_DATA

H, W = 6, 8


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return make_poses(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(size=(n, 3)))


def _save_rgb(path, i, grey=False):
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.full((H, W) if grey else (H, W, 3), 20 * i + 10, np.uint8)
    assert cv2.imwrite(str(path), image)


def _one_line(info):
    assert "\n" not in str(info.value)
    return str(info.value)


# ------------------------------------------------------------------ EXR (as Record3D writes it)


def write_exr(path: Path, image: np.ndarray, compression: int = 3, channel: str = "R") -> None:
    """A single-channel scanline EXR: HALF for float16 input, else FLOAT; compression 0 (NONE),
    2 (ZIPS) or 3 (ZIP, 16 lines a chunk), as OpenEXR's file layout document describes."""
    ptype = 1 if image.dtype == np.float16 else 2
    image = image.astype("<f2" if ptype == 1 else "<f4")
    height, width = image.shape

    def attr(name, kind, value):
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    chlist = channel.encode() + b"\0" + struct.pack("<iB3xii", ptype, 0, 1, 1) + b"\0"
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    header = (attr("channels", "chlist", chlist) + attr("compression", "compression", bytes([compression]))
              + attr("dataWindow", "box2i", box) + attr("displayWindow", "box2i", box)
              + attr("lineOrder", "lineOrder", b"\0") + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
              + attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
              + attr("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")
    lines = 16 if compression == 3 else 1
    chunks = []
    for y in range(0, height, lines):
        raw = image[y: y + lines].tobytes()
        if compression:
            b = np.frombuffer(raw, np.uint8)
            split = np.concatenate([b[0::2], b[1::2]]).astype(np.int64)
            coded = split.copy()
            coded[1:] = (split[1:] - split[:-1] + 128) & 0xFF
            packed = zlib.compress(coded.astype(np.uint8).tobytes())
            raw = packed if len(packed) < len(raw) else raw
        chunks.append(struct.pack("<ii", y, len(raw)) + raw)
    start = 8 + len(header) + 8 * len(chunks)
    offsets = np.cumsum([start] + [len(c) for c in chunks[:-1]]).astype("<u8")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + header + offsets.tobytes() + b"".join(chunks))


@pytest.mark.parametrize("compression", [0, 2, 3])
@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_exr_decoder(tmp_path, compression, dtype):
    rng = np.random.default_rng(1)
    image = rng.uniform(0.1, 5.0, (37, 21)).astype(dtype)  # 37 lines: a partial last ZIP chunk
    image[3, 4] = np.nan
    write_exr(tmp_path / "d.exr", image, compression)
    out = read_exr(tmp_path / "d.exr")
    assert out.dtype == np.float32 and out.shape == image.shape
    np.testing.assert_array_equal(out, image.astype(np.float32))


def test_exr_errors(tmp_path):
    write_exr(tmp_path / "piz.exr", np.ones((4, 4), np.float16), compression=4)
    with pytest.raises(ReconInputError, match=r"piz\.exr: EXR compression PIZ is not supported"):
        read_exr(tmp_path / "piz.exr")
    write_exr(tmp_path / "cut.exr", np.ones((40, 40), np.float32), compression=0)
    (tmp_path / "cut.exr").write_bytes((tmp_path / "cut.exr").read_bytes()[:-100])
    with pytest.raises(ReconInputError, match=r"cut\.exr: ") as info:
        read_exr(tmp_path / "cut.exr")
    _one_line(info)
    (tmp_path / "not.exr").write_bytes(b"hello")
    with pytest.raises(ReconInputError, match=r"not\.exr: not an OpenEXR file"):
        read_exr(tmp_path / "not.exr")


def test_nearest_upscaling_keeps_pixel_centres():
    small = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.testing.assert_array_equal(upscale_nearest(small, (6, 8)), np.repeat(np.repeat(small, 2, 0), 2, 1))
    # 7.5x, as Record3D's 192x256 -> 1440x1920: colour pixel u sees depth pixel floor((u + 0.5) / 7.5).
    big = upscale_nearest(np.arange(4, dtype=np.float32)[None].repeat(2, 0), (15, 30))
    assert big[0].tolist() == [int((u + 0.5) / 7.5) for u in range(30)]
    with pytest.raises(ReconInputError, match="another aspect ratio"):
        upscale_nearest(small, (6, 12))


# ------------------------------------------------------------------ Record3D


def make_record3d(root: Path, numbers=(0, 1, 3, 4), entries=5):
    """rgb/N.jpg for `numbers` (2 missing, as exports skip some), depth/N.exr at half size,
    metadata.json with ARKit (OpenGL-axes) poses for `entries` frames."""
    gl = _poses(entries, 3)
    quat = matrix_to_quat(gl[:, :3, :3])
    stamps = 0.5 + np.arange(entries) / 60.0
    meta = {"K": [100.0, 0, 0, 0, 101.0, 0, 3.9, 2.9, 1], "w": W, "h": H, "dw": W // 2, "dh": H // 2, "fps": 60,
            "poses": [[*q, *t] for q, t in zip(quat.tolist(), gl[:, :3, 3].tolist())],
            "frameTimestamps": stamps.tolist()}
    (root / "rgb").mkdir(parents=True)
    (root / "metadata.json").write_text(json.dumps(meta, indent=1))
    small = {}
    for n in numbers:
        _save_rgb(root / "rgb" / f"{n}.jpg", n)
        depth = (0.5 + 0.1 * n + np.arange(12).reshape(3, 4) / 100).astype(np.float16)
        depth[0, 0], depth[1, 1], depth[2, 2] = np.nan, -1.0, np.inf
        write_exr(root / "depth" / f"{n}.exr", depth)
        small[n] = depth
    return gl, stamps, small


def test_record3d(tmp_path):
    gl, stamps, small = make_record3d(tmp_path)
    assert detect_kind(tmp_path) == "record3d"
    ds = open_dataset(tmp_path)
    assert ds.kind == "record3d" and len(ds) == 4 and ds.frame_ids == ["0", "1", "3", "4"]
    assert ds.intrinsics == (100.0, 101.0, 3.9, 2.9) and ds.shape == (H, W)
    np.testing.assert_array_equal(ds.timestamps, stamps[[0, 1, 3, 4]])
    # OpenCV axes: the camera's x stays, its y and z are ARKit's negated; the centre stays.
    for k, n in enumerate([0, 1, 3, 4]):
        np.testing.assert_allclose(ds.poses[k, :3, 0], gl[n, :3, 0], atol=1e-9)
        np.testing.assert_allclose(ds.poses[k, :3, 1:3], -gl[n, :3, 1:3], atol=1e-9)
        np.testing.assert_allclose(ds.poses[k, :3, 3], gl[n, :3, 3], atol=1e-12)
    depth = ds.depth(2)
    expected = np.repeat(np.repeat(small[3].astype(np.float32), 2, 0), 2, 1)
    expected[~(expected > 0) | ~np.isfinite(expected)] = 0.0
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, expected)
    assert (depth == 0).sum() == 3 * 4


def test_record3d_errors(tmp_path):
    make_record3d(tmp_path)
    meta_path = tmp_path / "metadata.json"
    meta = json.loads(meta_path.read_text())
    (tmp_path / "depth" / "3.exr").unlink()
    with pytest.raises(ReconInputError, match=r"depth/3\.exr: file not found") as info:
        open_dataset(tmp_path)
    _one_line(info)
    write_exr(tmp_path / "depth" / "3.exr", np.ones((3, 4), np.float16))
    _save_rgb(tmp_path / "rgb" / "7.jpg", 7)
    with pytest.raises(ReconInputError, match=r"metadata\.json: no pose for .*rgb/7\.jpg \('poses' has 5 entries"):
        open_dataset(tmp_path)
    (tmp_path / "rgb" / "7.jpg").unlink()
    bad = dict(meta, poses=[*meta["poses"][:2], meta["poses"][2][:6], *meta["poses"][3:]])
    meta_path.write_text(json.dumps(bad))
    with pytest.raises(ReconInputError, match=r"metadata\.json: poses\[2\]: expected 7 numbers") as info:
        open_dataset(tmp_path)
    _one_line(info)
    meta_path.write_text(json.dumps(meta, indent=1).replace('"w": 8,', '"w": 8'))
    with pytest.raises(ReconInputError, match=r"metadata\.json:\d+: invalid JSON"):
        open_dataset(tmp_path)
    meta_path.write_text(json.dumps(dict(meta, w=16)))
    with pytest.raises(ReconInputError, match=r"metadata\.json: 'K' is for a 16x6 image"):
        open_dataset(tmp_path)
    meta_path.unlink()
    with pytest.raises(ReconInputError, match=r"metadata\.json: file not found"):
        open_dataset(tmp_path, kind="record3d")


# ------------------------------------------------------------------ KITTI

P0 = np.array([[700.0, 0, 4.1, 0], [0, 701.0, 2.9, 0], [0, 0, 1, 0]])
P2 = np.array([[710.0, 0, 4.2, 710.0 * 0.06], [0, 710.0, 3.1, 0], [0, 0, 1, 0]])


def make_kitti(root: Path, n=4, image_dir="image_0", prefixed=True, times=True):
    poses = _poses(n, 4)
    for i in range(n):
        _save_rgb(root / image_dir / f"{i:06d}.png", i, grey=image_dir != "image_2")
    rows = [P0, P0 + [[0, 0, 0, -380.0], [0, 0, 0, 0], [0, 0, 0, 0]], P2, P2]
    (root / "calib.txt").write_text("".join((f"P{k}: " if prefixed else "") + " ".join(f"{v:.12e}" for v in p.ravel())
                                            + "\n" for k, p in enumerate(rows)))
    write_poses(root / "poses.txt", poses, "kitti")
    stamps = 1.0 + np.arange(n) * 0.1037
    if times:
        (root / "times.txt").write_text("".join(f"{t:.6e}\n" for t in stamps))
    return poses, stamps


def test_kitti(tmp_path):
    poses, stamps = make_kitti(tmp_path)
    assert detect_kind(tmp_path) == "kitti"
    ds = open_dataset(tmp_path)
    assert ds.kind == "kitti" and len(ds) == 4 and not ds.has_depth and ds.depth(0) is None
    assert ds.intrinsics == (700.0, 701.0, 4.1, 2.9) and ds.distortion is None
    np.testing.assert_allclose(ds.poses, poses, atol=1e-9)
    np.testing.assert_allclose(ds.timestamps, stamps, rtol=1e-6)
    image = ds.rgb(2)
    assert image.shape == (H, W, 3) and (image == 50).all()  # greyscale as 3 equal channels


def test_kitti_variants(tmp_path):
    # Bare calibration lines (as our copy has), image_l/, no times.txt: KITTI's 10 Hz.
    poses, _ = make_kitti(tmp_path / "a", image_dir="image_l", prefixed=False, times=False)
    ds = open_dataset(tmp_path / "a")
    assert ds.kind == "kitti" and ds.intrinsics == (700.0, 701.0, 4.1, 2.9)
    np.testing.assert_allclose(ds.timestamps, [0.0, 0.1, 0.2, 0.3])
    # image_2/: P2's intrinsics, and the colour camera sits 6 cm left (-x) of camera 0.
    poses, _ = make_kitti(tmp_path / "b", image_dir="image_2")
    ds = open_dataset(tmp_path / "b")
    assert ds.intrinsics == (710.0, 710.0, 4.2, 3.1)
    np.testing.assert_allclose(ds.poses[:, :3, :3], poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(ds.poses[:, :3, 3], poses[:, :3, 3] - 0.06 * poses[:, :3, 0], atol=1e-9)
    # Official layout: sequences/07/ with the ground truth in poses/07.txt.
    seq = tmp_path / "dataset" / "sequences" / "07"
    poses, _ = make_kitti(seq)
    (tmp_path / "dataset" / "poses").mkdir()
    (seq / "poses.txt").rename(tmp_path / "dataset" / "poses" / "07.txt")
    np.testing.assert_allclose(open_dataset(seq).poses, poses, atol=1e-9)


def test_kitti_errors(tmp_path):
    make_kitti(tmp_path)
    lines = (tmp_path / "poses.txt").read_text().splitlines()
    (tmp_path / "poses.txt").write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(ReconInputError, match=r"poses\.txt: 3 poses, but 000003\.png is frame 3") as info:
        open_dataset(tmp_path)
    _one_line(info)
    (tmp_path / "poses.txt").write_text("\n".join([lines[0], lines[1].rsplit(" ", 1)[0], *lines[2:]]) + "\n")
    with pytest.raises(ReconInputError, match=r"poses\.txt:2: expected 12 columns") as info:
        open_dataset(tmp_path)
    _one_line(info)
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "times.txt").write_text("0.0\n0.1\nabc\n0.3\n")
    with pytest.raises(ReconInputError, match=r"times\.txt:3: non-numeric value 'abc'"):
        open_dataset(tmp_path)
    (tmp_path / "times.txt").unlink()
    calib = (tmp_path / "calib.txt").read_text().splitlines()
    (tmp_path / "calib.txt").write_text("\n".join([calib[0] + " 1.0", *calib[1:]]) + "\n")
    with pytest.raises(ReconInputError, match=r"calib\.txt:1: expected 12 numbers"):
        open_dataset(tmp_path)
    (tmp_path / "calib.txt").write_text(calib[1] + "\n")
    with pytest.raises(ReconInputError, match=r"calib\.txt: no P0 line"):
        open_dataset(tmp_path)
    (tmp_path / "calib.txt").unlink()
    assert detect_kind(tmp_path) is None
    with pytest.raises(ReconInputError, match=r"calib\.txt: file not found"):
        open_dataset(tmp_path, kind="kitti")


# ------------------------------------------------------------------ COLMAP project


def make_colmap(root: Path, cameras: list[str], image_cams: list[int], present=None):
    """A text COLMAP project: images/ (the names in `present`, default all) and sparse/0/."""
    n = len(image_cams)
    names = [f"img_{i}.png" for i in range(n)]
    poses = _poses(n, 5)
    w2c = invert_poses(poses)
    quat = matrix_to_quat(w2c[:, :3, :3])
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cameras) + "\n")
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"]
    for i in range(n):
        q, t = quat[i], w2c[i, :3, 3]
        nums = " ".join(f"{v:.17g}" for v in (q[3], q[0], q[1], q[2], *t))
        lines += [f"{i + 1} {nums} {image_cams[i]} {names[i]}", ""]
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    (model / "points3D.txt").write_text("")
    for i in range(n) if present is None else present:
        _save_rgb(root / "images" / names[i], i)
    return poses, names


@pytest.fixture(params=["text reader", "pycolmap"])
def colmap_reader(request, monkeypatch):
    """Text models are read by pycolmap when it is installed, else by recon's own parser: test both."""
    if request.param == "text reader":
        monkeypatch.setattr(recon.io.pose_formats.colmap, "_import_pycolmap", lambda required: None)
    elif recon.io.pose_formats.colmap._import_pycolmap(required=False) is None:
        pytest.skip("pycolmap is not installed")
    return request.param


def test_colmap_project_with_a_camera_per_image(tmp_path, colmap_reader):
    cams = [f"1 SIMPLE_RADIAL {W} {H} 100 4 3 0.01", f"2 SIMPLE_RADIAL {W} {H} 110 4.5 3 0.03",
            f"3 SIMPLE_RADIAL {W} {H} 130 4 3.5 0.08", f"4 SIMPLE_RADIAL {W} {H} 90 4 3 -0.2"]
    # Image 3 is in the model but not in images/.
    poses, names = make_colmap(tmp_path, cams, [1, 2, 3, 4], present=[0, 1, 2])
    _save_rgb(tmp_path / "images" / "unregistered.png", 9)  # in images/, not in the model
    assert detect_kind(tmp_path) == "colmap"
    assert detect_kind(tmp_path / "images") is None  # a bare image folder stays an image folder
    ds = open_dataset(tmp_path)
    assert ds.kind == "colmap" and len(ds) == 3 and ds.frame_ids == ["img_0", "img_1", "img_2"]
    assert not ds.has_depth and ds.timestamps is None and ds.pose_valid.all()
    np.testing.assert_allclose(ds.poses, poses[:3], atol=1e-9)
    # COLMAP's principal points less half a pixel: its first pixel's centre is at 0.5, ours at 0.
    np.testing.assert_allclose(ds.frame_intrinsics, [[100, 100, 3.5, 2.5], [110, 110, 4, 2.5], [130, 130, 3.5, 3]])
    assert ds.intrinsics == (110.0, 110.0, 3.5, 2.5)  # medians over the three frames
    assert ds.intrinsics_of(2) == (130.0, 130.0, 3.5, 3.0)
    assert ds.distortion == (0.03, 0.0, 0.0, 0.0, 0.0)
    # read_colmap keeps the distortion and, with several cameras, each image's values.
    data = read_poses(tmp_path)
    assert data.intrinsics["distortion"] == (0.01, 0.0, 0.0, 0.0, 0.0)
    np.testing.assert_allclose(data.frame_distortion[:, 0], [0.01, 0.03, 0.08, -0.2])


def test_colmap_project_camera_models(tmp_path, colmap_reader):
    make_colmap(tmp_path / "opencv", [f"1 OPENCV {W} {H} 100 102 4 3 0.1 -0.2 0.001 0.002"], [1, 1])
    ds = open_dataset(tmp_path / "opencv")
    assert ds.intrinsics == (100.0, 102.0, 3.5, 2.5) and ds.frame_intrinsics is None
    assert ds.distortion == (0.1, -0.2, 0.001, 0.002, 0.0)
    make_colmap(tmp_path / "radial", [f"1 RADIAL {W} {H} 100 4 3 0.1 -0.2"], [1])
    assert open_dataset(tmp_path / "radial").distortion == (0.1, -0.2, 0.0, 0.0, 0.0)
    make_colmap(tmp_path / "pinhole", [f"1 PINHOLE {W} {H} 100 102 4 3"], [1])
    assert open_dataset(tmp_path / "pinhole").distortion is None
    make_colmap(tmp_path / "fisheye", [f"1 OPENCV_FISHEYE {W} {H} 100 102 4 3 0.1 0 0 0"], [1])
    with pytest.raises(ReconInputError, match=r"cameras\.txt: the camera of img_0\.png has a lens model") as info:
        open_dataset(tmp_path / "fisheye")
    _one_line(info)


def test_colmap_project_errors(tmp_path, colmap_reader):
    make_colmap(tmp_path, [f"1 SIMPLE_RADIAL {W} {H} 100 4 3"], [1, 1])
    # pycolmap names the model folder only; recon's parser the file and line.
    where = r"sparse.0: cannot read COLMAP model" if colmap_reader == "pycolmap" else r"cameras\.txt:2: "
    with pytest.raises(ReconInputError, match=where + r"(SIMPLE_RADIAL has 4 parameters, got 3)?") as info:
        open_dataset(tmp_path)
    _one_line(info)
    model = tmp_path / "sparse" / "0"
    (model / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {W + 2} {H} 100 4 3 0\n")
    with pytest.raises(ReconInputError, match=r"cameras\.txt: the model's camera is 10x6 but .*img_0\.png is 8x6"):
        open_dataset(tmp_path)
    (model / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {W} {H} 100 4 3 0\n")
    text = (model / "images.txt").read_text().splitlines()
    (model / "images.txt").write_text("\n".join([text[0], text[1].replace(" ", " x", 1), *text[2:]]) + "\n")
    where = r"sparse.0: cannot read COLMAP model" if colmap_reader == "pycolmap" else r"images\.txt:2: non-numeric"
    with pytest.raises(ReconInputError, match=where) as info:
        open_dataset(tmp_path)
    _one_line(info)
    (model / "images.txt").unlink()
    assert detect_kind(tmp_path) is None
    with pytest.raises(ReconInputError, match=r"sparse.0: no COLMAP model \(images\.bin or images\.txt not found\)"):
        open_dataset(tmp_path, kind="colmap")


# ------------------------------------------------------------------ real recordings


def _real(name: str) -> Path:
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is not present")
    return path


def _reprojection_agreement(ds, i: int, j: int, poses: np.ndarray, step: int = 8) -> float:
    """Median |z_i->j - depth_j| / depth_j of frame i's depth (every `step`-th pixel) moved
    into frame j with `poses`, where both depths are valid."""
    fx, fy, cx, cy = ds.intrinsics
    v, u = np.mgrid[0:ds.height:step, 0:ds.width:step].astype(np.float64)
    z = ds.depth(i)[::step, ::step].astype(np.float64)
    ok = z > 0
    cam = np.stack([(u[ok] - cx) / fx * z[ok], (v[ok] - cy) / fy * z[ok], z[ok]], axis=1)
    world = cam @ poses[i, :3, :3].T + poses[i, :3, 3]
    w2c = invert_poses(poses[j][None])[0]
    p = world @ w2c[:3, :3].T + w2c[:3, 3]
    p = p[p[:, 2] > 1e-3]
    uj = np.rint(p[:, 0] / p[:, 2] * fx + cx).astype(np.int64)
    vj = np.rint(p[:, 1] / p[:, 2] * fy + cy).astype(np.int64)
    inside = (uj >= 0) & (uj < ds.width) & (vj >= 0) & (vj < ds.height)
    zj = ds.depth(j)[vj[inside], uj[inside]]
    both = zj > 0
    assert both.sum() > 1000  # enough overlap for a median to mean something
    return float(np.median(np.abs(p[inside, 2][both] - zj[both]) / zj[both]))


def test_real_record3d():
    root = _real("record3d-door-handle")
    ds = open_dataset(root)
    meta = json.loads((root / "metadata.json").read_text())
    assert ds.kind == "record3d" and len(ds) == 341 and len(meta["poses"]) == 345 and ds.shape == (1920, 1440)
    assert ds.intrinsics[0] == pytest.approx(1404.3, abs=0.05) and ds.intrinsics[1] == pytest.approx(1404.3, abs=0.05)
    assert ds.pose_valid.all() and np.all(np.diff(ds.timestamps) > 0)
    np.testing.assert_allclose(np.median(np.diff(ds.timestamps)), 1 / meta["fps"], rtol=0.01)
    depth = ds.depth(0)
    valid = depth[depth > 0]
    assert depth.shape == (1920, 1440) and valid.size > 0.9 * depth.size and 0.05 < valid.min() and valid.max() < 3
    # Frames 100 and 140: 7 cm apart and 13 degrees turned, a close-up at about 0.3 m.
    # Frame 100's depth moved into frame 140 meets its depth within a few percent with the
    # converted (OpenCV-axes) poses; ARKit's raw axes, taken as OpenCV's, miss it.
    i, j = 100, 140
    assert np.linalg.norm(ds.poses[j, :3, 3] - ds.poses[i, :3, 3]) > 0.03
    converted = _reprojection_agreement(ds, i, j, ds.poses)
    raw_arkit = ds.poses @ np.diag([1.0, -1.0, -1.0, 1.0])
    unconverted = _reprojection_agreement(ds, i, j, raw_arkit)
    assert converted < 0.04 and unconverted > 3 * converted


def test_real_kitti():
    ds = open_dataset(_real("kitti-odometry-seq1"))
    assert ds.kind == "kitti" and len(ds) == 51 and ds.shape == (370, 1226) and not ds.has_depth
    np.testing.assert_allclose(ds.intrinsics, (707.0912, 707.0912, 601.8873, 183.1104))
    assert ds.rgb(50).shape == (370, 1226, 3)
    np.testing.assert_allclose(ds.timestamps, np.arange(51) / 10)
    assert ds.pose_valid.all()
    np.testing.assert_allclose(ds.poses[0], np.eye(4), atol=1e-9)
    assert 55 < path_length(ds.poses) < 65  # about 1.2 m a frame
    travel = ds.poses[-1, :3, 3] - ds.poses[0, :3, 3]
    assert travel[2] > 55 and np.hypot(travel[0], travel[1]) < 0.1 * travel[2]  # forward along +z
    assert (ds.poses[:, 2, 2] > 0.99).all()  # every camera looks along world +z (the road ahead)


def test_real_colmap_project():
    root = _real("phone-beer")
    assert detect_kind(root / "images") is None
    ds = open_dataset(root)
    assert ds.kind == "colmap" and len(ds) == 71 and ds.shape == (1280, 720) and not ds.has_depth
    assert ds.pose_valid.all() and np.isfinite(ds.poses).all()
    assert ds.frame_intrinsics.shape == (71, 4)
    assert 1101 < ds.frame_intrinsics[:, 0].min() and ds.frame_intrinsics[:, 0].max() < 1156
    # 720 x 1280: the exact centre
    assert ds.intrinsics[0] == pytest.approx(1116, abs=2) and ds.intrinsics[2:] == (359.5, 639.5)
    k1, *rest = ds.distortion
    assert 0.0 < k1 < 0.11 and rest == [0.0] * 4
    # Filmed around a bottle: every optical axis passes close to one point, well in front.
    centres, axes = ds.poses[:, :3, 3], ds.poses[:, :3, 2]
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    target = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, centres))
    miss = np.linalg.norm(np.einsum("nij,nj->ni", proj, target - centres), axis=1)
    ahead = np.einsum("ni,ni->n", target - centres, axes)
    assert (ahead > 0).all() and np.median(miss) < 0.2 * np.median(ahead)
    assert len({p.name for p in ds.rgb_paths}) == 71 and ds.rgb(0).shape == (1280, 720, 3)
