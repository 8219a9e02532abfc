"""The streamed run's depth windows (recon.drivers.stream_depth): how the TSDF volume they
fuse into is sized."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from recon.drivers.stream_depth import _open_volume
from recon.fusion import FusionOptions, auto_max_depth
from recon.synthetic import render_sequence


def test_the_far_clip_reaches_the_first_windows_final_depth():
    """MEDeA stretched the prior's range: the prior's sample times the median ratio ends short
    of the far surface, and the volume's far clip follows the finished depth there instead."""
    room = render_sequence(4, 128, 96, seed=0)
    depth = room.depth.astype(np.float32)
    prior = np.sqrt(depth * np.median(depth[depth > 0])).astype(np.float32)  # the same order, half the range
    video = SimpleNamespace(depth_sample=prior[prior > 0][::7])
    seq = SimpleNamespace(prior_depth=prior, poses=room.poses, intrinsics=room.intrinsics)
    volume = _open_volume(video, depth, depth, seq, FusionOptions(progress=False))
    ratio = np.median(depth[depth > 0] / prior[prior > 0])
    assert auto_max_depth(video.depth_sample * ratio) < 0.95 * auto_max_depth(depth[depth > 0])
    assert volume.max_depth >= 0.99 * auto_max_depth(depth[:, ::4, ::4][depth[:, ::4, ::4] > 0])
    given = _open_volume(video, depth, depth, seq, FusionOptions(progress=False, max_depth=2.0))
    assert given.max_depth == 2.0
