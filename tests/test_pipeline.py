"""recon.pipeline on its own: which driver a run gets (stream_reason), on small generated
inputs; the drivers themselves are tested in test_drivers_streamed.py and test_commands_cli.py."""

from __future__ import annotations

from dataclasses import replace

import pytest

from recon.core.config import PipelineConfig
from recon.core.stages import PosePlan
from recon.io.frames import open_source
from recon.pipeline import stream_reason

from helpers import write_clip, write_images

FRAMES = 12


@pytest.fixture
def inputs(tmp_path):
    """(a 12-frame video, a 3-image folder, the auto configuration for the video)."""
    video = open_source(write_clip(tmp_path / "clip.mp4", FRAMES))
    write_images(tmp_path / "frames", [f"{k:03d}.png" for k in range(3)])
    return video, open_source(tmp_path / "frames"), PipelineConfig(input=video.path, output=tmp_path / "out")


def test_auto_streams_long_inputs_and_videos_with_estimated_poses(inputs):
    """stream "auto": one-shot for given poses, for SfM (which needs every frame at once) and
    for a rolling shutter with estimated poses (estimated twice), streamed beyond the frame
    budget and for a video whose poses are estimated."""
    video, images, auto = inputs
    given, estimated = PosePlan("file"), PosePlan("estimate")
    assert stream_reason(auto, video, given) is None
    assert "video" in stream_reason(auto, video, estimated)
    assert stream_reason(replace(auto, pose_method="sfm"), video, estimated) is None
    # A rolling shutter with estimated poses needs a second estimate, which only a one-shot run makes.
    assert stream_reason(replace(auto, rolling_shutter=30.0), video, estimated) is None
    assert "frame budget" in stream_reason(replace(auto, rolling_shutter=30.0, frame_budget=FRAMES - 1), video, given)
    assert stream_reason(auto, images, estimated) is None
    assert "frame budget" in stream_reason(replace(auto, frame_budget=FRAMES - 1), video, given)
    assert stream_reason(replace(auto, stream="off"), video, estimated) is None
    assert stream_reason(replace(auto, stream="on"), images, given) == "streaming"
