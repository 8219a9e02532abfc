"""Settings of the multi-view stereo refinement (one typed config, recorded in report.json)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class MvsConfig:
    """How :func:`mvs_core.refine_depth` searches, scores and trusts depth."""

    image_scale: float = 0.35
    """The working resolution relative to the input depth (0.35: 224x168 for 640x480)."""
    num_sources: int = 6
    """Neighbouring views matched against each frame, chosen by triangulation angle and overlap.

    :func:`mvs_core.select_sources`.
    """
    min_angle: float = 3.0
    """Degrees: sources whose rays meet the frame's surface at angles from min_angle to max_angle score best.

    Smaller angles triangulate poorly, larger ones change the appearance too much for patch
    matching.
    """
    max_angle: float = 20.0
    """Degrees: the upper end of the best triangulation angles (min_angle)."""
    band: float = 0.4
    """The half-width of the search in log depth around the input depth (0.4: x0.67 to x1.49)."""
    hypotheses: int = 20
    """Depths tried per pixel across the band (sub-sample parabola refinement after)."""
    radius: int = 3
    """The patch radius in working pixels of the normalised cross-correlation (NCC)."""
    keep_best: int = 3
    """The per-hypothesis cost averages this many best sources (occlusion-robust, Kang et al. 2001)."""
    texture_floor: float = 0.005
    """A grey-level standard deviation (0-1) added to every patch's in the NCC.

    Patches flatter than this (walls, sensor noise in the dark) get small NCC magnitudes.
    """
    max_cost: float = 0.7
    """A pixel whose best hypothesis costs more than this (1 - NCC) has no match."""
    consistency_depth: float = 0.02
    """The relative depth difference within which another view agrees."""
    consistency_pixels: float = 1.0
    """The reprojection error (working pixels) within which another view agrees."""
    min_consistent: int = 2
    """Views that must agree with a pixel for it to count as reconstructed (COLMAP's fusion asks for 2 or more)."""
    fill_sigma: float = 6.0
    """The Gaussian sigma (working pixels) that spreads the correction log(refined / input) into unmatched pixels.

    The spread is weighted by confidence.
    """
    min_fill_weight: float = 0.02
    """Pixels whose spread weight is below this keep the input depth unchanged."""
    min_frame_share: float = 0.02
    """A frame whose reconstructed share of pixels is below this is marked as unsupported.

    ``RefineResult.unsupported``: the images could not confirm its depth (near-pure rotation,
    blur, no texture), and the pipeline then fuses its filled depth whole rather than a few
    scattered pixels.
    """
    sparse_frame_share: float = 0.1
    """A frame reconstructed less than this share also fuses its filled pixels near evidence (0: none).

    ``RefineResult.sparse``, ``recon.core.refine.fusion_confidence``: where the images
    confirmed little of a frame (a textureless wall), the depth filled around what they did
    confirm is its only surface.
    """
    chunk: int = 16
    """Reference frames scored per batch in view selection (bounds the memory)."""
    device: str = "cpu"
    """The torch device of the computation."""

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
            "sparse_frame_share": 0 <= self.sparse_frame_share <= 1,
            "chunk": self.chunk >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"MVS setting {name}={getattr(self, name)!r} is out of range")
