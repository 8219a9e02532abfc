"""The one typed configuration of MEDeA; every default is the paper's value.

Paper: Artemyev et al., "MEDeA: Multi-view Efficient Depth Adjustment", ICIP 2024,
section "Implementation details". Fields that the paper does not fix (numerical
epsilons, the short-sequence fallback, the device) are documented where they live.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from operator import attrgetter
from typing import Literal


@dataclass
class StageConfig:
    """Optimiser schedule of one stage (Adam with exponential learning-rate decay)."""

    epochs: int
    """The most epochs of the stage (it stops earlier when the loss stops falling)."""
    gamma: float
    """The learning rate's decay per epoch."""
    patience: int
    """Epochs without enough improvement (min_rel_improvement) before the stage stops."""
    lr: float = 0.1
    """Adam's learning rate."""
    min_rel_improvement: float = 0.01
    """The fraction of the best loss so far an epoch must gain to count as improvement.

    The paper's "1% throughout 40 epochs".
    """
    adam_eps: float = 1e-8
    """Adam's epsilon (torch's default; the paper does not give one).

    A larger one damps the grid cells the data barely constrains.
    why: docs/decisions.md#medea-on-cpu-and-cuda
    """

    def checks(self) -> dict[str, bool]:
        """Each setting's name -> whether its value can work.

        Returns:
            dict of setting name -> True when its value is in range.
        """
        return {"epochs": self.epochs >= 0, "gamma": 0 < self.gamma <= 1, "patience": self.patience >= 1,
                "lr": self.lr > 0, "min_rel_improvement": self.min_rel_improvement >= 0, "adam_eps": self.adam_eps > 0}


@dataclass
class MedeaConfig:
    """All MEDeA options. Defaults reproduce the paper (MEDeA-S with feature loss S)."""

    grid_size: tuple[int, int] = (8, 10)
    """The log-scale deformation grid (h, w) of a landscape frame; portrait frames use the transpose."""
    image_scale: float = 0.25
    """The working resolution of images, priors and features relative to the input."""
    batch_pairs: int = 128
    """Frame pairs per optimiser step."""
    pixel_stride: int = 1
    """Score every k-th pixel of view i per step, at a random phase (1: every pixel, the paper's).

    Frame j is still sampled at full resolution. A speed knob: the 8x10 grid is estimated
    from far more pixels than it needs.
    """
    feature_stride: int = 1
    """The same as pixel_stride for the feature term, on the features' own grid."""
    feature_channels: int | None = None
    """Keep only this many feature channels, those of largest variance over the sequence (none: all, the paper's).

    Warping cost grows with the channel count, and pruned or near-constant channels carry no
    matching signal.
    """
    stage1: StageConfig = field(default_factory=lambda: StageConfig(epochs=600, gamma=0.996, patience=40))
    """Stage I's schedule (keyframes)."""
    stage2: StageConfig = field(default_factory=lambda: StageConfig(epochs=60, gamma=0.96, patience=4))
    """Stage II's schedule (all frames)."""
    stage1_levels: tuple[int, int] = (3, 6)
    """The Pairs(a, b) levels of Stage I: keyframe pairs Pairs(3, 6)."""
    stage2_levels: tuple[int, int] = (0, 2)
    """The Pairs(a, b) levels of Stage II: Pairs(0, 2)."""
    run_stage1: bool = True
    """Run Stage I (false: Stage II optimises every frame from scale 1)."""
    run_stage2: bool = True
    """Run Stage II."""
    propagate_scale: bool = True
    """Start the non-keyframe grids of Stage II from the nearest keyframe's (false: from scale 1)."""
    use_photometric: bool = True
    """Use the photometric loss."""
    use_depth: bool = True
    """Use the depth consistency loss."""
    use_features: bool = True
    """Use the feature-metric loss (only when features are given)."""
    depth_loss: Literal["metres", "relative"] = "metres"
    """The depth term: metres, |D_i - D_j->i| (the paper's), or relative, that divided by D_i + D_j->i (scale-free)."""
    feature_loss: Literal["S", "M"] = "S"
    """The feature loss: S, |Fi - Fj->i| / |Fi + Fj->i| (MEDeA-S), or M, the negative mean dot product (MEDeA-M)."""
    photometric_weight: float = 1.0
    """The photometric loss's weight (the paper sums the terms unweighted)."""
    depth_weight: float = 1.0
    """The depth consistency loss's weight."""
    feature_weight: float = 1.0
    """The feature-metric loss's weight."""
    seed: int = 0
    """The random seed (pair batches, pixel phases)."""
    device: str = "cpu"
    """The torch device of the optimisation."""
    feature_eps: float = 0.01
    """Added to the S-form's denominator |Fi + Fj->i| (the paper has none).

    The features are ReLU outputs, often 0, and where both sides are near 0 the bare ratio
    and its gradient jump. why: docs/decisions.md#medea-on-cpu-and-cuda
    """
    min_sample_validity: float = 0.999
    """A warped pixel counts only if this share of its bilinear footprint lies on valid depth in frame j."""
    min_pair_overlap: float = 0.0
    """A Stage I pair is scored only if frame j covers this share of view i (0: every pair, the paper's).

    The share is measured once, at the depths Stage I starts from. Keyframes far apart in
    time can share almost nothing; such a pair has no evidence for the depths, only a pull.
    When the pairs left do not join every keyframe, Stage I is skipped and Stage II
    optimises every frame.
    why: docs/decisions.md#keyframe-pairs-that-overlap-little
    """
    scale_search: bool = False
    """Search one factor on every frame's prior before Stage I (off: the paper's start, the prior as it is).

    For poses whose scale is not the prior's (given poses): :mod:`medea_core.global_scale`.
    why: docs/decisions.md#the-priors-scale-under-given-poses
    """
    scale_search_min_gain: float = 0.05
    """The searched factor starts Stage I only when it lowers the pairs' photometric term by this share."""

    @classmethod
    def fast(cls, **overrides) -> "MedeaConfig":
        """Our faster preset: the paper's defaults with these changes.

        - pixel_stride 2: each step scores a quarter of view i's pixels (random phase);
        - Stage II learning rate 0.01 (paper 0.1): Stage II refines the propagated scale
          instead of throwing it away, and stops early;
        - Stage I at most 150 epochs (paper 600);
        - the 96 most varying feature channels (FastDepth gives 207).

        why: docs/decisions.md#the-fast-preset

        Args:
            **overrides: fields set after the preset (name=value).

        Returns:
            The preset configuration.
        """
        config = cls(pixel_stride=2, feature_stride=2, feature_channels=96)
        config.stage1.epochs = 150
        config.stage2.lr = 0.01
        for key, value in overrides.items():
            setattr(config, key, value)
        return config

    def validate(self) -> None:
        """ValueError naming the first setting that cannot work."""
        levels = lambda pair: len(pair) == 2 and 0 <= pair[0] <= pair[1]  # noqa: E731
        checks = {
            "grid_size": len(self.grid_size) == 2 and min(self.grid_size) >= 1,
            "image_scale": 0 < self.image_scale <= 1,
            "batch_pairs": self.batch_pairs >= 1,
            "pixel_stride": self.pixel_stride >= 1,
            "feature_stride": self.feature_stride >= 1,
            "feature_channels": self.feature_channels is None or self.feature_channels >= 1,
            "stage1_levels": levels(self.stage1_levels),
            "stage2_levels": levels(self.stage2_levels),
            "feature_loss": self.feature_loss in ("S", "M"),
            "depth_loss": self.depth_loss in ("metres", "relative"),
            "photometric_weight": self.photometric_weight >= 0,
            "depth_weight": self.depth_weight >= 0,
            "feature_weight": self.feature_weight >= 0,
            "feature_eps": self.feature_eps >= 0,
            "min_sample_validity": 0 <= self.min_sample_validity <= 1,
            "min_pair_overlap": 0 <= self.min_pair_overlap < 1,
            "scale_search_min_gain": 0 <= self.scale_search_min_gain < 1,
        }
        for stage in ("stage1", "stage2"):
            checks.update({f"{stage}.{name}": ok for name, ok in getattr(self, stage).checks().items()})
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"MEDeA setting {name}={attrgetter(name)(self)!r} is out of range")

    def grid_for(self, height: int, width: int) -> tuple[int, int]:
        """The grid (h, w) for a frame of this size: (8, 10) landscape, (10, 8) portrait.

        Args:
            height: frame height in pixels.
            width: frame width in pixels.

        Returns:
            (h, w) grid cells.
        """
        h, w = sorted(self.grid_size)
        return (w, h) if height > width else (h, w)

    def to_dict(self) -> dict:
        """The configuration as nested plain values (report.json's ``options.medea``).

        Returns:
            dict of field name -> value, nested configs as dicts.
        """
        return asdict(self)
