"""What ``benchmarks/device.py`` changes in recon's process: a stand-in for open3d where it is
not installed (a GPU machine), the depth TSDF fusion is given recorded for the agreement,
and the experiments it can switch on (``--prior-fixed-batch``).
"""

from __future__ import annotations

import sys
import types
from unittest import mock

import numpy as np
import torch

FUSED: dict = {}  # what the last run gave TSDF fusion: depth as integrated, its options


def record_fusion(fuse):
    """`fuse`, recording the depth it integrates (masked by the confidence as fusion masks it)."""
    def recording(depth, rgb, poses, intrinsics, options, confidence=None):
        depth = np.asarray(depth, np.float32)
        if confidence is not None:
            from recon.fusion.tsdf import DEFAULT_MIN_CONFIDENCE

            threshold = DEFAULT_MIN_CONFIDENCE if options.min_confidence is None else options.min_confidence
            depth = np.where(np.asarray(confidence) >= threshold, depth, np.float32(0.0))
        FUSED.update(depth=depth, poses=np.asarray(poses, np.float64), intrinsics=np.asarray(intrinsics, np.float64),
                     min_confidence=options.min_confidence)
        return fuse(depth, rgb, poses, intrinsics, options)
    return recording


def open3d_available() -> bool:
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


def stand_in_for_open3d() -> None:
    """Lets recon import and run without open3d: fusion gives an empty mesh (the one-shot
    run's fuse, the streamed run's finished volume), export writes nothing. A streamed run
    still integrates its windows, into a stand-in volume that costs nothing and holds nothing."""
    for name in ("open3d", "open3d.core", "trimesh", "rerun"):
        stand_in = mock.MagicMock(name=name)
        stand_in.__version__ = "not installed"
        sys.modules.setdefault(name, stand_in)
    import recon.drivers.oneshot
    import recon.export
    import recon.fusion
    import recon.fusion.tsdf
    import recon.fusion.volume

    empty = types.SimpleNamespace(vertices=np.zeros((0, 3)), triangles=np.zeros((0, 3), np.int64),
                                  vertex_colors=np.zeros((0, 3)))

    def fuse(depth, rgb, poses, intrinsics, options, confidence=None):
        from recon.fusion.upright import estimate_upright

        return recon.fusion.FusionResult(mesh=empty, point_cloud=None, voxel_size=0.0, trunc=0.0, seconds=0.0,
                                         upright=estimate_upright(np.asarray(poses), empty.vertices))

    recon.fusion.fuse = fuse
    recon.fusion.tsdf.finished_mesh = lambda volume, options, confidence_used: (empty, None, 0, 0,
                                                                                options.meshing_weight)
    # A streamed run's volume: made on a stand-in device, and its ray casting (which anchors a
    # window to the surface fused so far) sees nothing, so windows anchor to shared frames.
    recon.fusion.tsdf.o3d_device = lambda device: f"stand-in for {device}"
    recon.fusion.volume.TsdfVolume.render_depth = lambda self, pose, intrinsics, size, min_weight=2.0: np.zeros(
        tuple(int(v) for v in size), np.float32)
    recon.export.export_reconstruction = recon.drivers.oneshot.export_reconstruction = lambda out, **kw: {}


def fixed_prior_batches() -> None:
    """FastDepth's network always given a batch of its full batch size (the frames padded with
    copies of the last, their outputs dropped): the experiment behind ``--prior-fixed-batch``.
    A streamed run with given poses hands the prior 1 to 8 frames a call; on the H200 its
    prior stage took 0.053 s/frame against 0.010 with one batch shape (stop 62)."""
    from recon.priors.fastdepth import FastDepthPrior

    run_network = FastDepthPrior._run

    def padded(self, x: torch.Tensor, taps: tuple[str, ...]):
        n = len(x)
        if n >= self.batch_size:
            return run_network(self, x, taps)
        out, tapped = run_network(self, torch.cat([x, x[-1:].expand(self.batch_size - n, *x.shape[1:])]), taps)
        return out[:n], {k: v[:n] for k, v in tapped.items()}

    FastDepthPrior._run = padded


def set_up(prior_fixed_batch: bool) -> bool:
    """open3d or its stand-in, fusion recorded, the experiments asked for: whether fusion runs."""
    fused = open3d_available()
    if not fused:
        stand_in_for_open3d()
    if prior_fixed_batch:
        fixed_prior_batches()
    import recon.fusion

    recon.fusion.fuse = record_fusion(recon.fusion.fuse)
    return fused
