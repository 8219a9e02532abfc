"""Do given poses agree with the frames? The epipolar check of neighbouring frames.

Under poses (R, t) of two frames every pixel x_a must land on its epipolar line F x_a,
F = K^-T [t]x R K^-1 (Hartley and Zisserman, "Multiple View Geometry", ch. 9), whatever its
depth. The dense flow between neighbouring frames (``recon.poses.matching.flow``) says where
it lands; the distance from that line is the poses' error, depth-free.
:func:`check_given_poses` takes the median over the confident flow of up to ``max_pairs``
pairs spread over the run; pairs with mostly unconfident flow are not judged, and with too
few judged pairs there is no verdict. More: docs/poses.md#given-poses
why: docs/decisions.md#the-gate-on-given-poses
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from recon.geometry.camera import scale_intrinsics
from recon.poses.matching import flow as fl


@dataclass(frozen=True)
class PoseCheckConfig:
    """max_pairs: neighbouring pairs (consecutive frames of the run) judged, spread over it.
    flow_stride: the flow runs at 1/flow_stride of the working resolution (as the front
    end's). min_confident: the share of a pair's pixels whose flow must be confident
    (forward-backward, ``flow.fb_confidence`` > 1/2) for the pair to be judged. min_pairs:
    fewer judged pairs give no verdict. max_median_px: the poses contradict the frames when
    the median epipolar distance exceeds this many pixels of a 640 px wide frame. flow:
    the DIS settings."""

    max_pairs: int = 16
    flow_stride: int = 4
    min_confident: float = 0.6
    min_pairs: int = 4
    max_median_px: float = 0.8
    flow: fl.FlowConfig = field(default_factory=fl.FlowConfig)


def fundamental_matrix(pose_a: np.ndarray, pose_b: np.ndarray, intrinsics) -> np.ndarray:
    """(3, 3) F with x_b^T F x_a = 0 for camera-to-world poses (4, 4) of frames a and b and
    intrinsics (fx, fy, cx, cy) in the pixels x are measured in."""
    fx, fy, cx, cy = intrinsics
    K_inv = np.linalg.inv(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    relative = np.linalg.inv(pose_b) @ pose_a  # frame a's camera coordinates -> frame b's
    R, t = relative[:3, :3], relative[:3, 3]
    t_cross = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return K_inv.T @ t_cross @ R @ K_inv


def epipolar_distance(flow: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(H, W) distance (pixels) of every pixel's flow end point (flow (H, W, 2)) from the
    epipolar line F gives it."""
    height, width = flow.shape[:2]
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    start = np.stack([u, v, np.ones_like(u)], -1)
    end = start.copy()
    end[..., :2] += flow
    lines = start @ F.T
    return np.abs((end * lines).sum(-1)) / np.maximum(np.hypot(lines[..., 0], lines[..., 1]), 1e-12)


@dataclass
class PoseCheck:
    """median_px: the median epipolar distance over the judged pairs' confident flow, in
    pixels of a 640 px wide frame (None: nothing judged); pairs, judged: pairs measured and
    those whose flow was confident enough to count; disagreement: why multi-view depth
    should not trust the poses (None: it may, or there is no verdict); seconds."""

    median_px: float | None
    pairs: int
    judged: int
    disagreement: str | None
    seconds: float
    config: dict

    def to_dict(self) -> dict:
        return asdict(self)


def check_given_poses(frames: np.ndarray, poses: np.ndarray, intrinsics,
                      config: PoseCheckConfig | None = None) -> PoseCheck:
    """The epipolar check (module docstring) of poses (N, 4, 4) camera-to-world against
    frames (N, H, W, 3) uint8 in their order; intrinsics (fx, fy, cx, cy) in frame pixels
    of a pinhole camera. Pairs with a non-finite pose are skipped."""
    cfg = config or PoseCheckConfig()
    t0 = time.perf_counter()
    height, width = frames.shape[1:3]
    shape = (max(8, height // cfg.flow_stride), max(8, width // cfg.flow_stride))
    flow_intrinsics = scale_intrinsics(intrinsics, shape[1] / width, shape[0] / height)
    valid = np.isfinite(poses).all(axis=(1, 2))
    starts = [a for a in range(len(frames) - 1) if valid[a] and valid[a + 1]]
    if len(starts) > cfg.max_pairs:
        starts = [starts[k] for k in np.linspace(0, len(starts) - 1, cfg.max_pairs).round().astype(int)]
    # Distances in pixels of a 640 px wide frame, like the front end's flow thresholds.
    to_640 = (width / shape[1]) * (640.0 / width)
    distances, judged = [], 0
    for a in starts:
        fwd, _, conf, _ = fl.flow_pair(fl.prepare_gray(frames[a], shape), fl.prepare_gray(frames[a + 1], shape),
                                       cfg.flow)
        confident = conf > 0.5
        if confident.mean() < cfg.min_confident:
            continue
        judged += 1
        F = fundamental_matrix(poses[a], poses[a + 1], flow_intrinsics)
        distances.append(epipolar_distance(fwd, F)[confident] * to_640)
    median = float(np.median(np.concatenate(distances))) if judged >= cfg.min_pairs else None
    disagreement = None
    if median is not None and median > cfg.max_median_px:
        disagreement = (f"the flow between neighbouring frames misses the epipolar lines of the given poses by "
                        f"{median:.2f} px (median over {judged} pairs; poses that agree with the frames miss them by "
                        f"under {cfg.max_median_px:g} px)")
    return PoseCheck(median, len(starts), judged, disagreement, time.perf_counter() - t0,
                     {k: v for k, v in asdict(cfg).items() if k != "flow"})


__all__ = ["PoseCheck", "PoseCheckConfig", "check_given_poses", "epipolar_distance", "fundamental_matrix"]
