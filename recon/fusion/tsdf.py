"""TSDF fusion of metric depth maps into a coloured mesh (Open3D VoxelBlockGrid).

Owns the settings (:class:`FusionOptions`; the automatic voxel, depth range and memory
budget are :mod:`recon.fusion.sizing`'s), the integration loop on CPU or CUDA, marching
cubes and the removal of small fragments. Pixels below ``min_confidence`` are left out;
``confidence_weights`` weigh the rest by confidence.
How each automatic value is chosen: docs/fusion.md#the-volume.
why: docs/decisions.md#the-tsdf-band, docs/decisions.md#which-refined-pixels-are-fused
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import open3d as o3d
import open3d.core as o3c
from tqdm import tqdm

from recon.errors import ReconInputError

from .decimate import within_budget
from .sizing import (
    BYTES_PER_VOXEL,
    VOXEL_PER_DEPTH,
    auto_max_depth,
    auto_voxel_size,
    depth_sample,
    fit_to_budget,
    frame_intrinsics,
)
from .upright import Upright, estimate_upright
from .volume import (  # noqa: F401 (re-exported)
    EXTRACTION_BUDGET_FACTOR,
    TsdfVolume,
    clean_depth,
    remove_fragments,
    triangle_components,
)

log = logging.getLogger(__name__)

# Confidence threshold when none is set: the refinement's reconstructed pixels (whose
# confidence is >= 1/3 by default) and no filled ones (< 0.1, recon.core.refine).
DEFAULT_MIN_CONFIDENCE = 0.1
DEFAULT_WEIGHT_THRESHOLD = 2.0


@dataclass
class FusionOptions:
    """Settings of :func:`fuse`; None means "choose from the data" (module docstring)."""

    voxel_size: float | None = None
    """The voxel's edge in metres (none: voxel_per_depth x the median depth, clamped to 5-50 mm)."""
    voxel_per_depth: float = VOXEL_PER_DEPTH
    """The automatic voxel's edge as a share of the median depth (when voxel_size is none)."""
    trunc: float | None = None
    """The truncation distance in metres (none: trunc_voxels x the voxel)."""
    trunc_voxels: float = 8.0
    """The truncation distance in voxels when trunc is none."""
    max_depth: float | None = None
    """Depth beyond this many metres is ignored (none: a margin over a high percentile of the depth)."""
    weight_threshold: float | None = None
    """The fewest frames that must have observed a voxel to mesh it (none: 1 with given poses and refinement, else 2).

    None is the caller's choice, else DEFAULT_WEIGHT_THRESHOLD (``meshing_weight``); the
    pipeline's: 1 with given poses and the refinement, whose fused pixels each already agree
    with ``mvs.min_consistent`` other views, else 2. Open3D's own
    threshold is strict, weight > t, so t - 0.5 is passed to it; with confidence_weights it
    sums weights, not frames. A surface that would mesh to more than ``max_extracted``
    triangles is meshed at a higher threshold.
    """
    block_resolution: int = 8
    """Voxels per block side: 4, 8, 16 or 32."""
    block_count: int = 80_000
    """The memory budget in voxel blocks (80 000 blocks at resolution 8: about 0.8 GB); the voxel grows to fit."""
    min_fragment_triangles: int = 100
    """Mesh pieces with fewer triangles are dropped (0 keeps all)."""
    min_fragment_fraction: float = 0.005
    """Mesh pieces with a smaller share of the triangles are dropped (0 keeps all)."""
    point_cloud: bool = False
    """Also extract a surface point cloud (point_cloud.ply)."""
    device: str = "cpu"
    """The device of the volume: cpu, cuda, cuda:1, ..."""
    progress: bool = True
    """Show a progress bar over the frames."""
    min_confidence: float | None = None
    """With a confidence map, fuse only pixels of at least this confidence (none: the caller's choice).

    The pipeline's default: 0.1 (reconstructed pixels only) with given poses, 0.01 (also
    filled pixels near evidence) with estimated poses; else DEFAULT_MIN_CONFIDENCE.
    Reconstructed pixels have the share of source views that agree (>= 1/3), filled pixels
    0.1 x the share of reconstructed pixels around them; 0 fuses all.
    """
    confidence_weights: tuple[float, ...] = ()
    """Confidence levels that each add one observation's weight to a fused pixel (empty: every pixel weighs 1).

    min_confidence admits a pixel with weight 1: with (0.1,) and min_confidence 0.02 a
    reconstructed pixel counts twice, a filled one near evidence once, so weight_threshold
    sums weights and not frames (``confidence_weight``).
    """
    max_triangles: int = 1_000_000
    """The mesh's triangle budget: a larger mesh is thinned to 80-100 % of it (0 keeps the full mesh).

    ``decimate.within_budget``: vertex clustering, colours kept.
    """
    max_extracted: int | None = None
    """The most triangles marching cubes may make before the budget thins them (none: 4 x max_triangles; 0: no bound).

    A surface counted above it is meshed at a higher weight threshold, a frame at a time
    (``TsdfVolume.bounded_weight``, with a warning): extraction and the cleanup after it
    hold about 0.25 GB per million triangles.
    """
    metric: bool = True
    """The depth is in metres to be trusted (false: the voxel follows the depth without the absolute bounds).

    The pipeline sets it from report.json's poses.metric_scale.
    """

    @property
    def extraction_bound(self) -> int:
        """The max_extracted in force.

        Returns:
            Triangles: EXTRACTION_BUDGET_FACTOR x max_triangles where none was chosen (0: no bound).
        """
        if self.max_extracted is None:
            return EXTRACTION_BUDGET_FACTOR * int(self.max_triangles)
        return int(self.max_extracted)

    @property
    def meshing_weight(self) -> float:
        """The weight_threshold in force.

        Returns:
            Observations a meshed voxel needs: DEFAULT_WEIGHT_THRESHOLD where none was chosen.
        """
        return DEFAULT_WEIGHT_THRESHOLD if self.weight_threshold is None else float(self.weight_threshold)

    def validate(self) -> None:
        """One-line ReconInputError for values that cannot work (they come from the CLI)."""
        positive = {"voxel_size": self.voxel_size, "trunc": self.trunc, "max_depth": self.max_depth,
                    "voxel_per_depth": self.voxel_per_depth}
        for name, value in positive.items():
            if value is not None and not (np.isfinite(value) and value > 0):
                raise ReconInputError(f"fusion option {name} must be > 0, got {value}")
        if not (self.trunc_voxels >= 1):
            raise ReconInputError(f"fusion option trunc_voxels must be >= 1, got {self.trunc_voxels}")
        if self.weight_threshold is not None and not (self.weight_threshold >= 0):
            raise ReconInputError(f"fusion option weight_threshold must be >= 0, got {self.weight_threshold}")
        if self.block_resolution not in (4, 8, 16, 32):
            raise ReconInputError(f"fusion option block_resolution must be 4, 8, 16 or 32, got {self.block_resolution}")
        if int(self.block_count) < 64:
            raise ReconInputError(f"fusion option block_count must be >= 64, got {self.block_count}")
        if self.min_confidence is not None and not (0 <= self.min_confidence <= 1):
            raise ReconInputError(f"fusion option min_confidence must be in [0, 1], got {self.min_confidence}")
        if not all(0 <= level <= 1 for level in self.confidence_weights):
            raise ReconInputError(f"fusion option confidence_weights must be in [0, 1], got {self.confidence_weights}")
        if self.max_extracted is not None and int(self.max_extracted) < 0:
            raise ReconInputError(f"fusion option max_extracted must be >= 0 (0: no bound), got {self.max_extracted}")
        if int(self.max_triangles) < 0:
            raise ReconInputError(f"fusion option max_triangles must be >= 0 (0: no limit), got {self.max_triangles}")
        if self.min_fragment_triangles < 0 or not (0 <= self.min_fragment_fraction <= 1):
            raise ReconInputError(
                "fusion options min_fragment_triangles must be >= 0 and min_fragment_fraction in [0, 1]"
            )


@dataclass
class FusionResult:
    """Output of :func:`fuse`.

    mesh: legacy TriangleMesh (world coordinates, vertex colours in [0, 1] and normals).
    point_cloud: legacy PointCloud of the zero crossings, or None.
    voxel_size, trunc, max_depth: metres actually used. seconds: wall time of fuse().
    frames_fused: frames integrated (frames with an invalid pose or no valid depth are
    skipped). block_estimate: blocks predicted before integrating; blocks_used: allocated.
    fragments_removed: triangles dropped by fragment removal. triangles_full: the mesh's
    triangles before the budget (FusionOptions.max_triangles) decimated it. upright: the
    rotation that stands the scene upright (:mod:`recon.fusion.upright`), for the GLB and
    the exports. weight_threshold: the observations a meshed voxel needed.
    """

    mesh: o3d.geometry.TriangleMesh
    point_cloud: o3d.geometry.PointCloud | None
    voxel_size: float
    trunc: float
    seconds: float
    max_depth: float = 0.0
    frames_fused: int = 0
    block_estimate: int = 0
    blocks_used: int = 0
    fragments_removed: int = 0
    triangles_full: int = 0
    upright: Upright | None = None
    weight_threshold: float = DEFAULT_WEIGHT_THRESHOLD


# --------------------------------------------------------------------------- devices


def o3d_device(device: str) -> o3c.Device:
    """Open3D device of a torch-style device name.

    Args:
        device: "cpu", "cuda" or "cuda:N" (case and surrounding spaces ignored).

    Returns:
        The Open3D device (CPU:0 or CUDA:N).

    Raises:
        ReconInputError: (one line) the name is malformed, or names a CUDA device that this
            Open3D build cannot use or that is not visible.
    """
    name = str(device).strip().lower()
    kind, _, number = name.partition(":")
    if kind not in ("cpu", "cuda") or (number and not number.isdigit()):
        raise ReconInputError(f"device must be 'cpu' or 'cuda[:N]', got {device!r}")
    index = int(number or 0)
    if kind == "cuda":
        if not o3c.cuda.is_available():
            raise ReconInputError(f"device {device!r}: this Open3D build has no CUDA support or no GPU is visible")
        if index >= o3c.cuda.device_count():
            raise ReconInputError(f"device {device!r}: only {o3c.cuda.device_count()} CUDA device(s) visible")
        return o3c.Device(f"CUDA:{index}")
    return o3c.Device("CPU:0")


def fusion_device(device: str) -> o3c.Device:
    """Where TSDF fusion runs: ``device`` when this Open3D build can use it.

    A CUDA device that only torch can use (pip's Open3D is often built without CUDA) falls
    back to the CPU with a warning, rather than failing after the torch stages have run on
    the GPU.

    Args:
        device: torch-style device name ("cpu", "cuda", "cuda:1").

    Returns:
        The Open3D device.

    Raises:
        ReconInputError: as :func:`o3d_device`.
    """
    if str(device).strip().lower().startswith("cuda") and not o3c.cuda.is_available():
        log.warning("this Open3D build has no CUDA support (or sees no GPU): TSDF fusion runs on the CPU; "
                    "the prior, MEDeA and the refinement still use %s", device)
        return o3c.Device("CPU:0")
    return o3d_device(device)


# --------------------------------------------------------------------------- fusion


def _check_inputs(depth, rgb, poses) -> tuple[int, int, int]:
    n = len(depth)
    if len(poses) != n:
        raise ValueError(f"{len(poses)} poses for {n} depth maps")
    if rgb is not None and len(rgb) != n:
        raise ValueError(f"{len(rgb)} colour images for {n} depth maps")
    if n == 0:
        raise ReconInputError("TSDF fusion: no frames to fuse")
    first = np.asarray(depth[0])
    if first.ndim != 2:
        raise ValueError(f"depth maps must be (H, W), got {first.shape}")
    return n, first.shape[0], first.shape[1]


class ConfidentDepth:
    """Depth maps (N, H, W) with the pixels of confidence below a threshold set to 0, read
    one frame at a time (indexable and sized like the depth it wraps); ``weight(i)`` the
    observations each pixel of frame i counts for (``confidence_weight``)."""

    def __init__(self, depth, confidence, threshold: float, levels: Sequence[float] = ()):
        if len(confidence) != len(depth):
            raise ValueError(f"{len(confidence)} confidence maps for {len(depth)} depth maps")
        self.depth, self.confidence, self.threshold = depth, confidence, float(threshold)
        self.levels = tuple(levels)

    def __len__(self) -> int:
        return len(self.depth)

    def __getitem__(self, i: int) -> np.ndarray:
        d = np.asarray(self.depth[i], dtype=np.float32)
        return np.where(np.asarray(self.confidence[i]) >= self.threshold, d, np.float32(0.0))

    def weight(self, i: int) -> np.ndarray | None:
        """The observations each pixel of frame i counts for (``confidence_weight``).

        Args:
            i: frame index.

        Returns:
            (H, W) uint8 observations, or None when every fused pixel weighs 1.
        """
        return confidence_weight(self.confidence[i], self.threshold, self.levels) if self.levels else None


def confidence_weight(confidence, min_confidence: float, levels: Sequence[float] = ()) -> np.ndarray:
    """Observations each pixel counts for in the TSDF.

    A weighted TSDF average (Curless and Levoy 1996) in whole steps, the steps Open3D
    integrates.

    Args:
        confidence: (H, W) confidence in [0, 1].
        min_confidence: pixels below it count 0 times.
        levels: each level the confidence reaches adds one observation.

    Returns:
        (H, W) uint8: 0 below min_confidence, else 1 plus the number of levels reached.
    """
    confidence = np.asarray(confidence)
    weight = (confidence >= min_confidence).astype(np.uint8)
    for level in levels:
        weight += weight.astype(bool) & (confidence >= level)
    return weight


def volume_size(values: np.ndarray, options: FusionOptions) -> tuple[float, float, float]:
    """Voxel size, truncation and depth limit: the options' values, else chosen from the depth.

    Args:
        values: (M,) valid depth values in metres of the frames (see depth_sample).
        options: voxel_size, trunc, trunc_voxels, max_depth and metric.

    Returns:
        (voxel, trunc, max_depth) in metres (module docstring).
    """
    max_depth = options.max_depth or auto_max_depth(values)
    in_range = values[values <= max_depth]
    median = float(np.median(in_range if in_range.size else values))
    voxel = options.voxel_size or auto_voxel_size(median, options.metric, options.voxel_per_depth)
    return float(voxel), float(options.trunc or options.trunc_voxels * voxel), float(max_depth)


def warn_empty_mesh(volume: TsdfVolume, options: FusionOptions, confidence_used: bool) -> None:
    """Say that fusion meshed nothing, and which settings decide what is meshed.

    Args:
        volume: the fused volume (frames fused, depth limit).
        options: the fusion options named in the warning.
        confidence_used: a confidence map gated the pixels.
    """
    gate = (f"; pixels the refinement confirmed less than --min-confidence {options.min_confidence:g} are not "
            "fused (0 fuses every pixel; camera motion between frames gives the refinement its evidence)"
            if confidence_used and options.min_confidence else "")
    log.warning("TSDF fusion: the mesh is empty (%d frames fused): no surface within --max-depth %.2f m was seen "
                "by the %g frames fusion.weight_threshold asks for%s; mesh.ply and mesh.glb are not written",
                volume.frames_fused, volume.max_depth, options.meshing_weight, gate)


def finished_mesh(volume: TsdfVolume, options: FusionOptions, confidence_used: bool):
    """The mesh and point cloud of a volume whose fusion is done.

    The voxels are freed before the decimation (TsdfVolume.close), which needs most of the
    memory they held.

    Args:
        volume: the fused volume; closed on return.
        options: weight threshold, fragment removal, point_cloud and max_triangles.
        confidence_used: a confidence map gated the pixels (for the empty-mesh warning).

    Returns:
        (mesh within options.max_triangles, point cloud or None, fragment triangles removed,
        triangles before the budget, the weight threshold the mesh was extracted at).
    """
    weight = volume.bounded_weight(options)
    if weight > options.meshing_weight:
        log.warning("TSDF fusion: the surface seen by %g frames would mesh to about %.1f M triangles, over the %.1f M "
                    "that fit in memory (fusion.max_extracted); meshing the surface seen by %g instead "
                    "(fusion.max_extracted=0 meshes it all)", options.meshing_weight,
                    volume.surface_triangles(options.meshing_weight) / 1e6, options.extraction_bound / 1e6, weight)
    mesh, removed = volume.mesh(options, weight)
    full = len(mesh.triangles)
    if full == 0:
        warn_empty_mesh(volume, options, confidence_used)
    cloud = volume.point_cloud(options, weight) if options.point_cloud else None
    volume.close()
    return within_budget(mesh, options.max_triangles), cloud, removed, full, weight


def fuse(depth, rgb, poses, intrinsics, options: FusionOptions | None = None, confidence=None) -> FusionResult:
    """Fuse metric depth maps (and colour) into a mesh by TSDF integration.

    Args:
        depth: (N, H, W) float32 z-depth in metres, 0 = invalid (an array, memmap or list
            of (H, W) arrays: frames are read one at a time).
        rgb: (N, H, W, 3) uint8 colour aligned with depth, or None for an uncoloured mesh.
        poses: (N, 4, 4) camera-to-world (OpenCV axes); frames with non-finite poses skipped.
        intrinsics: (fx, fy, cx, cy) of the depth maps, or (N, 4) per frame.
        options: FusionOptions (defaults: everything automatic, CPU).
        confidence: (N, H, W) in [0, 1] aligned with depth, or None: pixels below
            options.min_confidence are not integrated.

    Returns:
        FusionResult with a legacy TriangleMesh (vertex colours, normals).

    Raises:
        ReconInputError: an option is out of range, the device is unusable, or no frame has
            valid depth and a valid pose.
        ValueError: the inputs' frame counts or shapes disagree.
    """
    options = options or FusionOptions()
    options.validate()
    t0 = time.perf_counter()
    n, h, w = _check_inputs(depth, rgb, poses)
    if confidence is not None:
        threshold = DEFAULT_MIN_CONFIDENCE if options.min_confidence is None else options.min_confidence
        depth = ConfidentDepth(depth, confidence, threshold, options.confidence_weights)
    poses = np.asarray(poses, dtype=np.float64)
    k_all = frame_intrinsics(intrinsics, n)
    device = fusion_device(options.device)
    frames = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if len(frames) < n:
        log.warning("TSDF fusion: skipping %d of %d frames with invalid poses", n - len(frames), n)

    values = depth_sample(depth, frames)
    if values.size == 0:
        raise ReconInputError("TSDF fusion: no frame has valid depth and a valid pose")
    voxel, trunc, max_depth = volume_size(values, options)
    voxel, trunc, estimate = fit_to_budget(
        depth, poses, k_all, voxel, trunc, max_depth, options.block_resolution, int(options.block_count), frames
    )
    # Headroom over the estimate; the hash map still grows by itself if the estimate was low.
    capacity = int(min(options.block_count, max(1024, estimate * 1.3)))
    log.info(
        "TSDF fusion: voxel %.1f mm, trunc %.1f mm, max depth %.2f m, ~%d blocks (%.0f MB)",
        voxel * 1e3, trunc * 1e3, max_depth, estimate,
        capacity * options.block_resolution**3 * BYTES_PER_VOXEL / 1e6,
    )

    volume = TsdfVolume(voxel, trunc, max_depth, capacity, colored=rgb is not None,
                        block_resolution=options.block_resolution, device=device)
    for i in tqdm(frames, desc="TSDF fusion", unit="frame", disable=not options.progress, leave=False):
        volume.integrate(depth[i], poses[i], k_all[i], None if rgb is None else rgb[i],
                         weight=depth.weight(i) if confidence is not None else None)
    mesh, cloud, removed, full, weight = finished_mesh(volume, options, confidence is not None)
    fused, blocks_used = volume.frames_fused, volume.blocks_used
    return FusionResult(
        mesh=mesh,
        point_cloud=cloud,
        voxel_size=float(voxel),
        trunc=float(trunc),
        seconds=time.perf_counter() - t0,
        max_depth=float(max_depth),
        frames_fused=fused,
        block_estimate=estimate,
        blocks_used=blocks_used,
        fragments_removed=removed,
        triangles_full=full,
        upright=estimate_upright(poses, np.asarray(mesh.vertices)),
        weight_threshold=weight,
    )
