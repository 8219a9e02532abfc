"""Settings of the multi-view stereo refinement (one typed config, recorded in report.json)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class MvsConfig:
    """How :func:`mvs_core.refine_depth` searches, scores and trusts depth.

    image_scale: working resolution relative to the input depth (0.35: 224x168 for 640x480).
    num_sources: neighbouring views matched against each frame, chosen by triangulation
        angle and overlap (:func:`mvs_core.select_sources`).
    min_angle, max_angle: degrees; sources whose rays meet the frame's surface at angles in
        this range score best (smaller angles triangulate poorly, larger ones change the
        appearance too much for patch matching).
    band: half-width of the search in log depth around the input depth (0.4: x0.67 to x1.49).
    hypotheses: depths tried per pixel across the band (sub-sample parabola refinement after).
    radius: patch radius in working pixels for the normalised cross-correlation (NCC).
    keep_best: the per-hypothesis cost averages this many best sources (occlusion-robust,
        Kang et al. 2001).
    texture_floor: grey-level standard deviation (0-1) added to every patch's in the NCC:
        patches flatter than this (walls, sensor noise in the dark) get small NCC magnitudes.
    max_cost: a pixel whose best hypothesis costs more than this (1 - NCC) has no match.
    consistency_depth: relative depth difference within which another view agrees.
    consistency_pixels: reprojection error (working pixels) within which another view agrees.
    min_consistent: views that must agree with a pixel for it to count as reconstructed
        (COLMAP's fusion asks for 2 or more).
    fill_sigma: Gaussian sigma (working pixels) of the confidence-weighted spread of the
        correction log(refined / input) into pixels without a confident match.
    min_fill_weight: pixels whose spread weight is below this keep the input depth unchanged.
    min_frame_share: a frame whose reconstructed share of pixels is below this is marked as
        unsupported (``RefineResult.unsupported``): the images could not confirm its depth
        (near-pure rotation, blur, no texture), and the pipeline then fuses its filled depth
        whole rather than a few scattered pixels.
    chunk: reference frames scored per batch in view selection (memory bound).
    device: torch device of the computation.
    """

    image_scale: float = 0.35
    num_sources: int = 6
    min_angle: float = 3.0
    max_angle: float = 20.0
    band: float = 0.4
    hypotheses: int = 20
    radius: int = 3
    keep_best: int = 3
    texture_floor: float = 0.005
    max_cost: float = 0.7
    consistency_depth: float = 0.02
    consistency_pixels: float = 1.0
    min_consistent: int = 2
    fill_sigma: float = 6.0
    min_fill_weight: float = 0.02
    min_frame_share: float = 0.02
    chunk: int = 16
    device: str = "cpu"

    def validate(self) -> None:
        """ValueError naming the first setting that cannot work."""
        checks = {
            "image_scale": 0 < self.image_scale <= 1,
            "num_sources": self.num_sources >= 1,
            "min_angle": 0 <= self.min_angle < self.max_angle,
            "band": self.band > 0,
            "hypotheses": self.hypotheses >= 3,
            "radius": self.radius >= 1,
            "keep_best": 1 <= self.keep_best <= self.num_sources,
            "texture_floor": self.texture_floor >= 0,
            "max_cost": 0 < self.max_cost <= 2,
            "consistency_depth": self.consistency_depth > 0,
            "consistency_pixels": self.consistency_pixels > 0,
            "min_consistent": 1 <= self.min_consistent <= self.num_sources,
            "fill_sigma": self.fill_sigma > 0,
            "min_fill_weight": self.min_fill_weight >= 0,
            "min_frame_share": 0 <= self.min_frame_share <= 1,
            "chunk": self.chunk >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"MVS setting {name}={getattr(self, name)!r} is out of range")
