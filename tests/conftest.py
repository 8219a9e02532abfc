"""Shared fixtures: two torch threads per test, the torch devices (`device`), the ../shared
data and weights (tests that need them skip when they are absent), and the synthetic rooms
that several test files use, rendered once per session. Plain helper functions are in helpers.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from helpers import FASTDEPTH_WEIGHTS, SHARED


@pytest.fixture(autouse=True)
def _two_threads():
    torch.set_num_threads(2)


# The torch devices of this machine: every test that takes `device` runs once on each, so
# that a machine with CUDA runs the GPU path of the same assertions (a CPU-only machine
# runs "cpu" alone, without a skipped variant).
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture
def shared_dir() -> Path:
    if not (SHARED / "data").is_dir():
        pytest.skip("../shared is not present next to the checkout")
    return SHARED


@pytest.fixture(scope="session")
def fastdepth_weights() -> Path:
    """The FastDepth TF.js folder in ../shared/weights."""
    if not (FASTDEPTH_WEIGHTS / "model.json").is_file():
        pytest.skip("../shared/weights/fastdepth is not present next to the checkout")
    return FASTDEPTH_WEIGHTS


# Synthetic rooms shared between test files. Tests only read them: nothing may write into
# their arrays.


@pytest.fixture(scope="session")
def small_room():
    """12 frames of the synthetic room at 160x120 (synthetic scene and prior tests, video writing)."""
    from recon.synthetic import render_sequence

    return render_sequence(num_frames=12, width=160, height=120, seed=0)


@pytest.fixture(scope="session")
def pose_room():
    """36 frames of the synthetic room at 320x240 and a simulated prior (flow, BA, front end)."""
    from recon.synthetic import render_sequence, simulate_prior

    seq = render_sequence(36, 320, 240, seed=0)
    return seq, simulate_prior(seq.depth, seed=1)


@pytest.fixture(scope="session")
def sfm_room():
    """30 frames of the synthetic room at 320x240 and a simulated prior (SfM and its keyframes)."""
    from recon.synthetic import render_sequence, simulate_prior

    seq = render_sequence(30, 320, 240, seed=0)
    return seq, simulate_prior(seq.depth, seed=1)


@pytest.fixture(scope="session")
def fusion_room():
    """20 frames of the synthetic room at 320x240 (TSDF fusion and export)."""
    from recon.synthetic import render_sequence

    return render_sequence(20, 320, 240, seed=0)


@pytest.fixture(scope="session")
def fused_room(fusion_room):
    """fusion_room fused with automatic parameters, with a point cloud (TSDF fusion and export)."""
    from recon.fusion import FusionOptions, fuse

    room = fusion_room
    return fuse(room.depth, room.rgb, room.poses, room.intrinsics, FusionOptions(point_cloud=True, progress=False))
