"""One recording's tables for `benchmarks/report.py` (whose docstring says what each
table holds): the frames, ground truth and prior loaded once, table D's pipeline runs in
fresh processes, tables A-C and the ablations, each row scored by `report_runs`.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import say  # noqa: E402
from priors import MAX_DEPTH, oracles  # noqa: E402
from report_runs import (  # noqa: E402
    depth_scores,
    inconsistency,
    mesh_scores,
    refined_run,
    run_medea,
    run_pipeline_fresh,
    stage_summary,
)
from report_text import (  # noqa: E402
    FEATURE_NOTE,
    PAPER_ABLATION,
    PAPER_T1,
    PAPER_T2,
    PRESET,
    REFINE_NOTE,
    paper_text,
)

from recon.core.refine import default_min_confidence, fusion_confidence, refine_sequence  # noqa: E402
from recon.eval.depth import METRIC_NAMES  # noqa: E402
from recon.eval.evaluate import reference_tsdf_mesh  # noqa: E402
from recon.eval.trajectory import ate_rmse, path_length, pose_alignment, scale_error  # noqa: E402
from recon.fusion import FusionOptions, auto_voxel_size, fuse  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.poses.given.polish import polish_poses  # noqa: E402
from recon.priors import make_prior  # noqa: E402

# MEDeA rows of tables A and B: key -> (label, priors.VARIANTS key). Stride-8 features are
# the pipeline's (FastDepthPrior's default feature_layer).
MEDEA_ROWS = {"S": ("MEDeA-S", "S8"), "M": ("MEDeA-M", "M8"), "none": ("MEDeA, no feature loss", "none")}
# Ablations: label -> MedeaConfig overrides on top of the base row ("w/o feature loss" is
# the "none" row, whatever the base).
ABLATIONS = {
    "w/o photometric": {"use_photometric": False},
    "w/o depth": {"use_depth": False},
    "w/o feature loss": None,
    "w/o scale propagation": {"propagate_scale": False},
    "Stage II only": {"run_stage1": False},
}




# ------------------------------------------------------------------ one recording


@dataclass
class Recording:
    """One recording as every table sees it: the frames, ground truth and prior, and the
    results the later tables reuse (depths for the meshes, MEDeA and refinement runs)."""

    path: Path
    quick: bool
    dataset: object
    kind: str
    indices: np.ndarray  # frame numbers in the full recording
    rgb: np.ndarray
    gt: np.ndarray
    gt_poses: np.ndarray
    intrinsics: np.ndarray
    diff_common: str  # what every row differs from the paper in
    record: dict
    prior: object = None
    depths: dict = field(default_factory=dict)  # depth source -> (N, H, W), meshed in table C
    medea_info: dict = field(default_factory=dict)
    refine_runs: dict = field(default_factory=dict)
    pipeline_runs: dict = field(default_factory=dict)


def evaluate_recording(path: Path, step: int, args, workdir: Path) -> dict:
    rec = load_recording(path, step, args.quick)
    # Table D first: the pipeline runs, each in a fresh process (clean peak memory); the
    # estimated-pose run also gives table B its poses.
    if not args.no_pipeline:
        run_table_d(rec, step, args.threads, workdir)
    compute_prior(rec)
    rows_a = run_table_a(rec)
    run_ablations(rec, rows_a, args.ablation_base)
    est_poses = run_table_b(rec)
    run_table_c(rec, est_poses, 20_000 if rec.quick else args.mesh_points)
    check_pipeline_depth(rec)
    rec.record["medea_runs"] = rec.medea_info
    return rec.record


def load_recording(path: Path, step: int, quick: bool) -> Recording:
    max_frames = 12 if quick else None
    full = open_dataset(path)
    dataset = full.select(stride=step, max_frames=max_frames).with_valid_poses()
    kind = dataset.kind
    indices = np.arange(0, len(full), step)[:max_frames] if max_frames else np.arange(0, len(full), step)
    if dataset.pose_valid is not None and len(dataset) != len(indices):
        indices = indices[full.pose_valid[indices]]
    say(f"{path.name}: {kind}, {len(full)} frames, every {step}th -> {len(dataset)} frames")
    rgb = dataset.load_rgb_batch()
    gt = dataset.load_depth_batch()
    gt_poses = np.asarray(dataset.poses, np.float64)
    intrinsics = np.asarray(dataset.intrinsics, np.float64)
    n = len(rgb)
    record: dict = {
        "dataset": path.name, "path": str(path), "kind": kind, "frames_total": len(full), "step": step,
        "frames": n, "frame_indices": indices.tolist(), "size": [dataset.width, dataset.height],
        "intrinsics": intrinsics.tolist(), "path_length_m": path_length(gt_poses),
    }
    subset = "all frames" if step == 1 and n == len(full) else f"{n} of {len(full)} frames"
    diff_common = f"FastDepth prior; {subset}; 640x480 input, CPU"
    return Recording(path, quick, dataset, kind, indices, rgb, gt, gt_poses, intrinsics, diff_common, record)


def run_table_d(rec: Recording, step: int, threads: int, workdir: Path) -> None:
    path, quick = rec.path, rec.quick
    max_frames = 12 if quick else None
    pipeline_runs = rec.pipeline_runs
    for mode in ("gt", "estimate"):
        say(f"{path.name}: pipeline, poses {mode}")
        try:
            pipeline_runs[mode] = run_pipeline_fresh(path, workdir / f"{path.name}-{mode}", step, max_frames, mode,
                                                     threads, quick)
        except Exception as error:  # a failed run is a result too (e.g. tracking lost)
            pipeline_runs[mode] = {"error": f"{type(error).__name__}: {error}"}
            say(f"  failed: {error}")
    rec.record["table_d"] = {mode: (stage_summary(run) if "error" not in run else {"error": run["error"]})
                             for mode, run in pipeline_runs.items()}


def compute_prior(rec: Recording) -> None:
    """The prior, once (FastDepth + stride-8 features, as the pipeline builds it)."""
    say(f"{rec.path.name}: FastDepth prior")
    start = time.perf_counter()
    prior = make_prior("fastdepth", features=True, progress=False)(rec.rgb, rec.intrinsics)
    rec.record["prior"] = {"seconds_per_frame": (time.perf_counter() - start) / len(rec.rgb), "info": prior.info,
                           "features": list(prior.features.shape[1:])}
    rec.prior = prior
    rec.depths.update({"prior": prior.depth, "sensor": rec.gt})


def run_table_a(rec: Recording) -> dict:
    """Table A: GT poses, metric. Returns its rows (the ablations start from one)."""
    path, quick, kind, prior, diff_common = rec.path, rec.quick, rec.kind, rec.prior, rec.diff_common
    rgb, gt, gt_poses, intrinsics = rec.rgb, rec.gt, rec.gt_poses, rec.intrinsics
    depths, medea_info = rec.depths, rec.medea_info
    paper1 = PAPER_T1.get(kind, {})
    rows_a: dict = {}

    def add_a(key, label, depth, extra=None, paper=None, note="", truth=None, poses=None):
        scores = depth_scores(depth, gt if truth is None else truth, gt_poses, intrinsics)
        scores["inconsistency"] = inconsistency(depth, gt_poses if poses is None else poses, intrinsics)
        rows_a[key] = {"label": label, **scores, **(extra or {}), "paper": paper, "paper_note": note}
        say(f"  A {label}: abs rel {scores['abs_rel']:.4f} inconsistency {scores['inconsistency']:.4f}")

    add_a("prior", "prior (FastDepth)", prior.depth, paper=paper1.get("ZoeDepth"),
          note=f"paper's nearest: ZoeDepth, single-view metric (its MEDeA priors are not in Table 1; "
               f"SimpleRecon, MEDeA-M's prior: {paper_text(paper1.get('SimpleRecon'))}); {diff_common}")
    for key, (label, variant) in MEDEA_ROWS.items():
        say(f"{path.name}: MEDeA {label}, GT poses")
        depth, info = run_medea(rgb, prior, gt_poses, intrinsics, variant, None, quick)
        depths[f"gt/{key}"] = depth
        medea_info[f"gt/{key}"] = info
        if key == "none":
            paper = PAPER_ABLATION["w/o feature loss"] if kind == "tum" else None
            note = ("paper: MEDeA-M w/o L_feat (ablation, TUM)" if kind == "tum" else "not in the paper") + \
                f"; {diff_common}"
        else:
            paper = paper1.get(label)
            note = f"paper {label}; {diff_common}; {FEATURE_NOTE[key]}"
        add_a(key, f"{label} [{PRESET}]", depth, {"medea": info}, paper, note)
    for label, depth in oracles(prior.depth, gt).items():  # bounds: the prior corrected with ground truth
        key = "oracle grid" if "grid" in label else "oracle scale"
        depths[f"gt/{key}"] = depth
        add_a(key, label, depth, paper=None, note="bound, uses the ground truth: " + (
            "the best 8x10 log-scale grid (MEDeA's deformation model), median-pooled gt/prior"
            if key == "oracle grid" else "each frame's true median scale"))
    if "gt/oracle scale" in depths:
        del depths["gt/oracle scale"]
    add_a("sensor", "sensor depth (reference)", gt, paper=None,
          note="ground truth itself: 0 error by construction; inconsistency = the sensor's own floor")
    add_refinement_rows_a(rec, add_a)
    rec.record["table_a"] = rows_a
    return rows_a


def add_refinement_rows_a(rec: Recording, add_a) -> None:
    """Table A's refinement rows on ground-truth poses: polished (the pipeline's default), and as given."""
    path, quick, prior, diff_common = rec.path, rec.quick, rec.prior, rec.diff_common
    rgb, gt, gt_poses, intrinsics = rec.rgb, rec.gt, rec.gt_poses, rec.intrinsics
    depths, refine_runs = rec.depths, rec.refine_runs
    n = len(rgb)
    say(f"{path.name}: pose polish, MEDeA-S and MVS refinement, GT poses")
    start = time.perf_counter()
    polished = polish_poses(rgb, prior.depth, gt_poses, tuple(intrinsics), progress=False)
    polish_info = {**{k: v for k, v in polished.info.items() if k != "config"},
                   "seconds_per_frame": (time.perf_counter() - start) / n}
    refine_runs["gt"] = refined_run(rgb, prior, gt, polished.poses, intrinsics, polished.lens_k1, quick)
    run = refine_runs["gt"]
    run["polish"] = polish_info
    lens = f"lens k1 {run['k1']:+.3f}" if run["truth"] is not gt else "no lens"
    info = {"polish": polish_info, "refine_seconds_per_frame": run["refine_seconds_per_frame"],
            "reconstructed": run["reconstructed"], "unsupported_frames": run["unsupported_frames"]}
    add_a("S polished", "MEDeA-S [fast], polished poses", run["medea"], {"medea": {
        "seconds_per_frame": run["medea_seconds_per_frame"]}}, None,
        f"GT poses polished against the frames ({lens}); {diff_common}", run["truth"], run["poses"])
    add_a("refine", "MVS refinement [default]", run["refined"], {"refine": info}, None,
          f"{REFINE_NOTE}; {run['refine_seconds_per_frame']:.3f} s/frame; {diff_common}", run["truth"], run["poses"])
    add_a("refine reconstructed", f"MVS refinement, reconstructed pixels ({100 * run['reconstructed']:.0f} %)",
          run["reconstructed_depth"], {"refine": info}, None,
          "only the pixels at least 2 source views agree on (what fusion integrates); coverage "
          f"{100 * run['reconstructed']:.0f} % of the sensor's pixels", run["truth"], run["poses"])
    say(f"{path.name}: MVS refinement on the GT poses as given")
    start = time.perf_counter()
    raw = refine_sequence(rgb, depths["gt/S"], gt_poses, tuple(intrinsics), progress=False)
    refine_runs["gt raw"] = {"poses": gt_poses, "refined": raw.depth.numpy(), "confidence": fusion_confidence(raw),
                             "refine_seconds_per_frame": (time.perf_counter() - start) / n,
                             "reconstructed": float(raw.reconstructed.float().mean())}
    add_a("refine raw", "MVS refinement, GT poses not polished", refine_runs["gt raw"]["refined"], None, None,
          f"the refinement on table A's MEDeA-S depth with the poses as given: where their disagreement with the "
          f"colour frames leaves it; reconstructed {100 * refine_runs['gt raw']['reconstructed']:.0f} %")


def run_ablations(rec: Recording, rows_a: dict, base: str) -> None:
    """Ablations (GT poses, metric), on the base row of table A."""
    path, quick, kind, prior = rec.path, rec.quick, rec.kind, rec.prior
    rgb, gt, gt_poses, intrinsics = rec.rgb, rec.gt, rec.gt_poses, rec.intrinsics
    base_label, base_variant = MEDEA_ROWS[base]
    ablations: dict = {"base": base_label, "rows": {}}
    full_row = rows_a[base]
    ablations["rows"]["full"] = {"label": f"{base_label} (full)",
                                 **{k: full_row[k] for k in (*METRIC_NAMES, "inconsistency")},
                                 "seconds_per_frame": full_row["medea"]["seconds_per_frame"]}
    for label, overrides in ABLATIONS.items():
        if overrides is None:
            row = rows_a["none"]
            info = row["medea"]
        else:
            say(f"{path.name}: ablation {label}")
            depth, info = run_medea(rgb, prior, gt_poses, intrinsics, base_variant, overrides, quick)
            row = depth_scores(depth, gt, gt_poses, intrinsics)
            row["inconsistency"] = inconsistency(depth, gt_poses, intrinsics)
            del depth
        ablations["rows"][label] = {"label": label, **{k: row[k] for k in (*METRIC_NAMES, "inconsistency")},
                                    "seconds_per_frame": info["seconds_per_frame"], "medea": info}
        say(f"  ablation {label}: abs rel {row['abs_rel']:.4f}")
    for key, row in ablations["rows"].items():
        row["paper"] = PAPER_ABLATION.get(key) if kind == "tum" and base == "M" else None
    rec.record["ablations"] = ablations


def estimated_poses(rec: Recording) -> tuple[np.ndarray | None, dict, float, str]:
    """Table B's poses: from table D's estimated-pose run when it covers the same frames, else estimated here.

    Returns:
        poses (None if estimation failed), pose info, seconds, where they came from.
    """
    est = rec.pipeline_runs.get("estimate")
    if est is not None and "error" not in est and est["indices"] == rec.indices.tolist():
        est_poses, pose_info = np.asarray(est["poses"], np.float64), dict(est["pose_info"])
        return est_poses, pose_info, est["seconds"]["poses"], "pipeline run of table D"
    from recon.poses import estimate_poses

    say(f"{rec.path.name}: estimating poses")
    start = time.perf_counter()
    try:
        result = estimate_poses(rec.rgb, rec.prior.depth, intrinsics=tuple(rec.intrinsics), method="auto",
                                progress=False)
        est_poses = np.asarray(result.poses, np.float64)
        pose_info = {"keyframes": len(result.keyframes),
                     "diagnostics": {k: v for k, v in result.diagnostics.items()
                                     if np.ndim(v) == 0 or (hasattr(v, "__len__") and len(v) < 50)}}
    except Exception as error:
        est_poses, pose_info = None, {"error": f"{type(error).__name__}: {error}"}
    return est_poses, pose_info, time.perf_counter() - start, "estimate_poses in this script"


def run_table_b(rec: Recording) -> np.ndarray | None:
    """Table B: estimated poses, median-scaled depth. Returns the poses (None if estimation failed)."""
    path, quick, prior, diff_common = rec.path, rec.quick, rec.prior, rec.diff_common
    rgb, gt, gt_poses, intrinsics = rec.rgb, rec.gt, rec.gt_poses, rec.intrinsics
    record, depths, medea_info = rec.record, rec.depths, rec.medea_info
    n = len(rgb)
    paper2 = PAPER_T2.get(rec.kind, {})
    est_poses, pose_info, pose_seconds, pose_from = estimated_poses(rec)
    if est_poses is None:
        record["trajectory"] = {"error": pose_info.get("error", "no poses")}
        return None
    sim3, se3 = ate_rmse(est_poses, gt_poses, "sim3"), ate_rmse(est_poses, gt_poses, "se3")
    record["trajectory"] = {
        "source": pose_from, "method": "auto (front end, SfM fallback)",
        "fallback": pose_info.get("diagnostics", {}).get("fallback"),
        "ate_sim3_m": sim3["rmse"], "ate_se3_m": se3["rmse"], "sim3_scale": sim3["scale"],
        "scale_error": scale_error(est_poses, gt_poses), "path_length_m": path_length(gt_poses),
        "seconds_per_frame": pose_seconds / n, "keyframes": pose_info.get("keyframes"),
    }
    say(f"  poses: ATE Sim(3) {sim3['rmse'] * 100:.2f} cm, scale error {record['trajectory']['scale_error']:.3f}")
    rows_b: dict = {}

    def add_b(key, label, depth, extra=None, paper=None, note="", truth=None):
        seq = depth_scores(depth, gt if truth is None else truth, est_poses, intrinsics, "median_sequence")
        frame = depth_scores(depth, gt if truth is None else truth, est_poses, intrinsics, "median_frame")
        rows_b[key] = {"label": label, "median_sequence": seq, "median_frame": frame,
                       "inconsistency": inconsistency(depth, est_poses, intrinsics), **(extra or {}),
                       "paper": paper, "paper_note": note}
        say(f"  B {label}: abs rel (seq) {seq['abs_rel']:.4f} (frame) {frame['abs_rel']:.4f}")

    add_b("prior", "prior (FastDepth)", prior.depth, paper=paper2.get("Romanov et al."),
          note=f"paper: Romanov et al., MEDeA-S's prior; {diff_common}")
    for key, (label, variant) in MEDEA_ROWS.items():
        say(f"{path.name}: MEDeA {label}, estimated poses")
        depth, info = run_medea(rgb, prior, est_poses, intrinsics, variant, None, quick)
        if key in ("S", "M"):
            depths[f"est/{key}"] = depth
        medea_info[f"est/{key}"] = info
        paper = paper2.get(label) if key != "none" else None
        note = (f"paper {label} on DROID-SLAM poses" if key != "none" else "not in the paper") + \
            f"; our poses: recon front end; {diff_common}" + (f"; {FEATURE_NOTE[key]}" if key != "none" else "")
        add_b(key, f"{label} [{PRESET}]", depth, {"medea": info}, paper, note)
        del depth
    say(f"{path.name}: MEDeA-S and MVS refinement, estimated poses")
    k1 = float(pose_info.get("lens_k1", pose_info.get("diagnostics", {}).get("lens_k1", 0.0)) or 0.0)
    run = rec.refine_runs["est"] = refined_run(rgb, prior, gt, est_poses, intrinsics, k1, quick)
    lens = f"frames undistorted with the front end's lens k1 {k1:+.3f}" if run["truth"] is not gt else "no lens"
    add_b("S undistorted", "MEDeA-S [fast], as the pipeline", run["medea"], {"medea": {
        "seconds_per_frame": run["medea_seconds_per_frame"]}}, None,
        f"as the MEDeA-S row, {lens} (as `recon run`); {diff_common}", run["truth"])
    add_b("refine", "MVS refinement [default]", run["refined"], {"refine": {
        "seconds_per_frame": run["refine_seconds_per_frame"], "reconstructed": run["reconstructed"]}}, None,
        f"{REFINE_NOTE} (estimated poses are not polished); reconstructed {100 * run['reconstructed']:.0f} %",
        run["truth"])
    add_b("sensor", "sensor depth (reference)", gt, note="ground truth itself; inconsistency under estimated poses")
    record["table_b"] = rows_b
    return est_poses


def run_table_c(rec: Recording, est_poses: np.ndarray | None, points: int) -> None:
    """Table C: meshes of every depth source, and of the refinement as the pipeline fuses it."""
    say(f"{rec.path.name}: meshes")
    gt = rec.gt
    sensor_valid = gt[(gt > 0) & (gt <= MAX_DEPTH)]
    voxel = auto_voxel_size(float(np.median(sensor_valid)))
    reference = reference_tsdf_mesh(rec.dataset, np.arange(len(rec.rgb)), voxel, MAX_DEPTH, False, gt)
    rows_c: dict = {}
    options = FusionOptions(voxel_size=voxel, max_depth=MAX_DEPTH, progress=False)
    mesh_depth_sources(rec, est_poses, options, reference, points, rows_c)
    mesh_refinement(rec, options, reference, points, rows_c)
    rec.record["refine"] = {k: {f: v for f, v in run.items() if not isinstance(v, np.ndarray)}
                            for k, run in rec.refine_runs.items()}
    rec.record["table_c"] = {"voxel_size": voxel, "max_depth": MAX_DEPTH, "points": points,
                             "reference_triangles": int(len(reference.triangles)), "rows": rows_c}


def mesh_depth_sources(rec: Recording, est_poses, options, reference, points: int, rows_c: dict) -> None:
    """Table C's rows for the prior, MEDeA, the oracle and the sensor, on GT and estimated poses."""
    gt_poses, intrinsics, depths = rec.gt_poses, rec.intrinsics, rec.depths
    sources = [("prior", "prior (FastDepth)", "gt"), ("gt/S", "MEDeA-S [fast]", "gt"), ("gt/M", "MEDeA-M [fast]", "gt"),
               ("gt/none", "MEDeA, no feature loss [fast]", "gt"),
               ("gt/oracle grid", "oracle: 8x10 grid (bound)", "gt"), ("sensor", "sensor depth (sanity: F = 1)", "gt")]
    if est_poses is not None:
        sources += [("est/prior", "prior (FastDepth), estimated poses", "est"),
                    ("est/S", "MEDeA-S [fast], estimated poses", "est"),
                    ("est/M", "MEDeA-M [fast], estimated poses", "est")]
    for key, label, pose_kind in sources:
        depth = depths.get(key) if key != "est/prior" else rec.prior.depth
        if depth is None:
            continue
        start = time.perf_counter()
        if pose_kind == "gt":
            mesh = fuse(depth, None, gt_poses, intrinsics, options).mesh
            rows_c[key] = {"label": label, "poses": "gt", "align": "none", **mesh_scores(mesh, reference, points),
                           "seconds": time.perf_counter() - start}
            keys = [key]
        else:
            # Fused in the estimate's own frame, then brought onto the ground truth by the
            # orientations and centres of the cameras (pose_alignment), two ways: scaled by the
            # trajectory's Sim(3) scale (as `recon eval`; it rescales the depth too) and
            # unscaled (keeps the metric scale the front end and MEDeA produced).
            mesh = fuse(depth, None, est_poses, intrinsics, options).mesh
            keys = []
            for mode in ("sim3", "se3"):
                alignment = fit = pose_alignment(est_poses, gt_poses, mode)
                rows_c[f"{key}/{mode}"] = {"label": f"{label}, {'Sim(3)' if mode == 'sim3' else 'SE(3)'}-aligned",
                                           "poses": "estimated", "align": mode, "align_scale": fit["scale"],
                                           **mesh_scores(mesh, reference, points, alignment),
                                           "seconds": time.perf_counter() - start}
                keys.append(f"{key}/{mode}")
        for k in keys:
            say(f"  C {rows_c[k]['label']}: F {rows_c[k]['fscore']:.3f} (P {rows_c[k]['precision']:.3f}, "
                f"R {rows_c[k]['recall']:.3f})")


def mesh_refinement(rec: Recording, options, reference, points: int, rows_c: dict) -> None:
    """Table C's rows for the refinement, fused as the pipeline fuses it.

    Reconstructed pixels with given poses, also filled pixels near evidence with estimated
    ones (frames it could not support whole), in the poses it ran with.
    """
    gt_poses, intrinsics = rec.gt_poses, rec.intrinsics
    refine_meshes = [("gt", "refine", "MVS refinement [default], polished GT poses"),
                     ("gt", "medea", "MEDeA-S [fast], polished GT poses"),
                     ("gt raw", "refined", "MVS refinement, GT poses not polished"),
                     ("est", "refined", "MVS refinement [default], estimated poses"),
                     ("est", "medea", "MEDeA-S [fast], estimated poses, undistorted (as the pipeline)")]
    for run_key, depth_key, label in refine_meshes:
        run = rec.refine_runs.get(run_key)
        if run is None:
            continue
        start = time.perf_counter()
        confidence = run["confidence"] if depth_key != "medea" else None
        depth = run["refined"] if depth_key != "medea" else run["medea"]
        # The pipeline's fusion threshold for where the poses came from (recon.core.refine).
        threshold = default_min_confidence(not run_key.startswith("gt"))
        mesh = fuse(depth, None, run["poses"], intrinsics, replace(options, min_confidence=threshold),
                    confidence=confidence).mesh
        modes = ("none",) if run_key.startswith("gt") else ("sim3", "se3", "sim3+icp")
        names = {"sim3": "Sim(3)", "se3": "SE(3)", "sim3+icp": "Sim(3)+ICP"}
        for mode in modes:
            alignment = None if mode == "none" else pose_alignment(run["poses"], gt_poses, mode.removesuffix("+icp"))
            key = f"{run_key}/{depth_key}/{mode}"
            suffix = "" if mode == "none" else f", {names[mode]}-aligned"
            rows_c[key] = {"label": label + suffix, "poses": run_key, "align": mode,
                           **mesh_scores(mesh, reference, points, alignment, icp=mode.endswith("+icp")),
                           "seconds": time.perf_counter() - start}
            say(f"  C {rows_c[key]['label']}: F {rows_c[key]['fscore']:.3f} (P {rows_c[key]['precision']:.3f}, "
                f"R {rows_c[key]['recall']:.3f})")


def check_pipeline_depth(rec: Recording) -> None:
    """Sanity: the GT-pose pipeline's depth (MEDeA-S, fast) equals table A's MEDeA-S row."""
    run = rec.pipeline_runs.get("gt")
    if run is None or "error" in run or run["indices"] != rec.indices.tolist() or rec.quick:
        return
    files = sorted((Path(run["output"]) / "depth").glob("*.npy"))
    if len(files) != len(rec.rgb):
        return
    pipeline_depth = np.stack([np.load(f) for f in files])
    ours = rec.refine_runs["gt"]["refined"]
    if pipeline_depth.shape == ours.shape:
        rec.record["pipeline_vs_table_a_S_max_abs_diff_m"] = float(np.abs(pipeline_depth - ours).max())
        pipe_scores = depth_scores(pipeline_depth, rec.refine_runs["gt"]["truth"], rec.gt_poses, rec.intrinsics)
        rec.record["pipeline_gt_abs_rel"] = pipe_scores["abs_rel"]
