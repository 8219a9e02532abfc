"""Shared fixtures: where ../shared lives, and tiny analytic scenes for geometry tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(autouse=True)
def _two_threads():
    torch.set_num_threads(2)


@pytest.fixture
def shared_dir() -> Path:
    if not (SHARED / "data").is_dir():
        pytest.skip("../shared is not present next to the checkout")
    return SHARED


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def plane_depth(pose: np.ndarray, intrinsics, height: int, width: int, normal, offset) -> np.ndarray:
    """z-depth (H, W) of the world plane normal . X = offset seen from a camera-to-world pose."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    rays_world = rays_cam @ pose[:3, :3].T
    normal = np.asarray(normal, dtype=np.float64)
    t = (offset - pose[:3, 3] @ normal) / (rays_world @ normal)
    return t.astype(np.float32)
