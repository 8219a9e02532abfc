"""MEDeA's two-stage test-time optimisation (paper, "Test-time Optimization" and
"Implementation details"): Stage I on keyframe pairs, scale propagation, Stage II on
short-range pairs with keyframe grids frozen.

The optimiser is Adam applied lazily per frame (:mod:`medea_core.lazy_adam`, over an
embedding table of grids): a frame's grid and moments change only in steps whose batch
contains it. With one batch per epoch (Stage I on typical lengths) this is exactly Adam; with
several it avoids moving frames on stale momentum from other batches.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable

import torch
import torch.nn.functional as F

from .config import MedeaConfig, StageConfig
from .frames import FrameData, prepare_frames
from .geometry import pair_transforms
from .global_scale import GlobalScale, search_configured_scale
from .grid import adjust_depth
from .lazy_adam import AdamMoments, lazy_adam_step
from .objective import PairBatch, pair_losses, pair_overlap
from .pairs import connects, nearest_keyframe, stage_pairs
from .propagate import propagate_scales

# progress(stage_name, epoch, epoch_losses) is called after every epoch.
ProgressCallback = Callable[[str, int, dict], None]


@dataclass
class StageHistory:
    """Per-epoch mean loss of each term over the stage's pairs; the pairs scored, those left
    out for overlapping too little (Stage I: MedeaConfig.min_pair_overlap), and whether the
    stage was skipped because the pairs left do not connect its keyframes."""

    losses: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    epochs: int = 0
    stopped_early: bool = False
    seconds: float = 0.0
    pairs: int = 0
    pairs_left_out: int = 0
    skipped: bool = False


def overlapping_pairs(data: FrameData, pairs: torch.Tensor, log_scales: torch.Tensor,
                      config: MedeaConfig) -> tuple[torch.Tensor, int]:
    """The pairs whose view i frame j covers at least config.min_pair_overlap at the current depths.

    Args:
        data: frames at working resolution (see prepare_frames).
        pairs: (P, 2) frame pairs (i, j) on the CPU.
        log_scales: (N, h, w) the grids the overlap is measured at.
        config: min_pair_overlap (0 keeps every pair) and min_sample_validity.

    Returns:
        ((P', 2) pairs kept, in their order; the number left out).
    """
    if config.min_pair_overlap <= 0 or pairs.numel() == 0:
        return pairs, 0
    overlap = pair_overlap(data, pairs.to(log_scales.device), log_scales, config.min_sample_validity)
    keep = (overlap >= config.min_pair_overlap).cpu()
    return pairs[keep], int((~keep).sum())


@dataclass
class MedeaResult:
    """depth: (N, H, W) adjusted depth at the prior's resolution (0 where the prior was
    invalid); log_scales: (N, h, w); keyframes: (K,); history per stage; seconds per step;
    global_scale: the search before Stage I (None when config.scale_search is off)."""

    depth: torch.Tensor
    log_scales: torch.Tensor
    keyframes: torch.Tensor
    history: dict[str, StageHistory]
    seconds: dict[str, float]
    global_scale: GlobalScale | None = None


def _grids(table: torch.Tensor, frozen: torch.Tensor, trainable: torch.Tensor, frames: torch.Tensor, grid):
    """Grids (B, h, w) of `frames`: trainable rows via a sparse-gradient lookup."""
    rows = F.embedding(frames, table, sparse=True)
    rows = torch.where(trainable[frames, None], rows, frozen[frames])
    return rows.view(-1, *grid)


def optimise_stage(
    data: FrameData,
    log_scales: torch.Tensor,
    trainable: torch.Tensor,
    pairs: torch.Tensor,
    stage: StageConfig,
    config: MedeaConfig,
    generator: torch.Generator,
    name: str = "stage",
    progress: ProgressCallback | None = None,
) -> tuple[torch.Tensor, StageHistory]:
    """Optimise the grids of `trainable` frames on `pairs`.

    Each epoch visits the pairs in a random order in batches of config.batch_pairs; pairs
    without overlap are left out of the loss. The stage stops early when the epoch loss has
    not improved by stage.min_rel_improvement for stage.patience epochs.

    Args:
        data: frames at working resolution (see prepare_frames).
        log_scales: (N, h, w) starting grids (left untouched; a new tensor is returned).
        trainable: (N,) bool, the frames whose grids are optimised; the others stay fixed.
        pairs: (P, 2) frame pairs (i, j) on the CPU.
        stage: epochs, learning rate, decay and early-stop settings of this stage.
        config: loss terms, weights and batch size.
        generator: CPU generator that shuffles the pairs and draws pixel lattices.
        name: stage name passed to `progress`.
        progress: optional callback progress(name, epoch, epoch_losses) after every epoch.

    Returns:
        (N, h, w) optimised grids and the stage history. With no pairs, no trainable frame
        or no epochs the grids are a copy of log_scales and the history is empty.
    """
    history = StageHistory()
    start = time.perf_counter()
    device = log_scales.device
    num, grid = log_scales.shape[0], tuple(log_scales.shape[1:])
    history.pairs = int(pairs.shape[0])
    if pairs.numel() == 0 or not bool(trainable.any()) or stage.epochs <= 0:
        return log_scales.clone(), history
    pairs_dev = pairs.to(device)
    i_to_j, j_to_i = pair_transforms(data.poses, pairs_dev)
    frozen = log_scales.detach().reshape(num, -1).clone()
    table = frozen.clone().requires_grad_(True)
    trainable = trainable.to(device)
    moments, lr = AdamMoments.zeros_like(table), stage.lr
    best, stall = float("inf"), 0
    for epoch in range(stage.epochs):
        sums: dict[str, float] = defaultdict(float)
        counted = 0
        for chunk in torch.randperm(pairs.shape[0], generator=generator).split(config.batch_pairs):
            chunk = chunk.to(device)
            batch = PairBatch(pairs_dev[chunk, 0], pairs_dev[chunk, 1], i_to_j[chunk], j_to_i[chunk])
            terms = pair_losses(
                data,
                batch,
                _grids(table, frozen, trainable, batch.i, grid),
                _grids(table, frozen, trainable, batch.j, grid),
                config,
                generator,
            )
            overlapping = terms["valid_fraction"] > 0
            if not bool(overlapping.any()):
                continue
            loss = terms["total"][overlapping].mean()
            table.grad = None
            loss.backward()
            lazy_adam_step(table, table.grad, moments, lr, eps=stage.adam_eps)
            counted += int(overlapping.sum())
            for key, value in terms.items():
                sums[key] += float(value.detach()[overlapping].sum())
        if counted == 0:
            break
        lr *= stage.gamma  # the learning rate decays once per epoch
        epoch_losses = {key: value / counted for key, value in sums.items()}
        for key, value in epoch_losses.items():
            history.losses[key].append(value)
        history.epochs = epoch + 1
        if progress is not None:
            progress(name, epoch, epoch_losses)
        current = epoch_losses["total"]
        if epoch == 0 or current < best - stage.min_rel_improvement * abs(best):
            best, stall = current, 0
        else:
            stall += 1
            if stall >= stage.patience:
                history.stopped_early = True
                break
    result = torch.where(trainable[:, None], table.detach(), frozen).view(num, *grid)
    history.losses = dict(history.losses)
    history.seconds = time.perf_counter() - start
    return result, history


def run_medea(
    images: torch.Tensor,
    prior: torch.Tensor,
    poses: torch.Tensor,
    intrinsics: torch.Tensor,
    features: torch.Tensor | None = None,
    config: MedeaConfig | None = None,
    progress: ProgressCallback | None = None,
) -> MedeaResult:
    """Adjust prior depth maps to be consistent across views.

    Args:
        images: (N, 3, H', W') RGB in [0, 1]; any resolution with the prior's aspect
            (passing them already at the working resolution saves memory).
        prior: (N, H, W) prior depth in metres; 0 or NaN where invalid.
        poses: (N, 4, 4) camera-to-world, metres.
        intrinsics: (N, 4) or (4,) fx, fy, cx, cy in pixels of the prior's resolution.
        features: optional (N, C, h, w) dense features for the feature-metric term.
        config: options; the defaults are the paper's.
        progress: optional per-epoch callback.

    Returns:
        MedeaResult with depth (N, H, W) in metres at the prior's resolution (0 where the
        prior was invalid), on the prior's device.

    Raises:
        ValueError: a setting of config is out of range, there are no frames, or images,
            prior, poses and features differ in frame count.
    """
    config = config or MedeaConfig()
    config.validate()
    num = prior.shape[0]
    if num == 0:
        raise ValueError("run_medea: no frames")
    if images.shape[0] != num or poses.shape[0] != num or (features is not None and features.shape[0] != num):
        raise ValueError("run_medea: images, prior, poses and features must have the same number of frames")
    device = torch.device(config.device)
    generator = torch.Generator().manual_seed(config.seed)
    seconds: dict[str, float] = {}

    start = time.perf_counter()
    # Unused features are not prepared: for many channels they are most of the memory.
    features = features if config.use_features else None
    data = prepare_frames(images, prior, poses, intrinsics, features, config.image_scale, device,
                          config.feature_channels)
    grid = config.grid_for(*prior.shape[-2:])
    log_scales = torch.zeros((num, *grid), device=device)
    pairs1, keyframes, pairs2 = stage_pairs(num, config.stage1_levels, config.stage2_levels)
    is_key = torch.zeros(num, dtype=torch.bool)
    is_key[keyframes] = True
    seconds["prepare"] = time.perf_counter() - start

    global_scale = None
    if config.scale_search:
        start = time.perf_counter()
        global_scale = search_configured_scale(data, config)
        if global_scale.applied:
            log_scales += math.log(global_scale.factor)
        seconds["scale_search"] = time.perf_counter() - start

    history: dict[str, StageHistory] = {}
    run_stage1 = config.run_stage1
    if run_stage1:
        # Keyframes far apart can share almost nothing: such pairs only pull the depths.
        # Stage I fixes the keyframes' scale relative to each other, which needs pairs that
        # join them all; where the overlapping pairs do not, every frame goes to Stage II.
        pairs1, left_out = overlapping_pairs(data, pairs1, log_scales, config)
        if connects(pairs1, keyframes):
            log_scales, history["stage1"] = optimise_stage(
                data, log_scales, is_key, pairs1, config.stage1, config, generator, "stage1", progress
            )
        else:
            run_stage1 = False
            history["stage1"] = StageHistory(pairs=int(pairs1.shape[0]), skipped=True)
            if pairs2.numel() == 0:  # a short sequence: every frame was a keyframe
                pairs2 = pairs1
        history["stage1"].pairs_left_out = left_out
    seconds["stage1"] = history["stage1"].seconds if "stage1" in history else 0.0

    start = time.perf_counter()
    others = torch.nonzero(~is_key).flatten()
    if run_stage1 and config.propagate_scale and others.numel() > 0:
        sources = nearest_keyframe(num, keyframes)[others]
        log_scales[others.to(device)] = propagate_scales(
            data, log_scales, others, sources, config.batch_pairs, config.min_sample_validity
        )
    seconds["propagate"] = time.perf_counter() - start

    if config.run_stage2:
        # Without Stage I there is nothing to freeze: every frame is optimised.
        trainable = ~is_key if run_stage1 else torch.ones(num, dtype=torch.bool)
        log_scales, history["stage2"] = optimise_stage(
            data, log_scales, trainable, pairs2, config.stage2, config, generator, "stage2", progress
        )
    seconds["stage2"] = history["stage2"].seconds if "stage2" in history else 0.0

    out_device = prior.device
    depth = adjust_depth(torch.nan_to_num(prior.float(), nan=0.0).clamp(min=0), log_scales.to(out_device))
    return MedeaResult(depth=depth, log_scales=log_scales.to(out_device), keyframes=keyframes, history=history,
                       seconds=seconds, global_scale=global_scale)
