"""The streamed pipeline (recon.stream) against the one-shot pipeline on the synthetic room:
the same poses and frames give the same depth and mesh, within the goals of issue 22."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from medea_core import MedeaConfig
from recon.config import PipelineConfig
from recon.demo import mesh_scores, write_demo_inputs
from recon.eval.depth import depth_metrics
from recon.io.output_folder import OutputFolder, load_output
from recon.pipeline import run_pipeline
from recon.synthetic import render_sequence, simulate_prior


@pytest.fixture(scope="module")
def room_video(tmp_path_factory):
    """36 frames of the synthetic room at 256x192 as a video, its trajectory and a simulated prior."""
    seq = render_sequence(36, 256, 192, seed=0)
    out = OutputFolder(tmp_path_factory.mktemp("room"))
    return seq, write_demo_inputs(out, seq, simulate_prior(seq.depth, seed=1))


def _config(room_video, output, stream: str, **fields) -> PipelineConfig:
    seq, inputs = room_video
    fast = MedeaConfig.fast()  # fewer epochs: the test compares two runs, it does not tune MEDeA
    medea = replace(fast, seed=0, stage1=replace(fast.stage1, epochs=60), stage2=replace(fast.stage2, epochs=10))
    return PipelineConfig(input=inputs["video"], output=output, width=None, intrinsics=seq.intrinsics,
                          poses=str(inputs["poses"]), prior="folder", prior_path=inputs["prior"], medea=medea,
                          polish=False, stream=stream, depth_frames="all", window=16, window_overlap=4,
                          rerun="off", progress=False, **fields)


def test_streamed_run_matches_the_one_shot_run(room_video, tmp_path):
    seq, _ = room_video
    batch = run_pipeline(_config(room_video, tmp_path / "batch", "off"))
    streamed = run_pipeline(_config(room_video, tmp_path / "stream", "on"))

    assert streamed.report["streamed"] and streamed.report["windows"]["count"] == 3
    written = load_output(tmp_path / "stream")
    assert np.array_equal(written.indices, np.arange(36))  # every frame got depth, in order
    batch_depth = depth_metrics(batch.depth, seq.depth)["abs_rel"]
    stream_depth = depth_metrics(written.depth, seq.depth)["abs_rel"]
    print(f"abs rel one-shot {batch_depth:.4f} streamed {stream_depth:.4f}")
    assert batch_depth < 0.05
    assert stream_depth <= batch_depth * 1.02 + 1e-3
    f_batch = mesh_scores(batch.fusion.mesh, seq)["fscore"]
    f_stream = mesh_scores(streamed.fusion.mesh, seq)["fscore"]
    print(f"F@5cm one-shot {f_batch:.4f} streamed {f_stream:.4f}", streamed.report["windows"]["each"])
    assert f_batch > 0.8 and f_stream >= f_batch - 0.02
    print(batch.seconds, streamed.seconds)
    assert np.allclose(written.poses, seq.poses, atol=1e-4)
