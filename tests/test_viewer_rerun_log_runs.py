"""Every frame's camera in a saved Rerun recording: the logger's final cameras (log_cameras)
replacing what tracking logged, then the recordings of real runs read back (a streamed
estimate whose focal search buffers every frame, a one-shot run, `recon view` of the
streamed run's folder): at each frame a Transform3D at the pose of trajectory.txt and a
Pinhole of the logged RGB's size."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

import numpy as np
import pytest

from recon.commands.demo import write_demo_inputs
from recon.core.config import PipelineConfig
from recon.fusion import FusionOptions
from recon.io.output_folder import OutputFolder, read_report, read_trajectory
from recon.pipeline import run_pipeline
from recon.synthetic import render_sequence, simulate_prior
from viewer import RerunLogger

pytestmark = pytest.mark.slow  # end-to-end runs: `make test-fast` leaves them out

rr_chunk = pytest.importorskip("rerun.chunk", reason="needs rerun-sdk with rerun.chunk (0.41+)")

FRAMES = 36
H, W = 24, 40
INTRINSICS = (30.0, 30.0, 19.5, 11.5)


def shown_at_frames(path, entity: str, column: str) -> dict[int, object]:
    """{frame: the value of ``column`` the viewer shows at that frame} over the rows of
    ``entity`` logged at exactly that frame (the last logged wins, as in Rerun's latest-at);
    frames without such a row are absent."""
    rows: dict[int, list[tuple[bytes, object]]] = defaultdict(list)
    for chunk in rr_chunk.RrdReader(path).stream():
        if chunk.entity_path != entity or "frame" not in chunk.timeline_names:
            continue
        batch = chunk.to_record_batch()
        if column not in batch.schema.names:
            continue
        for row_id, frame, value in zip(batch.column("rerun.controls.RowId").to_pylist(),
                                        batch.column("frame").to_pylist(), batch.column(column).to_pylist()):
            if value is not None:
                rows[frame].append((row_id, value))
    return {frame: max(values, key=lambda v: v[0])[1] for frame, values in rows.items()}


def _translation(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).ravel()


def _pose(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = [x, 0.0, 0.0]
    return pose


# ---------------------------------------------------------------------- the logger


def test_final_cameras_replace_what_tracking_logged(tmp_path):
    """Frames 0-2 logged without pose or intrinsics (a focal search buffering), 3-5 with live
    poses; then the final cameras, frame 4 without a pose (dropped): every frame has the final
    camera at its time, frame 4 the one of frame 3, the trajectory is the final poses alone."""
    path = tmp_path / "final.rrd"
    rng = np.random.default_rng(0)
    final = [_pose(float(i)) for i in range(6)]
    final[4] = np.full((4, 4), np.nan)
    with RerunLogger("save", path, max_width=W // 2) as logger:
        for i in range(6):
            rgb, tracked = rng.integers(0, 256, (H, W, 3), dtype=np.uint8), i >= 3
            logger.log_frame(i, rgb, pose=_pose(-5.0 - i) if tracked else None,
                             intrinsics=INTRINSICS if tracked else None, timestamp=i / 30.0)
        logger.log_cameras(np.arange(6), np.stack(final), INTRINSICS, (H, W))
    translations = shown_at_frames(path, "/world/camera", "Transform3D:translation")
    assert {f: _translation(t)[0] for f, t in translations.items()} == {0: 0, 1: 1, 2: 2, 3: 3, 4: 3, 5: 5}
    resolutions = shown_at_frames(path, "/world/camera", "Pinhole:resolution")
    assert sorted(resolutions) == list(range(6))
    assert all(np.ravel(r).tolist() == [W // 2, H // 2] for r in resolutions.values())  # the RGB's logged size
    strips = shown_at_frames(path, "/world/trajectory/00000", "LineStrips3D:strips")
    assert np.asarray(strips[5][0])[:, 0].tolist() == [0, 1, 2, 3, 5]  # in order, the dropped frame left out
    assert np.asarray(strips[2][0])[:, 0].tolist() == [0, 1, 2]  # the trajectory so far


def test_a_camera_without_images_gets_its_pinhole_from_the_intrinsics_size(tmp_path):
    """(fx, fy, cx, cy, width, height): a camera logged without an image (`recon view` of a
    frame without depth) still gets its pinhole."""
    path = tmp_path / "bare.rrd"
    with RerunLogger("save", path, max_width=W // 2) as logger:
        logger.log_frame(0, None, pose=_pose(0.0), intrinsics=(*INTRINSICS, W, H))
        logger.log_frame(1, None, pose=_pose(1.0), intrinsics=INTRINSICS)  # no size known: no pinhole
    resolutions = shown_at_frames(path, "/world/camera", "Pinhole:resolution")
    assert {f: np.ravel(r).tolist() for f, r in resolutions.items()} == {0: [W // 2, H // 2]}
    k = np.asarray(shown_at_frames(path, "/world/camera", "Pinhole:image_from_camera")[0]).reshape(3, 3).T
    fx, fy, cx, cy = INTRINSICS
    np.testing.assert_allclose(k, [[fx / 2, 0, (cx + 0.5) / 2], [0, fy / 2, (cy + 0.5) / 2], [0, 0, 1]], atol=1e-5)


def test_losses_show_on_every_timeline(tmp_path):
    """Loss histories: scalars on the epoch timeline and a static bar chart per loss term."""
    path = tmp_path / "losses.rrd"
    with RerunLogger("save", path) as logger:
        logger.log_losses({"stage1": {"total": [3.0, 2.0, 1.5], "depth": [1.0, 0.5, 0.4],
                                      "valid_fraction": [0.9, 0.9, 0.9]}})
    charts = {}
    for chunk in rr_chunk.RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if "BarChart:values" in batch.schema.names:
            assert chunk.is_static
            charts[chunk.entity_path] = batch.column("BarChart:values").to_pylist()[-1][0]
    assert set(charts) == {"/medea/stage1/total", "/medea/stage1/depth"}
    assert np.ravel(charts["/medea/stage1/total"]["buffer"]).tolist() == [3.0, 2.0, 1.5]


# ---------------------------------------------------------------------- recordings of runs


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The synthetic room at 256x192 as a video, its trajectory and a simulated prior."""
    seq = render_sequence(FRAMES, 256, 192, seed=0)
    out = OutputFolder(tmp_path_factory.mktemp("room"))
    return seq, write_demo_inputs(out, seq, simulate_prior(seq.depth, seed=1))


def _config(room, output, **fields) -> PipelineConfig:
    """A quick run: the prior fused as it is (no MEDeA, no refinement) into coarse voxels,
    recording saved."""
    _, inputs = room
    return PipelineConfig(input=inputs["video"], output=output, width=None, prior="folder",
                          prior_path=inputs["prior"], adjust=False, refine="none", glb=False, progress=False,
                          fusion=FusionOptions(voxel_size=0.08), rerun="save", **fields)


def _check_every_camera(path, frames, folder) -> None:
    """At every frame of ``frames`` a Transform3D and a Pinhole of the RGB's logged size; the
    frames in trajectory.txt at its pose, the others at the pose of the frame before them."""
    poses, report = read_trajectory(folder), read_report(folder)
    posed = dict(zip(report["frames"]["indices"], poses))
    translations = shown_at_frames(path, "/world/camera", "Transform3D:translation")
    resolutions = shown_at_frames(path, "/world/camera", "Pinhole:resolution")
    assert sorted(translations) == sorted(resolutions) == list(frames)
    rgb = shown_at_frames(path, "/world/camera/rgb", "Image:format")
    assert sorted(rgb) == list(frames)
    assert all(np.ravel(resolutions[f]).tolist() == [rgb[f][0]["width"], rgb[f][0]["height"]] for f in frames)
    last = None
    for f in frames:
        last = posed.get(f, last)
        np.testing.assert_allclose(_translation(translations[f]), last[:3, 3], atol=1e-4, err_msg=f"frame {f}")
    # the whole trajectory at the last frame, in order
    pieces = sorted({e for e in (c.entity_path for c in rr_chunk.RrdReader(path).stream())
                     if e.startswith("/world/trajectory/")})
    strips = [np.asarray(shown_at_frames(path, p, "LineStrips3D:strips")[frames[-1]][0]) for p in pieces]
    line = np.concatenate([strips[0]] + [s[1:] for s in strips[1:]])
    np.testing.assert_allclose(line, np.stack([p[:3, 3] for _, p in sorted(posed.items())]), atol=1e-4)


def test_a_streamed_estimate_logs_every_frames_camera(room, tmp_path):
    """Estimated poses, intrinsics unknown: the focal search buffers the whole video (80
    frames), so tracking logs every frame's RGB without a camera; once the trajectory is
    closed every frame gets its camera, and `recon view` of the folder logs every camera too."""
    from recon.commands.view import log_output_folder

    result = run_pipeline(_config(room, tmp_path / "stream", stream="on", poses="estimate", depth_frames="3"))
    assert result.report["streamed"] and result.intrinsics is not None
    folder = tmp_path / "stream"
    _check_every_camera(folder / "recording.rrd", list(range(FRAMES)), folder)

    viewed = tmp_path / "view.rrd"
    with RerunLogger("save", viewed, max_width=None) as logger:
        log_output_folder(folder, logger, progress=False)
    kept = read_report(folder)["frames"]["indices"]
    translations = shown_at_frames(viewed, "/world/camera", "Transform3D:translation")
    resolutions = shown_at_frames(viewed, "/world/camera", "Pinhole:resolution")
    assert sorted(translations) == sorted(resolutions) == sorted(kept)
    assert all(np.ravel(r).tolist() == [256, 192] for r in resolutions.values())


def test_a_one_shot_run_logs_every_frames_camera(room, tmp_path):
    seq, inputs = room
    config = replace(_config(room, tmp_path / "once", stream="off", poses=str(inputs["poses"])),
                     intrinsics=seq.intrinsics)
    run_pipeline(config)
    _check_every_camera(tmp_path / "once" / "recording.rrd", list(range(FRAMES)), tmp_path / "once")
