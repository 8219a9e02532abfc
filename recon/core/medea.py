"""The MEDeA stage of the pipeline: numpy frames in, adjusted depth out, with progress
bars. The method itself lives in `medea_core`; this module only adapts arrays and
reports progress.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from medea_core import MedeaConfig, MedeaResult, run_medea
from medea_core.frames import prepare_frames, working_size
from medea_core.global_scale import GlobalScale, search_configured_scale


def _as_tensor(array, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array) if not isinstance(array, torch.Tensor) else array).to(dtype)


def images_at_working_size(rgb, prior_size: tuple[int, int], image_scale: float, chunk: int = 32) -> torch.Tensor:
    """RGB frames (N, H, W, 3) uint8 -> (N, 3, h, w) float in [0, 1] at MEDeA's working size.

    Resizing here, chunk by chunk, keeps full-resolution float copies out of memory.
    """
    size = working_size(*prior_size, image_scale)
    out = []
    for start in range(0, len(rgb), chunk):
        block = torch.as_tensor(np.ascontiguousarray(rgb[start : start + chunk])).permute(0, 3, 1, 2).float() / 255.0
        if tuple(block.shape[-2:]) != size:
            block = F.interpolate(block, size=size, mode="bilinear", antialias=True, align_corners=False)
        out.append(block)
    return torch.cat(out)


class _EpochBars:
    """tqdm bars, one per stage, fed by run_medea's per-epoch callback."""

    def __init__(self, config: MedeaConfig, enabled: bool):
        self.totals = {"stage1": config.stage1.epochs, "stage2": config.stage2.epochs}
        self.enabled = enabled
        self.bars: dict[str, tqdm] = {}

    def __call__(self, stage: str, epoch: int, losses: dict) -> None:
        if not self.enabled:
            return
        if stage not in self.bars:
            for bar in self.bars.values():
                bar.close()
            label = {"stage1": "MEDeA stage I (keyframes)", "stage2": "MEDeA stage II (all frames)"}[stage]
            self.bars[stage] = tqdm(total=self.totals[stage], desc=label, unit="epoch", leave=False)
        bar = self.bars[stage]
        bar.update(1)
        bar.set_postfix(loss=f"{losses['total']:.4f}")

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()


def adjust_sequence(
    rgb,
    prior,
    poses,
    intrinsics,
    features=None,
    config: MedeaConfig | None = None,
    progress: bool = True,
) -> MedeaResult:
    """Run MEDeA on a sequence.

    Args:
        rgb: (N, H', W', 3) uint8 frames (any resolution with the prior's aspect).
        prior: (N, H, W) prior depth in metres, 0 where invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) or (N, 4) fx, fy, cx, cy in pixels of the prior's resolution.
        features: optional (N, C, h, w).
    """
    config = config or MedeaConfig()
    prior_t = _as_tensor(prior)
    images = images_at_working_size(rgb, tuple(prior_t.shape[-2:]), config.image_scale)
    bars = _EpochBars(config, progress)
    try:
        return run_medea(
            images,
            prior_t,
            _as_tensor(poses, torch.float64),
            _as_tensor(intrinsics),
            None if features is None else _as_tensor(features),
            config,
            progress=bars,
        )
    finally:
        bars.close()


def search_prior_scale(rgb, prior, poses, intrinsics, config: MedeaConfig) -> GlobalScale:
    """The factor on the prior that MEDeA's search (medea_core.global_scale) finds on a
    sequence, without running MEDeA: a streamed run chooses its depth frames with it.

    Args:
        rgb: (N, H', W', 3) uint8 frames (any resolution with the prior's aspect).
        prior: (N, H, W) prior depth in metres, 0 where invalid.
        poses: (N, 4, 4) camera-to-world.
        intrinsics: (4,) fx, fy, cx, cy in pixels of the prior's resolution.
        config: the MedeaConfig whose search is run (its pairs, stride and gate).

    Returns:
        GlobalScale.
    """
    prior_t = _as_tensor(prior)
    images = images_at_working_size(rgb, tuple(prior_t.shape[-2:]), config.image_scale)
    data = prepare_frames(images, prior_t, _as_tensor(poses, torch.float64), _as_tensor(intrinsics), None,
                          config.image_scale, torch.device(config.device))
    return search_configured_scale(data, config)
