"""The SfM fallback: COLMAP (via pycolmap) on keyframes, dense registration of the other
frames, metric scale from the depth prior.

This module owns the pycolmap pipeline: every k-th frame is written to a temporary folder,
SIFT features are extracted (one shared camera: SIMPLE_RADIAL, so that COLMAP's BA
estimates the lens' radial term k1 as the front end does; the focal length is held when
given and refined when unknown; PINHOLE without a lens term when given intrinsics have
fx != fy, which SIMPLE_RADIAL cannot hold), matched sequentially
(with vocabulary-tree loop detection when a tree file is given: none ships with pycolmap
and nothing is downloaded), and mapped incrementally (or globally, GLOMAP, when asked). The
largest model is kept. Its scale is fixed to metres by the robust median ratio of prior
depth to the SfM depth of the triangulated points seen in each image (a log-mean over
images). The remaining frames (and keyframes the mapper left out) are registered by the
front end's motion-only dense alignment (``frontend.align_to_keyframes``) against the
neighbouring registered keyframes, whose dense depth is the prior corrected by that
keyframe's own prior / SfM depth ratios on a coarse grid.
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from recon.errors import ReconInputError
from recon.poses import flow as fl
from recon.poses.frontend import FrontendConfig, align_to_keyframes, make_geometry
from recon.poses.result import (
    PoseResult,
    PriorSource,
    TrackingLostError,
    invert_poses,
    iterate_frames,
    parse_intrinsics,
    pool_depth,
    robust_log_mean,
)

log = logging.getLogger(__name__)


@dataclass
class SfMConfig:
    """SfM fallback settings.

    max_keyframes: at most this many frames go to COLMAP (every k-th frame, k chosen so),
        which bounds the time; the rest are registered densely.
    keyframe_stride: force k (None: from max_keyframes).
    max_num_features: SIFT features per image.
    overlap: sequential matching links each keyframe to the next `overlap` ones.
    vocab_tree_path: a COLMAP vocabulary tree file enabling loop detection (none by default:
        pycolmap would download one, and nothing may be downloaded at run time).
    mapper: "incremental" (COLMAP) or "global" (GLOMAP).
    min_registered: fraction of keyframes the model must register, else SfM fails.
    num_threads: threads for feature extraction, matching and mapping.
    correction_grid: (rows, cols) of the per-keyframe prior correction from SfM points
        (the keyframe depth used to register the other frames).
    calibrate_lens: estimate the radial term k1 in COLMAP's bundle adjustment (reported as
        ``lens_k1``, used to register the other frames and by the pipeline to undistort).
    frontend: flow / alignment settings used to register the remaining frames.
    """

    max_keyframes: int = 100
    keyframe_stride: int | None = None
    max_num_features: int = 4096
    overlap: int = 10
    vocab_tree_path: str | None = None
    mapper: str = "incremental"
    min_registered: float = 0.5
    num_threads: int = 2
    correction_grid: tuple[int, int] = (3, 4)
    calibrate_lens: bool = True
    frontend: FrontendConfig = field(default_factory=FrontendConfig)


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as err:  # pragma: no cover - pycolmap is a dev dependency
        raise ReconInputError("the SfM fallback needs pycolmap (pip install pycolmap)") from err
    return pycolmap


def _run_colmap(frames: list[np.ndarray], kf_ids: list[int], intrinsics, cfg: SfMConfig, workdir: Path):
    """Run extraction, matching and mapping; returns the largest reconstruction (or None)."""
    pycolmap = _import_pycolmap()
    level = pycolmap.logging.minloglevel
    # COLMAP's INFO lines would flood the console, and so would its warnings: Ceres reports
    # every rejected LM step (hundreds on a rotating camera once the lens term is refined).
    # Its errors ("Failed to create any sparse model") are failures we report ourselves, in
    # one line with what to do, so only fatal ones get through.
    pycolmap.logging.minloglevel = max(level, 3)
    try:
        return _colmap_pipeline(pycolmap, frames, kf_ids, intrinsics, cfg, workdir)
    finally:
        pycolmap.logging.minloglevel = level


def _colmap_pipeline(pycolmap, frames, kf_ids, intrinsics, cfg: SfMConfig, workdir: Path):
    image_dir = workdir / "images"
    image_dir.mkdir()
    names = []
    for i in kf_ids:
        name = f"{i:06d}.png"
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR))
        names.append(name)
    height, width = frames[0].shape[:2]
    db = workdir / "database.db"
    reader = pycolmap.ImageReaderOptions()
    lens = cfg.calibrate_lens
    if intrinsics is not None:
        # COLMAP puts pixel centres at +0.5, recon at integers.
        fx, fy, cx, cy = intrinsics
        lens = lens and abs(fx - fy) <= 1e-3 * fx
        params = (fx, cx + 0.5, cy + 0.5, 0.0) if lens else (fx, fy, cx + 0.5, cy + 0.5)
        reader.camera_model = "SIMPLE_RADIAL" if lens else "PINHOLE"
        reader.camera_params = ",".join(f"{v:.6f}" for v in params)
    else:
        reader.camera_model = "SIMPLE_RADIAL" if lens else "SIMPLE_PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = cfg.num_threads
    extraction.max_image_size = max(width, height)
    extraction.sift.max_num_features = cfg.max_num_features
    pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = cfg.overlap
    pairing.num_threads = cfg.num_threads
    if cfg.vocab_tree_path:
        if not Path(cfg.vocab_tree_path).is_file():
            raise ReconInputError(f"{cfg.vocab_tree_path}: vocabulary tree file not found")
        pairing.loop_detection = True
        pairing.vocab_tree_path = str(cfg.vocab_tree_path)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    out = workdir / "sparse"
    out.mkdir()
    if cfg.mapper == "global":
        models = pycolmap.global_mapping(db, image_dir, out)
    elif cfg.mapper == "incremental":
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = cfg.num_threads
        opts.ba_refine_focal_length = intrinsics is None
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = lens
        models = pycolmap.incremental_mapping(db, image_dir, out, opts)
    else:
        raise ReconInputError(f"SfM mapper must be 'incremental' or 'global', got {cfg.mapper!r}")
    if not models:
        return None
    return max(models.values(), key=lambda r: r.num_reg_images())


def _model_poses(rec) -> tuple[dict[int, np.ndarray], tuple[float, float, float, float], float]:
    """World-to-camera 4x4 poses {frame index: T_cw}, the camera's (fx, fy, cx, cy) and its
    radial term k1 (0 for the pinhole models; SIMPLE_RADIAL's k is OpenCV's k1, as
    ``projective.undistort``)."""
    poses = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        T = np.eye(4)
        T[:3] = image.cam_from_world().matrix()
        poses[int(Path(image.name).stem)] = T
    cam = next(iter(rec.cameras.values()))
    p = np.asarray(cam.params, dtype=np.float64)
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if cam.model.name.startswith("SIMPLE") else (p[0], p[1], p[2], p[3])
    k1 = float(p[3]) if cam.model.name == "SIMPLE_RADIAL" else 0.0
    return poses, (float(fx), float(fy), float(cx) - 0.5, float(cy) - 0.5), k1


def _depth_ratios(rec, prior: PriorSource, frames: list[np.ndarray], grid: tuple[int, int]
                  ) -> dict[int, tuple[float, np.ndarray]]:
    """Per registered image: the median ratio prior depth / SfM depth over its triangulated
    points, and the same median per cell of a coarse (rows, cols) grid over the image (the
    image median where a cell has fewer than 5 points). Network depth errors are mostly
    smooth, so the grid corrects the prior's shape as well as its scale."""
    out = {}
    rows, cols = grid
    for image in rec.images.values():
        if not image.has_pose:
            continue
        i = int(Path(image.name).stem)
        pts = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in image.points2D if p.has_point3D()]
        if len(pts) < 10:
            continue
        xy = np.array([a for a, _ in pts])
        xyz = np.array([b for _, b in pts])
        T = image.cam_from_world().matrix()
        z = xyz @ T[:, :3].T + T[:, 3]
        depth = prior.get(i, frames[i])
        height, width = frames[i].shape[:2]
        # COLMAP pixel coordinates start at the image corner: floor() gives the pixel.
        u = np.clip((xy[:, 0] * depth.shape[1] / width).astype(int), 0, depth.shape[1] - 1)
        v = np.clip((xy[:, 1] * depth.shape[0] / height).astype(int), 0, depth.shape[0] - 1)
        d = depth[v, u]
        ok = (d > 0) & (z[:, 2] > 1e-6)
        if ok.sum() < 10:
            continue
        ratio = d[ok] / z[ok, 2]
        total = float(np.median(ratio))
        cell = (v[ok] * rows // depth.shape[0]) * cols + (u[ok] * cols // depth.shape[1])
        cells = np.full(rows * cols, total)
        for c in range(rows * cols):
            if (cell == c).sum() >= 5:
                cells[c] = np.median(ratio[cell == c])
        out[i] = (total, cells.reshape(rows, cols))
    return out


def _corrected_disp(depth: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Inverse depth (h, w) in SfM units of a pooled prior depth (h, w) and its per-cell
    ratios (rows, cols) prior / SfM depth (bilinear between cell centres)."""
    h, w = depth.shape
    ratio = np.exp(cv2.resize(np.log(cells).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR))
    fill = np.median(depth[depth > 0])
    return ratio / np.where(depth > 0, depth, fill)


def estimate_poses_sfm(frames, prior_depth, intrinsics=None, progress: bool = True,
                       config: SfMConfig | None = None) -> PoseResult:
    """Metric camera-to-world poses of every frame by COLMAP SfM on keyframes.

    Same inputs as ``frontend.estimate_poses_frontend``. diagnostics: method "sfm",
    keyframe stride, registered keyframes, model points, mean reprojection error, the metric
    scale factor and its spread over images, per-frame status ("sfm", "aligned",
    "interpolated"). Raises TrackingLostError when COLMAP registers too few keyframes.
    """
    cfg = config or SfMConfig()
    t0 = time.perf_counter()
    frames_list = [f for _, f in iterate_frames(frames)]
    n = len(frames_list)
    if n < 2:
        raise ReconInputError(f"SfM needs at least 2 frames, got {n}")
    prior = PriorSource(prior_depth)
    if not prior.is_callable and len(prior) != n:
        raise ReconInputError(f"prior depth has {len(prior)} frames but the video has {n}")
    intr_in = parse_intrinsics(intrinsics)
    stride = cfg.keyframe_stride or max(1, int(np.ceil(n / cfg.max_keyframes)))
    kf_ids = list(range(0, n, stride))
    if kf_ids[-1] != n - 1:
        kf_ids.append(n - 1)
    with tempfile.TemporaryDirectory(prefix="recon-sfm-") as tmp:
        if progress:
            print(f"recon: SfM (pycolmap) on {len(kf_ids)} keyframes of {n} frames")
        rec = _run_colmap(frames_list, kf_ids, intr_in, cfg, Path(tmp))
    registered = 0 if rec is None else rec.num_reg_images()
    if registered < max(2, cfg.min_registered * len(kf_ids)):
        raise TrackingLostError(
            f"SfM registered only {registered} of {len(kf_ids)} keyframes (need {cfg.min_registered:.0%}); "
            "the video may lack texture or overlap", frame=None)
    T_model, intr, k1 = _model_poses(rec)
    ratios = _depth_ratios(rec, prior, frames_list, cfg.correction_grid)
    if not ratios:
        raise TrackingLostError("SfM: no triangulated point has a valid prior depth; cannot fix the metric scale")
    scale = robust_log_mean(np.array([r for r, _ in ratios.values()]))

    # Dense registration of the other frames against registered keyframes (SfM units).
    fcfg = cfg.frontend
    height, width = frames_list[0].shape[:2]
    geo = make_geometry(width, height, fcfg.ba_stride)
    kf_reg = sorted(i for i in T_model if i in ratios)
    kf_frames = np.array(kf_reg)
    kf_gray = [fl.prepare_gray(frames_list[i], geo.flow_size) for i in kf_reg]
    T_kf = torch.from_numpy(np.stack([T_model[i] for i in kf_reg]))
    disp_kf = torch.from_numpy(np.stack([
        _corrected_disp(pool_depth(prior.get(i, frames_list[i]), geo.ba_size).astype(np.float64), ratios[i][1])
        for i in kf_reg]))
    jobs = [i for i in range(n) if i not in set(kf_reg)]
    aligned = align_to_keyframes(jobs, lambda i: fl.prepare_gray(frames_list[i], geo.flow_size), kf_frames, kf_gray,
                                 T_kf, disp_kf, geo.ba_intrinsics(intr), fcfg, progress=progress, k1=k1)
    T_all = np.zeros((n, 4, 4))
    status = ["sfm"] * n
    for i in kf_reg:
        T_all[i] = T_model[i]
    for i, (T, ok, _) in aligned.items():
        T_all[i] = T.numpy()
        status[i] = "aligned" if ok else "interpolated"
    poses = invert_poses(T_all)
    poses[:, :3, 3] *= scale
    log_r = np.log(np.array([r for r, _ in ratios.values()]))
    diagnostics = {
        "method": "sfm",
        "mapper": cfg.mapper,
        "keyframe_stride": stride,
        "num_keyframes": len(kf_ids),
        "registered_keyframes": registered,
        "num_points3d": rec.num_points3D(),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "metric_scale_factor": float(scale),
        "scale_spread_log_std": float(log_r.std()),
        "loop_detection": bool(cfg.vocab_tree_path),
        "frame_status": status,
        "lost_frames": [i for i, s in enumerate(status) if s == "interpolated"],
        "lens_k1": k1,
    }
    if intr_in is None:
        diagnostics["focal_estimate"] = {"focal": intr[0], "source": "COLMAP bundle adjustment"}
    return PoseResult(poses=poses, intrinsics=intr, keyframes=np.array(kf_reg, dtype=np.int64),
                      seconds=time.perf_counter() - t0, diagnostics=diagnostics)
