"""How `benchmarks/report.py` produces and scores each depth source: MEDeA runs with a
feature variant, the refinement as `recon run` runs it (frames in the lens' pinhole image),
the whole pipeline in a fresh process (table D: timings and peak memory), and the depth and
mesh scores of tables A-C.
"""

from __future__ import annotations

import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from priors import MAX_DEPTH, VARIANTS, medea_config  # noqa: E402
from report_text import PRESET  # noqa: E402

from recon.core.medea import adjust_sequence  # noqa: E402
from recon.core.refine import fusion_confidence, refine_sequence  # noqa: E402
from recon.eval.depth import METRIC_NAMES, depth_metrics, multiview_inconsistency  # noqa: E402
from recon.eval.mesh import icp_registered, mesh_metrics  # noqa: E402
from recon.eval.trajectory import move_points  # noqa: E402
from recon.geometry.lens import undistort_features, undistort_images, worth_undistorting  # noqa: E402
from recon.pipeline import STAGES  # noqa: E402

# ------------------------------------------------------------------ scoring



def depth_scores(depth, gt, poses, intrinsics, align: str = "none") -> dict:
    """Every depth metric (frame-averaged) plus coverage, scale and multi-view inconsistency."""
    metrics = depth_metrics(depth, gt, max_depth=MAX_DEPTH, align=align)
    out = {k: metrics[k] for k in (*METRIC_NAMES, "coverage")}
    if "scale" in metrics:
        out["scale"] = metrics["scale"]
    return out


def inconsistency(depth, poses, intrinsics) -> float:
    return multiview_inconsistency(torch.from_numpy(np.ascontiguousarray(depth, np.float32)),
                                   torch.from_numpy(np.asarray(poses, np.float64)),
                                   torch.as_tensor(intrinsics, dtype=torch.float32))


def run_medea(rgb, prior, poses, intrinsics, variant: str, extra: dict | None, quick: bool):
    """MEDeA (fast preset) with the feature setting of priors.VARIANTS[variant] plus `extra`."""
    layer, overrides = VARIANTS[variant]
    config = medea_config(PRESET, {**overrides, **(extra or {})})
    if quick:  # a smoke run: a few epochs only
        config.stage1.epochs, config.stage2.epochs = 20, 5
    features = prior.features if layer is not None else None
    start = time.perf_counter()
    result = adjust_sequence(rgb, prior.depth, poses, intrinsics, features=features, config=config, progress=False)
    wall = time.perf_counter() - start
    depth = result.depth.numpy() if isinstance(result.depth, torch.Tensor) else np.asarray(result.depth)
    info = {"variant": variant, "overrides": {**overrides, **(extra or {})}, "seconds": wall,
            "seconds_per_frame": wall / len(rgb), "stage_seconds": dict(result.seconds),
            "epochs": {stage: int(h.epochs) for stage, h in result.history.items()}}
    return depth.astype(np.float32, copy=False), info


def mesh_scores(mesh, reference, points: int, alignment=None, icp: bool = False) -> dict:
    """Table C's scores of a mesh moved by `alignment`, then (icp) registered onto the
    reference by ICP as `recon eval --mesh-align sim3+icp` does."""
    triangles = np.asarray(mesh.triangles)
    moved, registration = (move_points(mesh.vertices, alignment), triangles), None
    if icp:
        moved, registration = icp_registered(moved, reference, points)
    out = mesh_metrics(moved, reference, num_points=points).to_dict()
    out["triangles"] = int(len(triangles))
    if registration is not None:
        out["icp"] = registration
    return out


# ------------------------------------------------------------------ table D: the pipeline, in a fresh process


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM) in MiB.

    Not ``ru_maxrss``: Linux keeps ``ru_maxrss`` across exec, so a spawned child reports at
    least the RSS its (large) parent had when it forked; VmHWM belongs to the child's own
    address space. Falls back to ru_maxrss where /proc is missing.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _pipeline_child(options: dict) -> dict:
    """Run recon.pipeline in this (freshly spawned) process; report timings and peak memory."""
    torch.set_num_threads(options.pop("threads"))
    from recon.pipeline import PipelineConfig, run_pipeline

    baseline = peak_rss_mb()
    config = PipelineConfig(**options)
    start = time.perf_counter()
    result = run_pipeline(config)
    wall = time.perf_counter() - start
    return {
        "frames": len(result.frames), "indices": result.frames.indices.tolist(), "seconds": dict(result.seconds),
        "wall": wall, "peak_rss_mb": peak_rss_mb(), "rss_after_imports_mb": baseline,
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "poses": np.asarray(result.poses), "intrinsics": list(result.intrinsics),
        "pose_info": result.report["poses"], "medea": result.report["medea"],
        "fusion": result.report["fusion"], "output": str(result.output),
    }


def run_pipeline_fresh(path: Path, out: Path, step: int, max_frames: int | None, poses: str, threads: int,
                       quick: bool) -> dict:
    from recon.core.config import pipeline_medea

    medea = pipeline_medea()  # what `recon run` runs
    if quick:
        medea.stage1.epochs, medea.stage2.epochs = 20, 5
    options = dict(input=path, output=out, overwrite=True, stride=step, max_frames=max_frames, poses=poses,
                   rerun="save", progress=False, medea=medea, threads=threads)
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        return pool.submit(_pipeline_child, options).result()


def stage_summary(run: dict) -> dict:
    n = run["frames"]
    per_frame = {stage: run["seconds"].get(stage, 0.0) / n for stage in STAGES}
    total = sum(per_frame.values())
    return {"frames": n, "seconds_per_frame": per_frame, "total_per_frame": total,
            "total_per_frame_without_logging": total - per_frame["logging"],
            "wall_per_frame": run["wall"] / n, "peak_rss_mb": run["peak_rss_mb"], "ru_maxrss_mb": run["ru_maxrss_mb"],
            "rss_after_imports_mb": run["rss_after_imports_mb"], "medea_epochs": {
                s: v["epochs"] for s, v in run["medea"].get("stages", {}).items()}}


# ------------------------------------------------------------------ the refinement, as the pipeline runs it


def pipeline_inputs(rgb, prior, gt, intrinsics, k1: float):
    """Frames, prior depth, features and sensor depth moved into the pinhole image of lens
    k1 when it matters (as `recon run` does after the poses), else unchanged."""
    k = tuple(float(v) for v in intrinsics)
    size = rgb.shape[1:3]
    if not worth_undistorting(k, size, k1):
        return rgb, prior.depth, prior.features, gt
    return (undistort_images(rgb, k, k1), undistort_images(prior.depth, k, k1, nearest=True),
            undistort_features(prior.features, k, size, k1), undistort_images(gt, k, k1, nearest=True))


def refined_run(rgb, prior, gt, poses, intrinsics, k1: float, quick: bool) -> dict:
    """MEDeA-S (fast) then the MVS refinement on given poses: depths, timings and the lens."""
    frames, prior_depth, features, truth = pipeline_inputs(rgb, prior, gt, intrinsics, k1)
    config = medea_config(PRESET, VARIANTS["S8"][1])
    if quick:
        config.stage1.epochs, config.stage2.epochs = 20, 5
    start = time.perf_counter()
    medea = adjust_sequence(frames, prior_depth, poses, tuple(intrinsics), features, config, progress=False)
    medea_seconds = time.perf_counter() - start
    start = time.perf_counter()
    result = refine_sequence(frames, medea.depth.numpy(), poses, tuple(intrinsics), progress=False)
    refine_seconds = time.perf_counter() - start
    depth = result.depth.numpy()
    return {"poses": poses, "k1": k1, "truth": truth, "medea": medea.depth.numpy().astype(np.float32),
            "refined": depth, "reconstructed_depth": np.where(result.reconstructed.numpy(), depth, 0.0),
            "confidence": fusion_confidence(result), "reconstructed": float(result.reconstructed.float().mean()),
            "unsupported_frames": int(result.unsupported.sum()),
            "medea_seconds_per_frame": medea_seconds / len(rgb), "refine_seconds_per_frame": refine_seconds / len(rgb)}
