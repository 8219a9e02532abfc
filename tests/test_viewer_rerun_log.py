"""viewer: log a tiny run to an .rrd, read it back with rerun's chunk API, check it; the
default layout (viewer.blueprint) as built and as saved in the .rrd."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from viewer import RerunLogger, arrays, default_blueprint, default_mode, rerun_log
from viewer.blueprint import LOSSES_TAB, RECONSTRUCTION_TAB, SCENE_VIEW

from helpers import read_recording, recording_blueprint

N_FRAMES = 5
H, W = 24, 40
INTRINSICS = (30.0, 30.0, 19.5, 11.5)  # fx fy cx cy, pixel centres at integers

pytest.importorskip("rerun.chunk", reason="needs rerun-sdk with rerun.chunk (0.41+)")


def _poses() -> list[np.ndarray]:
    poses = []
    for i in range(N_FRAMES):
        pose = np.eye(4)
        pose[:3, 3] = [0.1 * i, 0.0, 0.0]
        poses.append(pose)
    return poses


def _history() -> dict:
    return {
        "stage1": {"total": [3.0, 2.0, 1.5], "photometric": [1.0, 0.9, 0.8], "depth": [1.0, 0.6, 0.4],
                   "feature": [1.0, 0.5, 0.3]},
        "stage2": {"total": [1.2, 1.1], "photometric": [0.5, 0.4], "depth": [0.4, 0.4], "feature": [0.3, 0.3]},
    }


def _log_run(logger: RerunLogger) -> None:
    rng = np.random.default_rng(0)
    for i, pose in enumerate(_poses()):
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        prior = (1.0 + rng.random((H, W))).astype(np.float32)
        prior[0, 0] = 0.0  # invalid pixel
        adjusted = torch.from_numpy(prior * 1.1)  # torch input accepted too
        confidence = rng.random((H, W)).astype(np.float32)
        logger.log_frame(i, rgb, prior, adjusted, pose, INTRINSICS, timestamp=i / 30.0, refined_depth=prior * 1.05,
                         confidence=confidence)
    vertices = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], dtype=np.float32)
    triangles = np.array([[0, 1, 2], [1, 3, 2]])
    logger.log_mesh(vertices, triangles, vertex_colors=np.full((4, 3), 0.5))
    logger.log_points(vertices, colors=np.full((4, 3), 200, dtype=np.uint8))
    logger.log_losses(_history())


def test_save_roundtrip(tmp_path):
    path = tmp_path / "sub" / "run.rrd"
    with RerunLogger("save", path, max_width=None) as logger:
        assert logger.enabled
        _log_run(logger)
    assert not logger.enabled
    assert path.is_file() and path.stat().st_size > 0

    entities, components, frames, values = read_recording(path)
    expected = [
        "/world",
        "/world/camera",
        "/world/camera/rgb",
        "/world/camera/prior_depth",
        "/world/camera/adjusted_depth",
        "/world/camera/refined_depth",
        "/world/camera/confidence",
        "/world/trajectory/00000",
        "/world/mesh",
        "/world/points",
    ] + [f"/medea/{stage}/{term}" for stage in ("stage1", "stage2")
         for term in ("total", "photometric", "depth", "feature")]
    for entity in expected:
        assert entity in entities, entity

    assert "ViewCoordinates:xyz" in components["/world"]
    camera_columns = {"Pinhole:image_from_camera", "Pinhole:resolution", "Transform3D:translation",
                      "Transform3D:mat3x3"}
    assert camera_columns <= components["/world/camera"]
    assert "Image:buffer" in components["/world/camera/rgb"]
    assert {"DepthImage:buffer", "DepthImage:meter"} <= components["/world/camera/prior_depth"]
    assert {"DepthImage:buffer", "DepthImage:meter"} <= components["/world/camera/adjusted_depth"]
    assert "LineStrips3D:strips" in components["/world/trajectory/00000"]
    assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices", "Mesh3D:vertex_colors"} <= components["/world/mesh"]
    assert "Scalars:scalars" in components["/medea/stage1/total"]

    # exactly one rgb row per frame on the "frame" timeline
    assert sorted(frames["/world/camera/rgb"]) == list(range(N_FRAMES))
    assert sorted(frames["/world/camera/adjusted_depth"]) == list(range(N_FRAMES))
    assert sorted(frames["/world/camera/refined_depth"]) == list(range(N_FRAMES))
    assert sorted(frames["/world/camera/confidence"]) == list(range(N_FRAMES))
    assert {"DepthImage:buffer", "DepthImage:meter"} <= components["/world/camera/refined_depth"]
    assert "Image:buffer" in components["/world/camera/confidence"]
    # the mesh is static; losses are per epoch
    assert "/world/mesh" not in frames
    assert sorted(frames["/medea/stage1/total#epoch"]) == [0, 1, 2]
    assert sorted(frames["/medea/stage2/total#epoch"]) == [0, 1]
    stage1_total = [row[0] for row in values["/medea/stage1/total"]["Scalars:scalars"]]
    assert stage1_total == pytest.approx(_history()["stage1"]["total"])

    # pinhole: full resolution, principal point shifted to Rerun's pixel-corner origin
    k = np.asarray(values["/world/camera"]["Pinhole:image_from_camera"][0], dtype=np.float64).reshape(3, 3).T
    fx, fy, cx, cy = INTRINSICS
    np.testing.assert_allclose(k, [[fx, 0, cx + 0.5], [0, fy, cy + 0.5], [0, 0, 1]], atol=1e-5)
    assert np.ravel(values["/world/camera"]["Pinhole:resolution"][0]).tolist() == [W, H]
    translations = values["/world/camera"]["Transform3D:translation"]
    np.testing.assert_allclose(np.asarray(translations[0], dtype=np.float64).ravel(), [0.0, 0.0, 0.0])


def test_save_downscaled(tmp_path):
    path = tmp_path / "small.rrd"
    with RerunLogger("save", path, max_width=W // 2) as logger:
        _log_run(logger)
    _, _, frames, values = read_recording(path)
    assert sorted(frames["/world/camera/rgb"]) == list(range(N_FRAMES))
    assert np.ravel(values["/world/camera"]["Pinhole:resolution"][0]).tolist() == [W // 2, H // 2]
    k = np.asarray(values["/world/camera"]["Pinhole:image_from_camera"][0], dtype=np.float64).reshape(3, 3).T
    fx, fy, cx, cy = INTRINSICS
    np.testing.assert_allclose(k, [[fx / 2, 0, (cx + 0.5) / 2], [0, fy / 2, (cy + 0.5) / 2], [0, 0, 1]], atol=1e-5)


def test_resize_nearest_keeps_invalid_pixels_unmixed():
    depth = np.array([[0.0, 2.0], [3.0, 4.0]], dtype=np.float32).repeat(2, 0).repeat(2, 1)
    small = arrays.resize_nearest(depth, 2, 2)
    assert set(np.unique(small)) <= {0.0, 2.0, 3.0, 4.0}
    np.testing.assert_array_equal(arrays.resize_nearest(depth, 4, 4), depth)


def test_off_mode_is_noop(tmp_path):
    path = tmp_path / "off.rrd"
    logger = RerunLogger("off", path)
    assert not logger.enabled
    _log_run(logger)
    logger.close()
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []


def test_asking_for_the_default_mode_does_not_import_rerun():
    """A run without a viewer never needs the Rerun SDK (half a second of imports)."""
    code = ("import sys, viewer\n"
            "from recon.commands.cli_config import default_rerun_mode\n"
            "viewer.default_mode(), default_rerun_mode()\n"
            "assert 'rerun' not in sys.modules, 'rerun imported'\n"
            "viewer.RerunLogger\n"
            "assert 'rerun' in sys.modules\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]


def test_default_mode(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert default_mode() == "off"
    assert RerunLogger().mode == "off"
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert default_mode() == "spawn"


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError):
        RerunLogger("nope")
    with pytest.raises(ValueError):
        RerunLogger("save")
    with RerunLogger("save", tmp_path / "bad.rrd") as logger, pytest.raises(TypeError):
        logger.log_mesh(np.eye(3), [[0, 1, 2]], None, "world/other")  # entity is keyword-only


# ---------------------------------------------------------------------- live logging and the layout

DEPTH_ENTITIES = ("/world/camera/prior_depth", "/world/camera/adjusted_depth", "/world/camera/refined_depth",
                  "/world/camera/confidence")


def _log_live(logger: RerunLogger) -> None:
    """A streamed run: tracking, RGB + camera per frame, depth one frame late, the mesh
    growing at frames 1 and 3, losses at the end."""
    rng = np.random.default_rng(1)
    vertices = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], dtype=np.float32)
    for i, pose in enumerate(_poses()):
        logger.log_tracking(i, "keyframe" if i == 0 else "tracked", pose)
        logger.log_frame(i, rng.integers(0, 256, (H, W, 3), dtype=np.uint8), pose=pose, intrinsics=INTRINSICS,
                         timestamp=i / 30.0)
        if i > 0:  # the previous frame's depth arrives after this frame's RGB
            prior = (1.0 + rng.random((H, W))).astype(np.float32)
            logger.log_depth(i - 1, prior_depth=prior)
            logger.log_depth(i - 1, adjusted_depth=prior * 1.1, refined_depth=prior, confidence=rng.random((H, W)))
        if i in (1, 3):
            logger.log_mesh(vertices[: i + 1], [[0, 1, 2]] if i == 1 else [[0, 1, 2], [1, 3, 2]], index=i)
    logger.log_depth(N_FRAMES - 1, prior_depth=np.ones((H, W), np.float32))
    logger.log_losses(_history())


def test_live_logging_roundtrip_with_layout(tmp_path):
    path = tmp_path / "live.rrd"
    with RerunLogger("save", path, max_width=W // 2) as logger:
        _log_live(logger)
    entities, components, frames, values = read_recording(path)

    # every frame once, in order, RGB and depth at the same frame and time
    rgb_frames = frames["/world/camera/rgb"]
    assert rgb_frames == sorted(rgb_frames) == list(range(N_FRAMES))
    assert sorted(frames["/world/camera/prior_depth"]) == list(range(N_FRAMES))
    for entity in DEPTH_ENTITIES[1:]:
        assert sorted(frames[entity]) == list(range(N_FRAMES - 1))
    times = dict(zip(frames["/world/camera/rgb"], frames["/world/camera/rgb#time"]))
    depth_times = dict(zip(frames["/world/camera/prior_depth"], frames["/world/camera/prior_depth#time"]))
    assert depth_times == times
    # depth logged later is resampled to the size the frame's RGB was logged at
    assert values["/world/camera/prior_depth"]["DepthImage:format"][0][0]["width"] == W // 2
    # the trajectory holds one centre per frame; tracking lines on the frame timeline
    assert sorted(frames["/tracking"]) == list(range(N_FRAMES))
    assert len(values["/world/trajectory/00000"]["LineStrips3D:strips"][0][0]) == 1

    # the mesh: two updates on the frame timeline, none static
    assert sorted(frames["/world/mesh"]) == [1, 3]
    assert "/world/mesh#time" in frames  # frames 1 and 3 carry their timestamps
    assert {"Mesh3D:vertex_positions", "Mesh3D:triangle_indices"} <= components["/world/mesh"]

    # the layout travels with the file, active and default
    layout = recording_blueprint(path)
    _check_layout(layout)
    assert layout["play_state"] == "Following"
    if layout["activation"] is not None:  # None: no bundled CLI to read the activation command
        assert layout["activation"] == {"make_active": True, "make_default": True}


def _check_layout(layout: dict) -> None:
    """The default layout: frame timeline; tabs "reconstruction" (active: the 3D scene without
    depth, a row of 2D views) and "losses" (bar charts of medea/)."""
    assert layout["timeline"] == "frame"
    root = layout["root"]
    assert root["kind"] == "Tabs" and root["active_tab"] == 0
    reconstruction, losses = root["contents"]
    assert reconstruction["name"] == RECONSTRUCTION_TAB and losses["name"] == LOSSES_TAB

    scene, row = reconstruction["contents"]
    assert scene["class"] == "3D" and scene["name"] == SCENE_VIEW and scene["origin"] == "/world"
    assert "+ /world/**" in scene["contents"]
    for entity in DEPTH_ENTITIES:
        assert f"- {entity}" in scene["contents"]
    assert row["kind"] == "Horizontal"
    images = [(view["class"], view["origin"]) for view in row["contents"] if view["class"] == "2D"]
    assert images == [("2D", "/world/camera/rgb")] + [("2D", entity) for entity in DEPTH_ENTITIES]
    assert {view["class"] for view in losses["contents"]} == {"BarChart"}  # shown on every timeline
    assert all(view["origin"].startswith("/medea/") for view in losses["contents"])
    assert [view["class"] for view in layout["views"]].count("3D") == 1


def test_default_blueprint_is_pure_and_complete():
    import rerun.blueprint as rrb

    blueprint = default_blueprint()
    assert isinstance(blueprint, rrb.Blueprint)
    assert blueprint.time_panel.timeline == "frame"
    tabs = blueprint.root_container
    assert isinstance(tabs, rrb.Tabs) and tabs.active_tab == 0
    reconstruction, losses = tabs.contents
    scene = reconstruction.contents[0]
    assert isinstance(scene, rrb.Spatial3DView) and scene.origin == "/world"
    assert [view.origin for view in losses.contents] == ["/medea/stage1", "/medea/stage2"]
    assert [view.origin for view in default_blueprint(["only"]).root_container.contents[1].contents] == ["/medea/only"]


def test_trajectory_is_logged_in_pieces_that_join(tmp_path, monkeypatch):
    """Each camera re-logs only its piece of the trajectory (a recording grows linearly with
    the frames, not with their square), and the pieces join into one line."""
    monkeypatch.setattr(rerun_log, "TRAJECTORY_PIECE", 4)
    path = tmp_path / "long.rrd"
    centres = np.stack([np.arange(11.0), np.zeros(11), np.zeros(11)], axis=1)
    with RerunLogger("save", path, max_width=None) as logger:
        for k, c in enumerate(centres):
            pose = np.eye(4)
            pose[:3, 3] = c
            logger.log_frame(k, None, pose=pose)
    _, _, frames, _ = read_recording(path)
    pieces = sorted(e for e in frames if e.startswith("/world/trajectory/") and "#" not in e)
    assert pieces == ["/world/trajectory/00000", "/world/trajectory/00001", "/world/trajectory/00002"]
    assert sorted(frames["/world/trajectory/00001"]) == [4, 5, 6, 7]
    last = _last_strips(path)
    assert [len(last[p]) for p in pieces] == [4, 5, 4]  # pieces after the first start at the one before
    joined = np.concatenate([last[pieces[0]]] + [last[p][1:] for p in pieces[1:]])
    assert np.allclose(joined, centres)


def _last_strips(path) -> dict[str, np.ndarray]:
    """The last logged strip of each trajectory piece of an .rrd."""
    import rerun.chunk as rr_chunk

    last = {}
    for chunk in rr_chunk.RrdReader(path).stream():
        if chunk.entity_path.startswith("/world/trajectory/"):
            strips = chunk.to_record_batch().column("LineStrips3D:strips").to_pylist()
            last[chunk.entity_path] = np.asarray(strips[-1][0], dtype=np.float64)
    return last
