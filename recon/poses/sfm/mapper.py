"""The SfM fallback: COLMAP (via pycolmap) on keyframes chosen by motion, dense registration
of the other frames, metric scale from the depth prior, and a check of the result.

This module owns the pycolmap pipeline: keyframes (``sfm_keyframes``) and their SIFT
features on one shared SIMPLE_RADIAL camera, sequential and loop matching, incremental (or
GLOMAP) mapping, the largest model's scale fixed to metres by the prior, and the other frames
registered by the front end's motion-only alignment. Too few registered frames raise a
TrackingLostError naming the range. What is read from the model is ``sfm_model``'s.
More: docs/poses.md#how-the-sfm-fallback-runs-colmap
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
from recon.geometry import lie
from recon.poses.checks import prior_agreement as pa
from recon.poses.config import (
    FRACTION,
    POSITIVE,
    Bounds,
    FrontendConfig,
    at_least,
    bounded,
    calibrates_lens,
    make_geometry,
    one_of,
)
from recon.poses.frontend.filler import align_to_keyframes
from recon.poses.matching import flow as fl
from recon.poses.result import (
    TRUSTED_STATES,
    PoseResult,
    PriorSource,
    TrackingLostError,
    invert_poses,
    iterate_frames,
    numbered,
    parse_intrinsics,
    pool_depth,
    robust_log_mean,
)
from recon.poses.sfm import keyframes as skf
from recon.poses.sfm import model as sm

log = logging.getLogger(__name__)

LOOP_MATCHING = ("retrieval", "exhaustive", "none")
MAPPERS = ("incremental", "global")
GRID = Bounds("two numbers >= 1", lambda v: len(v) == 2 and min(v) >= 1)  # correction_grid's


@dataclass
class SfMConfig:
    """SfM fallback settings; a field's range, where it has one, is its ``bounded`` metadata.
    why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen
    """

    max_keyframes: int = bounded(100, at_least(1))
    """At most this many frames go to COLMAP, which bounds the time; the rest are registered densely."""
    keyframe_motion: float = bounded(16.0, POSITIVE)
    """Keyframe spacing by motion: a new keyframe when the flow summed since the last one reaches this.

    A frame becomes a keyframe when the mean DIS flow (pixels as if the frames were 640 px wide,
    confidence-weighted) summed over the frames since the last keyframe reaches this, and both
    frames of a step the flow cannot follow do (``sfm_keyframes.select_keyframes``). Raised as
    needed to respect max_keyframes.
    """
    keyframe_stride: int | None = bounded(None, at_least(1))
    """Every k-th frame (and the last) instead of the motion selection (None: by motion)."""
    max_num_features: int = bounded(4096, at_least(1))
    """SIFT features per image."""
    overlap: int = bounded(10, at_least(1))
    """Sequential matching links each keyframe to the next `overlap` ones."""
    loop_matching: str = bounded("retrieval", one_of(LOOP_MATCHING))
    """How keyframes far apart in time get matched, for paths that come back: retrieval, exhaustive or none.

    "retrieval" (each keyframe with its `loop_candidates` most similar keyframes beyond the
    sequential window, by a bag of `loop_words` visual words over their SIFT descriptors:
    ``sfm_keyframes.loop_pairs``), "exhaustive" (every pair; the matching time grows with the
    square of the keyframe count) or "none".
    """
    loop_candidates: int = bounded(5, at_least(1))
    """Retrieval pairs per keyframe (each verified by COLMAP like any pair)."""
    loop_words: int = bounded(256, at_least(2))
    """Size of the visual vocabulary learnt on the keyframes (k-means)."""
    vocab_tree_path: str | None = None
    """A COLMAP vocabulary tree file enabling COLMAP's own loop detection in sequential matching.

    None by default: pycolmap would download one, and nothing may be downloaded at run time.
    """
    mapper: str = bounded("incremental", one_of(MAPPERS))
    """The mapper: "incremental" (COLMAP) or "global" (GLOMAP) (``MAPPERS``)."""
    min_registered: float = bounded(0.8, FRACTION)
    """Fraction of all frames that must be registered, else SfM fails.

    Registered in COLMAP's model ("keyframe") or densely next to a keyframe in it ("tracked");
    else SfM fails, naming the longest range of frames it could not register.
    """
    num_threads: int = bounded(2, at_least(1))
    """Threads for feature extraction, matching and mapping."""
    correction_grid: tuple[int, int] = bounded((3, 4), GRID)
    """(rows, cols) of the per-keyframe prior correction from SfM points.

    The corrected keyframe depth is used to register the other frames.
    """
    calibrate_lens: bool | None = None
    """Estimate the radial term k1 in COLMAP's bundle adjustment (None: only when the focal length is unknown too).

    Reported as ``lens_k1``, used to register the other frames and by the pipeline to
    undistort; None (default): only when the focal length is unknown too
    (``frontend_config.calibrates_lens``).
    """
    max_scale_spread: float = 0.25
    """The most the map's scale may vary against the depth prior's over the frames (0 = not checked).

    Standard deviation of the per-frame log ratio that the metric scale is the median of.
    Beyond it the model is marked (``scale_spread``), and refused under ``--on-break stop``:
    five times the prior's own scale noise (about 5 % a frame, ``scale_watch``) may be a map
    whose parts are at different scales, or the prior's own noise on a scene it knows badly.
    why: docs/decisions.md#the-checks-on-an-estimated-trajectory
    """
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    """Flow / alignment settings used to choose keyframes and to register the remaining frames.

    Its flow settings, ``min_match_correlation`` and ``min_edge_weight`` decide which steps the
    flow can follow; ``lost_inlier`` and the rest, the registration.
    """


def _import_pycolmap():
    try:
        import pycolmap
    except ImportError as err:  # pragma: no cover - pycolmap is a dev dependency
        raise ReconInputError("the SfM fallback needs pycolmap (pip install pycolmap)") from err
    return pycolmap


def _run_colmap(frames: list[np.ndarray], kf_ids: list[int], intrinsics, cfg: SfMConfig, workdir: Path):
    """Run extraction, matching and mapping; returns the largest reconstruction (or None)
    and what the stages took ({"seconds": {stage: s}, "loop_pairs": ..., ...})."""
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


def views_model(frames: list[np.ndarray], intrinsics, cfg: SfMConfig | None = None) -> dict[int, np.ndarray]:
    """COLMAP's model of a few views on their own, no frames registered around it (the
    second opinion of a streamed run, a join through the map): {view index: camera-to-world
    pose (4, 4) in the model's own frame and scale} for the views in the largest model,
    empty without one. frames: (H, W, 3) uint8 RGB or (H, W) grey, one size; intrinsics
    (fx, fy, cx, cy) held fixed (None: COLMAP estimates the focal length); cfg: matching
    and mapping (default: ``SfMConfig`` with the lens term off)."""
    cfg = cfg or SfMConfig(calibrate_lens=False)
    rgb = [np.repeat(f[..., None], 3, axis=2) if f.ndim == 2 else f for f in frames]
    with tempfile.TemporaryDirectory(prefix="recon-sfm-views-") as tmp:
        rec, _ = _run_colmap(rgb, list(range(len(rgb))), intrinsics, cfg, Path(tmp))
    if rec is None:
        return {}
    world_to_camera, _, _ = sm.model_poses(rec)
    return {i: np.linalg.inv(T) for i, T in world_to_camera.items()}


def _reader_options(pycolmap, intrinsics, lens: bool):
    """COLMAP's camera for the frames, and whether it has the radial term."""
    reader = pycolmap.ImageReaderOptions()
    if intrinsics is not None:
        # COLMAP puts pixel centres at +0.5, recon at integers.
        fx, fy, cx, cy = intrinsics
        lens = lens and abs(fx - fy) <= 1e-3 * fx
        params = (fx, cx + 0.5, cy + 0.5, 0.0) if lens else (fx, fy, cx + 0.5, cy + 0.5)
        reader.camera_model = "SIMPLE_RADIAL" if lens else "PINHOLE"
        reader.camera_params = ",".join(f"{v:.6f}" for v in params)
    else:
        reader.camera_model = "SIMPLE_RADIAL" if lens else "SIMPLE_PINHOLE"
    return reader, lens


def _colmap_pipeline(pycolmap, frames, kf_ids, intrinsics, cfg: SfMConfig, workdir: Path):
    # The files below (keyframe PNGs, COLMAP's database, the loop pair list) are COLMAP's own
    # scratch workspace in a temporary folder, written and read only through pycolmap's
    # interface, not user files: they stay here rather than in recon/io.
    seconds = {}
    t = time.perf_counter()
    image_dir = workdir / "images"
    image_dir.mkdir()
    names = []
    for i in kf_ids:
        name = f"{i:06d}.png"
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR))
        names.append(name)
    height, width = frames[0].shape[:2]
    db = workdir / "database.db"
    reader, lens = _reader_options(pycolmap, intrinsics, calibrates_lens(cfg.calibrate_lens, intrinsics))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = cfg.num_threads
    extraction.max_image_size = max(width, height)
    extraction.sift.max_num_features = cfg.max_num_features
    pycolmap.extract_features(db, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    seconds["features"] = time.perf_counter() - t
    t = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = cfg.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    stats = {"loop_pairs": 0, "loop_pairs_verified": 0}
    if cfg.loop_matching == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pairing.quadratic_overlap = True  # the gaps loop_pairs leaves out (sequential_gaps)
        pairing.num_threads = cfg.num_threads
        if cfg.vocab_tree_path:
            if not Path(cfg.vocab_tree_path).is_file():
                raise ReconInputError(f"{cfg.vocab_tree_path}: vocabulary tree file not found")
            pairing.loop_detection = True
            pairing.vocab_tree_path = str(cfg.vocab_tree_path)
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)
    seconds["matching"] = time.perf_counter() - t
    if cfg.loop_matching == "retrieval" and len(names) > cfg.overlap + 1:
        t = time.perf_counter()
        stats.update(_match_loop_pairs(pycolmap, db, names, matching, verification, cfg, workdir))
        seconds["loop_matching"] = time.perf_counter() - t
    t = time.perf_counter()
    out = workdir / "sparse"
    out.mkdir()
    if cfg.mapper == "global":
        models = pycolmap.global_mapping(db, image_dir, out)
    else:
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = cfg.num_threads
        opts.ba_refine_focal_length = intrinsics is None
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = lens
        models = pycolmap.incremental_mapping(db, image_dir, out, opts)
    seconds["mapping"] = time.perf_counter() - t
    stats["seconds"] = seconds
    if not models:
        return None, stats
    t = time.perf_counter()
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    stats["evidence"] = sm.model_evidence(pycolmap, db, rec, verification.min_num_inliers)
    seconds["evidence"] = time.perf_counter() - t
    return rec, stats


def _match_loop_pairs(pycolmap, db_path: Path, names: list[str], matching, verification, cfg: SfMConfig,
                      workdir: Path) -> dict:
    """Match (and verify) the retrieval pairs of the keyframes `names` (in time order) that
    sequential matching did not reach; returns {"loop_pairs": proposed, "loop_pairs_verified":
    those with a verified two-view geometry}."""
    db = pycolmap.Database.open(db_path)
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        # An image COLMAP could not read in (its size differs from the shared camera's) has
        # no descriptors: it takes part in no pair.
        desc = [np.asarray(db.read_descriptors(ids[name]).data) if name in ids else np.zeros((0, 128), np.uint8)
                for name in names]
    finally:
        db.close()
    vectors = skf.bow_vectors(desc, cfg.loop_words)
    # COLMAP's sequential matching also pairs keyframes 2^j apart (its quadratic overlap).
    pairs = [(a, b) for a, b in skf.loop_pairs(vectors, skf.sequential_gaps(cfg.overlap), cfg.loop_candidates)
             if names[a] in ids and names[b] in ids]
    if not pairs:
        return {"loop_pairs": 0, "loop_pairs_verified": 0}
    pair_file = workdir / "loop_pairs.txt"
    pair_file.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = pair_file
    pycolmap.match_image_pairs(db_path, matching_options=matching, pairing_options=pairing,
                               verification_options=verification, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(db_path)
    try:
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    verified = {int(p) for p, m in zip(pair_ids, inliers) if m >= verification.min_num_inliers}
    wanted = {int(pycolmap.image_pair_to_pair_id(ids[names[a]], ids[names[b]])) for a, b in pairs}
    return {"loop_pairs": len(pairs), "loop_pairs_verified": len(wanted & verified)}


def choose_keyframes(grays: list[np.ndarray], px_scale: float, cfg: SfMConfig) -> tuple[list[int], float | None]:
    """Keyframe indices (sorted; first and last frame included) of N frames given as
    flow-resolution grey images (h, w) uint8, and the motion spacing used (None with a
    forced keyframe_stride)."""
    n = len(grays)
    if cfg.keyframe_stride:
        kf_ids = list(range(0, n, cfg.keyframe_stride))
        return kf_ids + ([n - 1] if kf_ids[-1] != n - 1 else []), None
    fcfg = cfg.frontend
    motion, ok = skf.step_motion(grays, fcfg.flow, px_scale, fcfg.min_match_correlation, fcfg.min_edge_weight,
                                 fcfg.min_local_correlation)
    return skf.select_keyframes(motion, ok, cfg.keyframe_motion, max(cfg.max_keyframes, 2))


def scale_spread(log_ratios: np.ndarray, limit: float) -> dict:
    """What report.json says of how much SfM's map and the depth prior disagree in scale from
    frame to frame (``poses.scale_spread``): log_ratios (M,) the per-frame log ratio of the
    prior's depth to the map's, limit ``SfMConfig.max_scale_spread`` (0: not judged).
    ``consistent`` is False beyond it: a map whose parts may be at different scales, marked
    and said (``recon.drivers.segments.check_scale_spread``), refused under ``--on-break stop``."""
    spread = float(np.std(log_ratios)) if len(log_ratios) else 0.0
    return {"log_std": spread, "factor": float(np.exp(spread)), "max_log_std": float(limit),
            "consistent": not (limit > 0 and spread > limit)}


def estimate_poses_sfm(frames, prior_depth, intrinsics=None, progress: bool = True,
                       config: SfMConfig | None = None, frame_numbers=None) -> PoseResult:
    """Metric camera-to-world poses of every frame by COLMAP SfM on keyframes.

    Same inputs as ``frontend.estimate_poses_frontend`` (frame_numbers: how errors name
    the frames). diagnostics: method "sfm",
    keyframe selection, registered keyframes and frames, loop pairs (proposed, verified),
    seconds per stage, model points, mean reprojection error, the metric scale factor and
    its spread over images, per-frame ``frame_status`` (``result.FRAME_STATES``:
    "keyframe" in COLMAP's model, "tracked" registered densely, "interpolated" a guess
    between registered neighbours), ``frame_inlier`` (per frame: the share of a model
    frame's 2D-3D correspondences its pose explains, ``sfm_model.model_evidence``; the
    dense alignment's inlier fraction where ``align_to_keyframes`` reports one, else NaN),
    ``lost_frames`` (the interpolated ones) and ``unregistered_ranges``. Raises
    TrackingLostError when fewer than ``min_registered`` of the frames are registered.
    """
    cfg = config or SfMConfig()
    number = numbered(frame_numbers)
    if cfg.loop_matching not in LOOP_MATCHING:
        raise ReconInputError(f"SfM loop_matching must be one of {', '.join(LOOP_MATCHING)}, got {cfg.loop_matching!r}")
    if cfg.mapper not in MAPPERS:
        raise ReconInputError(f"SfM mapper must be one of {', '.join(MAPPERS)}, got {cfg.mapper!r}")
    t0 = time.perf_counter()
    frames_list = [f for _, f in iterate_frames(frames)]
    n = len(frames_list)
    if n < 2:
        raise ReconInputError(f"SfM needs at least 2 frames, got {n}")
    prior = PriorSource(prior_depth)
    if not prior.is_callable and len(prior) != n:
        raise ReconInputError(f"prior depth has {len(prior)} frames but the video has {n}")
    intr_in = parse_intrinsics(intrinsics)
    fcfg = cfg.frontend
    geo = make_geometry(frames_list[0].shape[:2], fcfg.ba_stride)
    grays = [fl.prepare_gray(f, geo.flow_shape) for f in frames_list]
    kf_ids, spacing = choose_keyframes(grays, geo.px_scale, cfg)
    t_select = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="recon-sfm-") as tmp:
        log.info("SfM (pycolmap) on %d keyframes of %d frames", len(kf_ids), n)
        rec, stats = _run_colmap(frames_list, kf_ids, intr_in, cfg, Path(tmp))
    stats["seconds"] = {"keyframes": t_select, **stats["seconds"]}
    T_model, intr, k1 = sm.model_poses(rec) if rec is not None else ({}, None, 0.0)
    model_only = ["keyframe" if i in T_model else "interpolated" for i in range(n)]
    if len(T_model) < 2:  # nothing to register the other frames against
        raise skf.registration_error(model_only, len(kf_ids), cfg.min_registered, number)
    points = sm.point_depths(rec, prior, frames_list)
    ratios = sm.depth_ratios(points, cfg.correction_grid)
    if not ratios:
        # Without depth no frame can be registered densely: usually a model of a few images
        # and points (COLMAP's mapper now and then ends with one on fast rotation).
        raise (skf.registration_error(model_only, len(kf_ids), cfg.min_registered, number) or TrackingLostError(
            "SfM: no triangulated point has a valid prior depth; cannot fix the metric scale"))
    scale = robust_log_mean(np.array([r for r, _ in ratios.values()]))

    # Dense registration of the frames next to the model against its keyframes (SfM units).
    t = time.perf_counter()
    jobs = skf.dense_candidates(n, kf_ids, set(T_model))
    kf_reg = sorted(i for i in T_model if i in ratios)
    kf_frames = np.array(kf_reg)
    T_kf = torch.from_numpy(np.stack([T_model[i] for i in kf_reg]))
    disp_kf = torch.from_numpy(np.stack([
        sm.corrected_disp(pool_depth(prior.get(i, frames_list[i]), geo.ba_shape).astype(np.float64), ratios[i][1])
        for i in kf_reg]))
    aligned = align_to_keyframes(jobs, lambda i: grays[i], kf_frames, [grays[i] for i in kf_reg],
                                 T_kf, disp_kf, geo.ba_intrinsics(intr), fcfg, progress=progress, k1=k1)
    stats["seconds"]["dense"] = time.perf_counter() - t
    T_all = np.zeros((n, 4, 4))
    status = ["interpolated"] * n
    inlier = np.full(n, np.nan)
    for i, fraction in stats["evidence"].items():
        T_all[i], status[i], inlier[i] = T_model[i], "keyframe", fraction
    T_kf_np = T_kf.numpy()
    for i in range(n):
        if status[i] != "keyframe" and i not in aligned:
            T_all[i] = lie.interpolated_pose(i, kf_frames, T_kf_np)
    for i, (T, ok, _, fraction) in aligned.items():
        T_all[i] = T.numpy()
        status[i] = "tracked" if ok else "interpolated"
        inlier[i] = fraction
    if (err := skf.registration_error(status, len(kf_ids), cfg.min_registered, number)) is not None:
        raise err
    poses = invert_poses(T_all)
    poses[:, :3, 3] *= scale
    log_r = np.log(np.array([r for r, _ in ratios.values()]))
    spread = scale_spread(log_r, cfg.max_scale_spread)
    trusted = np.array([s in TRUSTED_STATES for s in status])
    agreement = [(i, *pa.point_log_correlation(p.z, p.d)) for i, p in sorted(points.items())]
    diagnostics = {
        "method": "sfm",
        "mapper": cfg.mapper,
        "keyframe_selection": "stride" if spacing is None else "motion",
        "keyframe_stride": cfg.keyframe_stride,
        "keyframe_spacing_px": spacing,
        "num_keyframes": len(kf_ids),
        "registered_keyframes": len(T_model),
        "registered_frames": int(trusted.sum()),
        "registered_fraction": float(trusted.mean()),
        "loop_matching": cfg.loop_matching,
        "loop_pairs": stats["loop_pairs"],
        "loop_pairs_verified": stats["loop_pairs_verified"],
        "seconds_per_stage": stats["seconds"],
        "num_points3d": rec.num_points3D(),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "metric_scale_factor": float(scale),
        "scale_spread_log_std": float(log_r.std()),
        "scale_spread": spread,
        "loop_detection": bool(cfg.vocab_tree_path),
        "frame_status": status,
        "frame_inlier": inlier.tolist(),
        "lost_frames": [i for i, s in enumerate(status) if s == "interpolated"],
        "unregistered_ranges": [list(r) for r in sorted(skf.unregistered_ranges(trusted))],
        "lens_k1": k1,
        "prior_agreement": pa.judge_agreement(*zip(*agreement)).to_dict(),
    }
    if intr_in is None:
        diagnostics["focal_estimate"] = {"focal": intr[0], "source": "COLMAP bundle adjustment"}
    return PoseResult(poses=poses, intrinsics=intr, keyframes=np.array(sorted(T_model), dtype=np.int64),
                      seconds=time.perf_counter() - t0, diagnostics=diagnostics)
