"""One global scale of the prior, searched before Stage I: the prior brought to the poses' scale.

MEDeA's grids start at zero (the prior as it is) and its photometric term has a basin only
near the true depths. Poses whose scale is not the prior's (given poses: a tracker's metres,
an SfM model's units) warp every pixel far from its match. With the poses fixed, one factor
on every frame's prior is a 1-D problem: the pairs' photometric term is evaluated on a log
grid of factors and refined around the best, the exhaustive search of plane-sweep stereo
(Collins, CVPR 1996) made once per sequence. The factor is taken only when it explains the
frames clearly better than the prior's own scale (a turning camera leaves the term flat).
why: docs/decisions.md#the-priors-scale-under-given-poses
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import MedeaConfig
from .frames import FrameData
from .geometry import pair_transforms
from .losses import photometric_loss
from .objective import PairBatch, warp_level
from .pairs import stage_pairs


@dataclass(frozen=True)
class GlobalScale:
    """The search's outcome.

    factor: the best factor found (the prior times it explains the frames best); gain: the
    share by which it lowers the pairs' photometric term below the prior's own scale's;
    applied: whether it starts Stage I (gain >= the configured minimum); pairs: the pairs scored.
    """

    factor: float
    gain: float
    applied: bool
    pairs: int

    def to_dict(self) -> dict:
        """The outcome as report.json holds it.

        Returns:
            dict with factor, gain, applied and pairs.
        """
        return {"factor": self.factor, "gain": self.gain, "applied": self.applied, "pairs": self.pairs}


def spread_pairs(pairs: torch.Tensor, count: int) -> torch.Tensor:
    """At most `count` of `pairs` (P, 2), evenly spread over them.

    Args:
        pairs: (P, 2) frame pairs.
        count: the most pairs kept.

    Returns:
        (min(P, count), 2) pairs, in their order.
    """
    if pairs.shape[0] <= count:
        return pairs
    keep = torch.linspace(0, pairs.shape[0] - 1, count).round().long()
    return pairs[keep]


def photometric_at(data: FrameData, batch: PairBatch, log_scale: float, stride: int,
                   min_validity: float, min_overlap: float) -> float:
    """The pairs' mean photometric term with every frame's prior times exp(log_scale).

    Args:
        data: frames at working resolution (see prepare_frames).
        batch: B pairs with their relative transforms.
        log_scale: the one log factor on every frame's prior.
        stride: score every stride-th pixel of view i (phase 0).
        min_validity: as MedeaConfig.min_sample_validity.
        min_overlap: pairs whose view i is covered by j on less than this share are left out.

    Returns:
        The mean over the pairs that overlap; inf when fewer than half of them do (the
        factor moves the views apart: no evidence).
    """
    level = data.image
    grid = torch.full((batch.i.shape[0], 2, 2), float(log_scale), device=level.packed.device)  # a constant field
    lattice = (slice(0, level.size[0], stride), slice(0, level.size[1], stride))
    maps_i, _, warped, _, mask = warp_level(level, batch, grid, grid, min_validity, lattice)
    overlap = mask.flatten(1).float().mean(1)
    overlapping = overlap >= min_overlap
    if int(overlapping.sum()) * 2 < batch.i.shape[0]:
        return math.inf
    return float(photometric_loss(maps_i, warped, mask)[overlapping].mean())


@torch.no_grad()
def search_global_scale(data: FrameData, pairs: torch.Tensor, *, span: float = 16.0, steps_per_octave: int = 4,
                        max_pairs: int = 64, stride: int = 2, min_gain: float = 0.05,
                        min_validity: float = 0.999, min_overlap: float = 0.25) -> GlobalScale:
    """The factor on the prior whose depths make the frame pairs agree best in colour.

    Args:
        data: frames at working resolution with their poses (see prepare_frames).
        pairs: (P, 2) candidate pairs (MEDeA's Stage II pairs: neighbours, which overlap).
        span: factors from 1/span to span are searched.
        steps_per_octave: the coarse grid's candidates per doubling; the fine grid around
            the best has four times as many.
        max_pairs: the most pairs scored, spread over the sequence.
        stride: every stride-th pixel of view i is scored.
        min_gain: the factor is applied only when it lowers the term by this share below
            the prior's own scale's.
        min_validity: as MedeaConfig.min_sample_validity.
        min_overlap: a pair counts at a factor when view i is covered on this share.

    Returns:
        GlobalScale; factor 1 and gain 0 when no pair overlaps at any factor.
    """
    pairs = spread_pairs(pairs, max_pairs).to(data.poses.device)
    if pairs.shape[0] == 0:
        return GlobalScale(1.0, 0.0, False, 0)
    i_to_j, j_to_i = pair_transforms(data.poses, pairs)
    batch = PairBatch(pairs[:, 0], pairs[:, 1], i_to_j, j_to_i)

    def loss(log_scale: float) -> float:
        return photometric_at(data, batch, log_scale, stride, min_validity, min_overlap)

    step = math.log(2.0) / steps_per_octave
    half = int(math.ceil(math.log(span) / step))
    coarse = {k * step: loss(k * step) for k in range(-half, half + 1)}
    best = min(coarse, key=coarse.get)
    fine = {best + k * step / 4: loss(best + k * step / 4) for k in range(-3, 4) if k != 0}
    scores = {**coarse, **fine}
    best = min(scores, key=scores.get)
    own = coarse[0.0]
    if not math.isfinite(scores[best]) or not math.isfinite(own) or own <= 0:
        return GlobalScale(1.0, 0.0, False, int(pairs.shape[0]))
    gain = 1.0 - scores[best] / own
    return GlobalScale(math.exp(best), gain, gain >= min_gain, int(pairs.shape[0]))


def search_configured_scale(data: FrameData, config: MedeaConfig) -> GlobalScale:
    """The search as MEDeA runs it before Stage I: on its Stage II pairs, at its pixel stride and gate.

    Args:
        data: frames at working resolution with their poses (see prepare_frames).
        config: the MedeaConfig (its pairs' levels, pixel_stride, scale_search_min_gain,
            min_sample_validity).

    Returns:
        GlobalScale (see search_global_scale).
    """
    pairs1, _, pairs2 = stage_pairs(data.poses.shape[0], config.stage1_levels, config.stage2_levels)
    # Stage II's neighbours overlap most; a short sequence is all keyframes and has none.
    return search_global_scale(data, pairs2 if pairs2.numel() else pairs1, stride=max(2, config.pixel_stride),
                               min_gain=config.scale_search_min_gain, min_validity=config.min_sample_validity)


__all__ = ["GlobalScale", "photometric_at", "search_configured_scale", "search_global_scale", "spread_pairs"]
