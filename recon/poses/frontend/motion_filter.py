"""The front end's keyframe policy (DROID-SLAM's ``motion_filter``): which tracked frames
become keyframes, judged by how far the image moved and how much of that motion is
parallax (the part that carries depth) rather than rotation.

Pure functions over one flow field and one relative pose.
"""

from __future__ import annotations

import numpy as np
import torch

from recon.geometry import projective as pj
from recon.poses.config import FrontendConfig, Geometry
from recon.poses.matching import flow as fl


def rotation_flow(rel: torch.Tensor, intrinsics, geo: Geometry, shape: tuple[int, int]) -> np.ndarray:
    """(h, w, 2) flow from a keyframe to a frame at relative pose `rel` (keyframe camera ->
    frame camera, (4, 4)) that the rotation alone would cause: the reprojection of points
    at infinity (inverse depth 0), i.e. the infinite homography K R K^-1. intrinsics are
    those of the working frames (geo.shape); shape (h, w) is the flow's."""
    h, w = shape
    height, width = geo.shape
    intr = torch.tensor(pj.scale_intrinsics(intrinsics, w / width, h / height), dtype=torch.float64)
    uv = pj.pixel_grid(h, w)
    at_infinity = pj.backproject(uv, torch.zeros(h, w, dtype=torch.float64), intr)
    moved, _ = pj.project(pj.transform(rel[None], at_infinity[None])[0], intr)
    return (moved - uv).numpy().astype(np.float32)


def motion_and_parallax(flow: np.ndarray, conf: np.ndarray, rel: torch.Tensor, intrinsics, geo: Geometry
                        ) -> tuple[float, float]:
    """Confidence-weighted mean flow and mean parallax flow (flow minus what the rotation of
    `rel` explains), both in working pixels of a 640-px-wide frame."""
    motion = fl.mean_magnitude(flow, conf) * geo.px_scale
    parallax = fl.mean_magnitude(flow - rotation_flow(rel, intrinsics, geo, flow.shape[:2]), conf) * geo.px_scale
    return motion, parallax


def is_keyframe(motion: float, parallax: float, cfg: FrontendConfig) -> bool:
    """A new keyframe once the parallax is large enough to triangulate, or the image has
    moved so far (a rotating camera) that the overlap with the last keyframe runs out."""
    return parallax > cfg.keyframe_flow or motion > cfg.keyframe_max_flow
