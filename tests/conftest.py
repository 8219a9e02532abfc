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


def wall_texture(seed: int = 0, size: int = 512, extent: float = 6.0):
    """A band-limited random texture of a wall: (image (size, size) float32 in [0, 1], metres
    per texel). The wall spans [-extent / 2, extent / 2]^2 in its own x, y; its finest
    detail (~4 cm) is coarser than a pixel's footprint at a few metres, so views of it do
    not alias."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((size, size)).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), 3.0) + 0.5 * cv2.GaussianBlur(noise, (0, 0), 8.0)
    image = (image - image.min()) / (image.max() - image.min())
    return image, extent / size


def render_wall(poses, intrinsics, height: int, width: int, distance: float = 3.0, flat_right: bool = False,
                seed: int = 0):
    """Grey images (N, H, W) float32 in [0, 1] and depth (N, H, W) of a textured wall z = distance
    (world frame) seen from camera-to-world poses. flat_right: the wall's half x > 0 is a
    uniform grey (no texture at all), for textureless-surface tests."""
    import cv2

    texture, texel = wall_texture(seed)
    size = texture.shape[0]
    images, depths = [], []
    for pose in poses:
        depth = plane_depth(pose, intrinsics, height, width, normal=[0.0, 0.0, 1.0], offset=distance)
        fx, fy, cx, cy = intrinsics
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1) * depth[..., None]
        world = rays @ pose[:3, :3].T + pose[:3, 3]
        tx = (world[..., 0] / texel + size / 2).astype(np.float32)
        ty = (world[..., 1] / texel + size / 2).astype(np.float32)
        grey = cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if flat_right:
            grey = np.where(world[..., 0] > 0, np.float32(0.5), grey)
        images.append(grey)
        depths.append(depth)
    return np.stack(images).astype(np.float32), np.stack(depths).astype(np.float32)
