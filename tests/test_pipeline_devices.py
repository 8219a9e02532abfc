"""The same run on the CPU and on CUDA gives the same depth and the same mesh (issue 48).

7-Scenes redkitchen, every 8th of frames 0-399 with its ground-truth poses given, at the
defaults: the refined depth of the two devices differs by at most 1 % (median over the
pixels both keep) and their meshes' F@5cm against the sensor's TSDF mesh by at most 0.01.
Runs where CUDA is present; skips elsewhere. ``benchmarks/device.py --parts agreement``
measures the same on every 4th frame and across machines (``--save-depth``, ``--compare``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: compares the CPU with it")]


def test_cpu_and_cuda_give_the_same_depth_and_mesh(shared_dir, tmp_path):
    pytest.importorskip("open3d")
    from recon.eval.evaluate import evaluate_output
    from recon.pipeline import PipelineConfig, run_pipeline

    kitchen = shared_dir / "data" / "7scenes-redkitchen"
    runs = {}
    for device in ("cpu", "cuda"):
        config = PipelineConfig(input=kitchen, output=tmp_path / device, poses="gt", stride=8, stream="off",
                                device=device, progress=False, rerun="off")
        config.medea.device = device
        result = run_pipeline(config)
        runs[device] = (np.asarray(result.depth, np.float32), evaluate_output(result.output, kitchen))

    (cpu, cpu_eval), (cuda, cuda_eval) = runs["cpu"], runs["cuda"]
    both = (cpu > 0) & (cuda > 0)
    assert both.mean() > 0.5, "the devices keep different pixels"
    assert np.median(np.abs(cuda[both] / cpu[both] - 1.0)) <= 0.01
    assert cpu_eval["mesh"]["fscore"] > 0.3, "the CPU's mesh is not a kitchen: the comparison would say nothing"
    assert abs(cuda_eval["mesh"]["fscore"] - cpu_eval["mesh"]["fscore"]) <= 0.01
