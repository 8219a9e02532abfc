"""Dataset readers (recon.io.datasets): tiny generated examples of each layout, auto-detection, errors, real data."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from recon.errors import ReconInputError
from recon.eval.trajectory import path_length
from recon.geometry.rigid import make_poses
from recon.io.datasets import KINDS, detect_dataset, detect_kind, open_dataset
from recon.io.datasets.base import register_depth
from recon.io.pose_formats.trajectories import write_poses
from recon.poses.result import invert_poses
from test_io_datasets_new_layouts import make_colmap, make_kitti, make_record3d

from helpers import SHARED_DATA

H, W = 6, 8


def _poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return make_poses(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(size=(n, 3)))


def _rgb(i, h=H, w=W):
    """A distinct flat colour per frame (survives JPEG), RGB order."""
    return np.full((h, w, 3), (10 * i + 20, 100, 200 - 10 * i), np.uint8)


def _save_rgb(path, image):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))


def _save_depth(path, raw):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.asarray(raw, np.uint16))


def _raw_depth(value, h=H, w=W):
    raw = np.full((h, w), value, np.uint16)
    raw[0, 0] = 0
    return raw


def _save_matrix(path, m):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, m)


# ------------------------------------------------------------------ generated layouts


def make_7scenes(root: Path, n=3, intrinsics=True):
    poses = _poses(n, 1)
    for i in range(n):
        raw = _raw_depth(1234)
        raw[0, 1] = 65535
        _save_rgb(root / f"frame-{i:06d}.color.png", _rgb(i))
        _save_depth(root / f"frame-{i:06d}.depth.png", raw)
        _save_matrix(root / f"frame-{i:06d}.pose.txt", poses[i])
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", [[100.0, 0, 4.0], [0, 101.0, 3.0], [0, 0, 1]])
    return poses


def tum_motion(t):
    """Analytic ground truth: constant yaw rate about a fixed axis and linear translation."""
    rot = Rotation.from_rotvec(np.outer(t, [0.0, 0.3, 0.0]))
    return make_poses(rot.as_matrix(), np.outer(t, [0.5, 0.0, 0.1]) + [1.0, 2.0, 3.0])


def make_tum(root: Path, n=5):
    rgb_ts = 100.0 + np.arange(n) / 30.0
    depth_ts = rgb_ts + 0.004
    lines_rgb, lines_depth = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i, (tr, td) in enumerate(zip(rgb_ts, depth_ts)):
        _save_rgb(root / "rgb" / f"{tr:.6f}.png", _rgb(i))
        _save_depth(root / "depth" / f"{td:.6f}.png", _raw_depth(5000 + 500 * i))
        lines_rgb.append(f"{tr:.6f} rgb/{tr:.6f}.png")
        lines_depth.append(f"{td:.6f} depth/{td:.6f}.png")
    # One depth frame far from any colour frame: must be left out by association.
    lines_depth.append(f"{rgb_ts[-1] + 1.0:.6f} depth/stray.png")
    (root / "rgb.txt").write_text("\n".join(lines_rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(lines_depth) + "\n")
    gt_ts = np.arange(99.9, rgb_ts[-1] + 0.05, 0.01)
    write_poses(root / "groundtruth.txt", tum_motion(gt_ts), "tum", timestamps=gt_ts)
    return rgb_ts


def make_scannet(root: Path, n=3):
    poses = _poses(n, 2)
    for i in range(n):
        _save_rgb(root / "color" / f"{i}.jpg", _rgb(i, 2 * H, 2 * W))
        _save_depth(root / "depth" / f"{i}.png", _raw_depth(1500))
        _save_matrix(root / "pose" / f"{i}.txt", poses[i] if i != 1 else np.full((4, 4), -np.inf))
    k_color = np.array([[200.0, 0, 7.5, 0], [0, 202.0, 5.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    k_depth = np.array([[99.0, 0, 3.4, 0], [0, 100.0, 2.6, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    _save_matrix(root / "intrinsic" / "intrinsic_color.txt", k_color)
    _save_matrix(root / "intrinsic" / "intrinsic_depth.txt", k_depth)
    return poses


def make_arkitscenes(root: Path, n=3, video="4200"):
    base = root / f"{video}_frames"
    stamps = 6000.0 + np.arange(n) * 0.1
    world_to_cam = invert_poses(_poses(n, 3))
    lines = []
    for i, t in enumerate(stamps):
        _save_rgb(base / "lowres_wide" / f"{video}_{t:.3f}.png", _rgb(i))
        _save_depth(base / "lowres_depth" / f"{video}_{t:.3f}.png", _raw_depth(2000))
        (base / "lowres_wide_intrinsics").mkdir(parents=True, exist_ok=True)
        (base / "lowres_wide_intrinsics" / f"{video}_{t:.3f}.pincam").write_text(f"{W} {H} {50 + i} {51 + i} 3.9 2.9\n")
        rotvec = Rotation.from_matrix(world_to_cam[i, :3, :3]).as_rotvec()
        # The trajectory's timestamps carry more digits than the 3 in the file names.
        lines.append(" ".join(f"{v:.8f}" for v in (t + 0.0004, *rotvec, *world_to_cam[i, :3, 3])))
    (base / "lowres_wide.traj").write_text("\n".join(lines) + "\n")
    return world_to_cam


def make_redwood(root: Path, n=3, json_intrinsics=True):
    poses = _poses(n, 4)
    for i in range(n):
        _save_rgb(root / "color" / f"{i:05d}.jpg", _rgb(i))
        _save_depth(root / "depth" / f"{i:05d}.png", _raw_depth(800))
    write_poses(root / "trajectory.log", poses, "log")
    if json_intrinsics:
        k = np.array([[600.0, 0, 3.5], [0, 610.0, 2.5], [0, 0, 1]])
        intrinsic = {"width": W, "height": H, "intrinsic_matrix": k.T.ravel().tolist()}  # column-major
        (root / "camera.json").write_text(json.dumps(intrinsic))
    return poses


# ------------------------------------------------------------------ readers


def test_7scenes(tmp_path):
    poses = make_7scenes(tmp_path)
    ds = open_dataset(tmp_path)
    assert ds.kind == "7scenes" and len(ds) == 3 and ds.shape == (H, W)
    assert ds.frame_ids == ["frame-000000", "frame-000001", "frame-000002"]
    assert ds.depth_intrinsics == (100.0, 101.0, 4.0, 3.0)  # the file holds the depth camera's
    np.testing.assert_allclose(ds.intrinsics, (100.0 * 525 / 585, 101.0 * 525 / 585, 4.0, 3.0))
    np.testing.assert_allclose(ds.poses, poses, atol=1e-12)
    ds = open_dataset(tmp_path, colour_intrinsics=(100.0, 101.0, 4.0, 3.0))  # registered: raw depth
    depth = ds.depth(1)
    assert depth.dtype == np.float32 and depth.shape == (H, W)
    assert depth[0, 0] == 0 and depth[0, 1] == 0  # 0 and 65535 are invalid
    assert depth[2, 2] == pytest.approx(1.234)
    rgb = ds.rgb(2)
    assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3)
    np.testing.assert_array_equal(rgb, _rgb(2))  # RGB, not BGR
    (tmp_path / "camera-intrinsics.txt").unlink()
    ds = open_dataset(tmp_path)
    assert ds.depth_intrinsics == (585.0, 585.0, 320.0, 240.0)
    np.testing.assert_allclose(ds.intrinsics, (525.0, 525.0, 320.0, 240.0))


def test_depth_registration_into_the_colour_camera():
    """A depth camera with a longer focal sees a magnified image: registering it into the
    colour camera must put each scene point at the pixel the colour camera sees it at."""
    h, w = 48, 64
    depth_k, colour_k = (70.0, 70.0, 32.0, 24.0), (50.0, 50.0, 32.0, 24.0)
    # A tilted plane z = 2 + 0.5 x (x in metres): z-depth is a function of the ray only.
    def plane_depth(k):
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        slope = (u - k[2]) / k[0]
        return (2.0 / (1.0 - 0.5 * slope)).astype(np.float32)
    seen_by_depth, seen_by_colour = plane_depth(depth_k), plane_depth(colour_k)
    seen_by_depth[20:24, 30:34] = 0  # a hole stays a hole
    registered = register_depth(seen_by_depth[None], depth_k, colour_k)[0]
    # Colour pixels whose ray leaves the depth camera's narrower view are invalid.
    inside = registered > 0
    assert 0.4 < inside.mean() < 0.6
    # The hole's centre (31.5, 21.5) on the depth camera is colour pixel (31.6, 22.2).
    assert (registered[22, 31:33] == 0).all()
    good = inside & (seen_by_colour > 0)
    # Nearest lookup: error bounded by half a depth-camera pixel of slope.
    np.testing.assert_allclose(registered[good], seen_by_colour[good], rtol=0.01)


def test_tum_association_interpolation_and_intrinsics(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg2_xyz"
    rgb_ts = make_tum(root)
    ds = open_dataset(root)
    assert ds.kind == "tum" and len(ds) == 5
    np.testing.assert_allclose(ds.timestamps, rgb_ts)
    assert ds.depth_paths[0].name == f"{rgb_ts[0] + 0.004:.6f}.png"
    assert ds.intrinsics == (520.9, 521.0, 325.1, 249.7)
    assert ds.depth(2)[3, 3] == pytest.approx(6000 / 5000)
    assert ds.depth(2)[0, 0] == 0
    assert ds.pose_valid.all()
    # SLERP + linear interpolation is exact for this constant-rate motion.
    np.testing.assert_allclose(ds.poses, tum_motion(rgb_ts), atol=2e-6)


def test_tum_intrinsics_file_and_default(tmp_path):
    root = tmp_path / "seq"
    make_tum(root, n=2)
    assert open_dataset(root).intrinsics == (525.0, 525.0, 319.5, 239.5)
    (root / "intrinsics.txt").write_text(
        "# registered depth\nfx=525.0 fy=525.0 cx=319.5 cy=239.5\n"
        "# colour\nfx=517.3 fy=516.5 cx=318.6 cy=255.3 d=0.26,-0.95,0,0,1.1\n"
    )
    ds = open_dataset(root)
    assert ds.intrinsics == (517.3, 516.5, 318.6, 255.3) and ds.distortion[0] == 0.26


def test_tum_errors(tmp_path):
    root = tmp_path / "fr1_seq"
    make_tum(root, n=3)
    gt = (root / "groundtruth.txt").read_text()
    rows = [ln.split() for ln in gt.splitlines() if not ln.startswith("#")]
    shifted = [f"{float(r[0]) + 50:.4f} " + " ".join(r[1:]) for r in rows]
    (root / "groundtruth.txt").write_text("\n".join(shifted) + "\n")
    with pytest.raises(ReconInputError, match=r"groundtruth\.txt: no ground-truth timestamp within 0\.02 s"):
        open_dataset(root)
    (root / "groundtruth.txt").write_text(gt)
    lines = (root / "rgb.txt").read_text().splitlines()
    (root / "rgb.txt").write_text("\n".join(lines + ["100.5 rgb/missing.png"]) + "\n")
    with pytest.raises(ReconInputError, match=r"missing\.png: file not found \(listed in .*rgb\.txt\)"):
        open_dataset(root, max_diff=1.0)
    (root / "rgb.txt").write_text("\n".join(lines + ["100.5"]) + "\n")
    with pytest.raises(ReconInputError, match=r"rgb\.txt:6: expected 2 columns"):
        open_dataset(root)


def test_scannet_resizes_colour_and_marks_invalid_poses(tmp_path):
    poses = make_scannet(tmp_path)
    ds = open_dataset(tmp_path)
    assert ds.kind == "scannet" and ds.shape == (H, W)
    assert ds.intrinsics == (99.0, 100.0, 3.4, 2.6)
    assert ds.rgb(0).shape == (H, W, 3)
    assert np.abs(ds.rgb(0).astype(int) - _rgb(0)).max() <= 3  # JPEG
    assert ds.pose_valid.tolist() == [True, False, True]
    assert np.isnan(ds.poses[1]).all()
    np.testing.assert_allclose(ds.poses[[0, 2]], poses[[0, 2]], atol=1e-12)
    assert ds.depth(0)[1, 1] == pytest.approx(1.5)
    assert len(ds.with_valid_poses()) == 2
    fx, fy, cx, cy = open_dataset(tmp_path, intrinsics_from="color").intrinsics
    assert (fx, fy) == (100.0, 101.0) and (cx, cy) == pytest.approx((3.5, 2.5))
    (tmp_path / "depth" / "2.png").unlink()
    with pytest.raises(ReconInputError, match=r"depth.*2\.png: 3 colour images but 2 depth images"):
        open_dataset(tmp_path)


def test_arkitscenes_converts_world_to_camera(tmp_path):
    world_to_cam = make_arkitscenes(tmp_path)
    for root in (tmp_path, tmp_path / "4200_frames"):
        ds = open_dataset(root)
        assert ds.kind == "arkitscenes" and ds.name == "4200" and len(ds) == 3
        np.testing.assert_allclose(ds.poses, invert_poses(world_to_cam), atol=1e-6)
    assert ds.frame_ids[1] == "4200_6000.100"
    assert ds.intrinsics == (50.0, 51.0, 3.9, 2.9)
    assert ds.intrinsics_of(2) == (52.0, 53.0, 3.9, 2.9)
    assert ds.depth(0)[2, 2] == pytest.approx(2.0)
    # The camera centre of c2w is -R^T t of the stored world-to-camera transform.
    np.testing.assert_allclose(ds.poses[0, :3, 3], -world_to_cam[0, :3, :3].T @ world_to_cam[0, :3, 3], atol=1e-6)


def test_redwood(tmp_path):
    poses = make_redwood(tmp_path)
    ds = open_dataset(tmp_path)
    assert ds.kind == "redwood" and len(ds) == 3
    assert ds.intrinsics == (600.0, 610.0, 3.5, 2.5)  # column-major json read right
    np.testing.assert_allclose(ds.poses, poses, atol=1e-9)
    assert ds.depth(1)[1, 1] == pytest.approx(0.8)
    (tmp_path / "camera.json").unlink()
    assert open_dataset(tmp_path).intrinsics == (525.0, 525.0, 319.5, 239.5)
    write_poses(tmp_path / "trajectory.log", poses[:2], "log")
    with pytest.raises(ReconInputError, match=r"trajectory\.log: 2 poses for 3 frames"):
        open_dataset(tmp_path)


def test_detection(tmp_path):
    makers = {
        "7scenes": make_7scenes,
        "tum": make_tum,
        "scannet": make_scannet,
        "arkitscenes": make_arkitscenes,
        "redwood": make_redwood,
        "record3d": make_record3d,
        "kitti": make_kitti,
        "colmap": lambda root: make_colmap(root, ["1 PINHOLE 8 6 10 10 4 3"], [1, 1]),
    }
    assert set(makers) == set(KINDS)
    for kind, make in makers.items():
        make(tmp_path / kind)
        assert detect_kind(tmp_path / kind) == kind
        assert detect_dataset(tmp_path / kind).kind == kind
    (tmp_path / "empty").mkdir()
    assert detect_dataset(tmp_path / "empty") is None
    with pytest.raises(ReconInputError, match="not a recognised RGB-D dataset layout"):
        open_dataset(tmp_path / "empty")
    with pytest.raises(ReconInputError, match="no such folder"):
        open_dataset(tmp_path / "nope")


def test_selection_and_batches(tmp_path):
    poses = make_7scenes(tmp_path, n=5)
    ds = open_dataset(tmp_path)
    sel = ds.select(start=1, stride=2, max_frames=2)
    assert sel.frame_ids == ["frame-000001", "frame-000003"]
    np.testing.assert_allclose(sel.poses, poses[[1, 3]])
    assert ds.load_rgb_batch([4, 0]).shape == (2, H, W, 3)
    depth = sel.load_depth_batch()
    assert depth.shape == (2, H, W) and depth.dtype == np.float32
    assert ds.subset([2]).rgb(0)[0, 0].tolist() == _rgb(2)[0, 0].tolist()


def test_file_errors(tmp_path):
    make_7scenes(tmp_path, n=3)
    (tmp_path / "frame-000001.color.png").write_bytes(b"not a png")
    (tmp_path / "frame-000002.depth.png").unlink()
    with pytest.raises(ReconInputError, match=r"frame-000002\.depth\.png: file not found"):
        open_dataset(tmp_path)
    _save_depth(tmp_path / "frame-000002.depth.png", _raw_depth(10))
    ds = open_dataset(tmp_path)
    with pytest.raises(ReconInputError, match=r"frame-000001\.color\.png: cannot read colour image") as info:
        ds.rgb(1)
    assert "\n" not in str(info.value)
    assert cv2.imwrite(str(tmp_path / "frame-000002.depth.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(ReconInputError, match=r"frame-000002\.depth\.png: expected a single-channel 16-bit"):
        ds.depth(2)
    (tmp_path / "frame-000000.pose.txt").unlink()
    with pytest.raises(ReconInputError, match=r"frame-000000\.pose\.txt: file not found"):
        open_dataset(tmp_path)
    _save_matrix(tmp_path / "frame-000000.pose.txt", np.eye(4) * 2)
    with pytest.raises(ReconInputError, match=r"frame-000000\.pose\.txt: rotation is not orthonormal"):
        open_dataset(tmp_path)


# ------------------------------------------------------------------ real recordings


def _real(name: str) -> Path:
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"{path} is not present")
    return path


def test_real_7scenes():
    ds = open_dataset(_real("7scenes-redkitchen"))
    assert ds.kind == "7scenes" and len(ds) == 400 and ds.shape == (480, 640)
    np.testing.assert_allclose(ds.intrinsics, (525.0, 525.0, 320.0, 240.0))  # colour camera
    assert ds.pose_valid.all() and np.isfinite(ds.poses).all()
    assert 2.5 < path_length(ds.poses) < 3.5  # about 7 mm per frame
    depth = ds.depth(0)
    valid = depth[depth > 0]
    assert depth.shape == (480, 640) and 0.5 < valid.min() and valid.max() < 5.0
    assert ds.rgb(399).shape == (480, 640, 3)


def test_real_tum():
    root = _real("tum-fr1-rpy")
    ds = open_dataset(root)
    assert ds.kind == "tum" and 95 <= len(ds) <= 100 and ds.shape == (480, 640)
    assert ds.intrinsics == (517.3, 516.5, 318.6, 255.3)
    assert ds.pose_valid.all()
    assert 0.1 < path_length(ds.poses) < 0.5  # mostly rotation
    # Our association reproduces the shipped pre-associated list.
    assoc = [ln.split() for ln in (root / "rgbd_assoc.txt").read_text().splitlines() if ln.strip()]
    assert [p.name for p in ds.depth_paths] == [Path(a[3]).name for a in assoc]
    depth = ds.depth(0)
    assert 0.3 < depth[depth > 0].min() and depth.max() < 6.0
