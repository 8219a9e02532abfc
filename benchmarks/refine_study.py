"""The refinement study: pose polish and multi-view stereo settings on every recording.

For each recording and frame selection (7-Scenes every 4th / every 8th / the second half,
TUM every frame / every 2nd, the synthetic room with a simulated prior), the poses are
taken as given (raw), polished (``recon.poses.given.polish``: defaults, with the lens, other tie
strengths, without the gate) or estimated (``recon.poses.estimate_poses``); MEDeA (fast preset, FastDepth
features) runs on them, then the refinement (``mvs_core``) with each settings variant.
Scores: metric abs rel of the full-coverage depth against the sensor, the reconstructed
share and its abs rel, and the F-score at 5 cm of the TSDF mesh (fused as the pipeline
fuses: reconstructed pixels, unsupported frames whole) against the sensor-depth mesh
(estimated poses: fused in their frame, moved by the Sim(3) of the camera poses, as
benchmarks/report.py does). Rows without refinement (MEDeA alone) are the baseline.

    python benchmarks/refine_study.py                                   # everything (~30 min)
    python benchmarks/refine_study.py --sets 7s4 tum1 --poses polish --variants default half
    python benchmarks/refine_study.py --sets syn --poses raw polish nolens

Prints a table, writes benchmarks/results/refine_study.json (merged by set, poses, variant).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import RESULTS, machine, say, table, write_json  # noqa: E402

from medea_core import MedeaConfig  # noqa: E402
from mvs_core import MvsConfig  # noqa: E402
from recon.core.medea import adjust_sequence  # noqa: E402
from recon.core.refine import (  # noqa: E402
    FILLED_CONFIDENCE,
    MIN_CONFIDENCE_GIVEN,
    default_min_confidence,
    fusion_confidence,
    refine_sequence,
)
from recon.eval.depth import depth_metrics  # noqa: E402
from recon.eval.mesh import mesh_metrics  # noqa: E402
from recon.eval.trajectory import move_points, pose_alignment  # noqa: E402
from recon.fusion import FusionOptions, auto_voxel_size, fuse  # noqa: E402
from recon.geometry.lens import undistort_features, undistort_images, worth_undistorting  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.poses.given.polish import PolishConfig, polish_poses  # noqa: E402
from recon.priors import make_prior  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
MAX_DEPTH = 10.0
# name -> (folder, stride, first, last): frame selections of the real recordings.
SETS = {
    "7s4": ("7scenes-redkitchen", 4, 0, 400),
    "7s8": ("7scenes-redkitchen", 8, 0, 400),
    "7s2h": ("7scenes-redkitchen", 2, 200, 400),
    "tum1": ("tum-fr1-rpy", 1, 0, 100),
    "tum2": ("tum-fr1-rpy", 2, 0, 100),
    "syn": (None, 1, 0, 60),
}
# Pose variants: given poses as they are, polished (PolishConfig overrides), or estimated.
POLISH = {"polish": {}, "nolens": {"calibrate_lens": False}, "tie3": {"pose_weight": 1e-3},
          "tie5": {"pose_weight": 1e-5}, "always": {"min_gain": 0.0}}
POSES = ("raw", *POLISH, "estimate", "estimate+polish")
VARIANTS = {
    "default": {},
    "half": {"image_scale": 0.5, "hypotheses": 24},
    "s4": {"num_sources": 4, "keep_best": 2},
    "min3": {"min_consistent": 3},
    "tau1": {"consistency_depth": 0.01},
    "band6": {"band": 0.6, "hypotheses": 30},
}


# Fusion policies: which pixels of a refined frame reach the TSDF, as thresholds on
# recon.core.refine.fusion_confidence (filled pixels: FILLED_CONFIDENCE x support); "pipeline":
# the pipeline's default for the pose source; "share0.15": reconstructed pixels, and frames
# under 15 % reconstructed whole.
FUSION = {"pipeline": None, "rec": MIN_CONFIDENCE_GIVEN, "all": 0.0, "sup0.3": 0.3 * FILLED_CONFIDENCE,
          "sup0.1": 0.1 * FILLED_CONFIDENCE, "share0.15": MIN_CONFIDENCE_GIVEN}


def policy_confidence(result, policy: str) -> np.ndarray:
    confidence = fusion_confidence(result)
    if policy == "share0.15":
        weak = result.stats["reconstructed"].numpy() < 0.15
        confidence[weak] = (result.depth.numpy()[weak] > 0).astype(np.float32)
    return confidence


def load_set(name: str):
    """rgb (N, H, W, 3), sensor depth (N, H, W), poses (N, 4, 4), intrinsics (4,), prior, features."""
    folder, stride, first, last = SETS[name]
    if folder is None:
        from recon.synthetic import render_sequence
        from recon.synthetic.prior import simulate_prior

        seq = render_sequence(last - first, 640, 480, seed=0)
        prior = simulate_prior(seq.depth, seed=0)
        return seq.rgb, seq.depth, seq.poses, np.asarray(seq.intrinsics), prior, None
    dataset = open_dataset(DATA / folder).with_valid_poses()
    dataset = dataset.subset(np.arange(first, min(last, len(dataset)), stride))
    rgb, gt = dataset.load_rgb_batch(), dataset.load_depth_batch()
    intrinsics = np.asarray(dataset.intrinsics, np.float64)
    prior = make_prior("fastdepth", features=True, progress=False)(rgb, intrinsics)
    return rgb, gt, np.asarray(dataset.poses, np.float64), intrinsics, prior.depth, prior.features


def pose_variant(kind: str, rgb, prior, poses, intrinsics):
    """(poses, lens k1, info) for a pose variant."""
    if kind == "raw":
        return poses, 0.0, {}
    if kind in POLISH:
        result = polish_poses(rgb, prior, poses, tuple(intrinsics), replace(PolishConfig(), **POLISH[kind]),
                              progress=False)
        return result.poses, result.lens_k1, {k: v for k, v in result.info.items() if k != "config"}
    from recon.poses import estimate_poses

    result = estimate_poses(rgb, prior, intrinsics=tuple(intrinsics), method="auto", progress=False)
    poses, k1 = np.asarray(result.poses), float(result.diagnostics.get("lens_k1", 0.0))
    if kind == "estimate":
        return poses, k1, {"seconds": result.seconds}
    # The estimate polished as given poses are (the lens calibrated afresh on the raw frames).
    polished = polish_poses(rgb, prior, poses, tuple(intrinsics), PolishConfig(), progress=False)
    info = {k: v for k, v in polished.info.items() if k != "config"}
    return polished.poses, polished.lens_k1, {"seconds": result.seconds, "polish": info}


def mesh_score(depth, poses, intrinsics, reference, voxel, confidence=None, alignment=None,
               min_confidence: float | None = None) -> dict:
    options = FusionOptions(voxel_size=voxel, max_depth=MAX_DEPTH, progress=False, min_confidence=min_confidence)
    mesh = fuse(depth, None, poses, intrinsics, options, confidence=confidence).mesh
    vertices = move_points(np.asarray(mesh.vertices), alignment)
    scores = mesh_metrics((vertices, np.asarray(mesh.triangles)), reference, num_points=200_000).to_dict()
    return {k: scores[k] for k in ("fscore", "precision", "recall", "accuracy", "completeness")}


def run_set(name: str, pose_kinds, variants, threads: int, fusions=("pipeline",)) -> list[dict]:
    torch.set_num_threads(threads)
    say(f"{name}: loading")
    rgb, gt, gt_poses, intrinsics, prior, features = load_set(name)
    voxel = auto_voxel_size(float(np.median(gt[(gt > 0) & (gt <= MAX_DEPTH)])))
    reference = fuse(gt, None, gt_poses, intrinsics, FusionOptions(voxel_size=voxel, max_depth=MAX_DEPTH,
                                                                   progress=False)).mesh
    rows = []
    for kind in pose_kinds:
        say(f"{name}: poses {kind}")
        start = time.perf_counter()
        poses, k1, pose_info = pose_variant(kind, rgb, prior, gt_poses, intrinsics)
        pose_seconds = time.perf_counter() - start
        K = tuple(intrinsics)
        lens = worth_undistorting(K, rgb.shape[1:3], k1)
        frames = undistort_images(rgb, K, k1) if lens else rgb
        p_depth = undistort_images(prior, K, k1, nearest=True) if lens else prior
        feats = undistort_features(features, K, rgb.shape[1:3], k1) if lens and features is not None \
            else features
        truth = undistort_images(gt, K, k1, nearest=True) if lens else gt
        estimated = kind.startswith("estimate")
        alignment = pose_alignment(poses, gt_poses, "sim3") if estimated else None
        align_mode = "median_sequence" if estimated else "none"
        start = time.perf_counter()
        medea = adjust_sequence(frames, p_depth, poses, K, feats, MedeaConfig.fast(), progress=False).depth.numpy()
        medea_seconds = time.perf_counter() - start
        base = {"set": name, "poses": kind, "lens_k1": k1, "pose_seconds": pose_seconds, "pose_info": pose_info,
                "frames": len(rgb)}
        m = depth_metrics(medea, truth, max_depth=MAX_DEPTH, align=align_mode)
        row = {**base, "variant": "MEDeA only", "abs_rel": m["abs_rel"], "seconds_per_frame": medea_seconds / len(rgb),
               **mesh_score(medea, poses, K, reference, voxel, alignment=alignment)}
        rows.append(row)
        say(f"  MEDeA: abs rel {row['abs_rel']:.4f} F {row['fscore']:.3f}")
        for variant in variants:
            config = replace(MvsConfig(), **VARIANTS[variant])
            start = time.perf_counter()
            result = refine_sequence(frames, medea, poses, K, config, progress=False)
            seconds = time.perf_counter() - start
            depth = result.depth.numpy()
            full = depth_metrics(depth, truth, max_depth=MAX_DEPTH, align=align_mode)
            rec = depth_metrics(np.where(result.reconstructed.numpy(), depth, 0), truth, max_depth=MAX_DEPTH,
                                align=align_mode)
            for fusion in fusions:
                label = variant if fusion == "pipeline" else f"{variant}/{fusion}"
                threshold = default_min_confidence(estimated) if FUSION[fusion] is None else FUSION[fusion]
                row = {**base, "variant": label, "overrides": VARIANTS[variant], "fusion": fusion,
                       "abs_rel": full["abs_rel"], "reconstructed": float(result.reconstructed.float().mean()),
                       "abs_rel_reconstructed": rec["abs_rel"], "unsupported_frames": int(result.unsupported.sum()),
                       "seconds_per_frame": seconds / len(rgb),
                       "min_confidence": threshold,
                       **mesh_score(depth, poses, K, reference, voxel, policy_confidence(result, fusion), alignment,
                                    threshold)}
                rows.append(row)
                say(f"  {label}: abs rel {row['abs_rel']:.4f} (reconstructed {row['reconstructed']:.2f}: "
                    f"{row['abs_rel_reconstructed']:.4f}) F {row['fscore']:.3f} P {row['precision']:.3f} "
                    f"R {row['recall']:.3f}; {row['seconds_per_frame']:.3f} s/frame")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sets", nargs="+", default=list(SETS), choices=list(SETS))
    parser.add_argument("--poses", nargs="+", default=["raw", "polish", "estimate"], choices=list(POSES))
    parser.add_argument("--variants", nargs="+", default=["default"], choices=list(VARIANTS))
    parser.add_argument("--fusion", nargs="+", default=["pipeline"], choices=list(FUSION),
                        help="fusion policies scored per refinement (pipeline: the pipeline's default)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    path = RESULTS / "refine_study.json"
    old = json.loads(path.read_text()) if path.is_file() else {"rows": []}
    rows = []
    for name in args.sets:
        if SETS[name][0] is not None and not (DATA / SETS[name][0]).is_dir():
            say(f"{name}: {DATA / SETS[name][0]} not found, skipped")
            continue
        rows += run_set(name, args.poses, args.variants, args.threads, args.fusion)
    keys = {(r["set"], r["poses"], r["variant"]) for r in rows}
    merged = [r for r in old["rows"] if (r["set"], r["poses"], r["variant"]) not in keys] + rows
    headers = ["set", "poses", "variant", "abs rel", "reconstr.", "abs rel (rec.)", "F@5cm", "P", "R", "s/frame"]
    print(table(headers, [[r["set"], r["poses"], r["variant"], f"{r['abs_rel']:.4f}",
                           f"{r.get('reconstructed', 1.0):.2f}", f"{r.get('abs_rel_reconstructed', r['abs_rel']):.4f}",
                           f"{r['fscore']:.3f}", f"{r['precision']:.3f}", f"{r['recall']:.3f}",
                           f"{r['seconds_per_frame']:.3f}"] for r in rows]))
    print(f"machine: {machine()}")
    write_json("refine_study", {"machine": machine(), "rows": merged})


if __name__ == "__main__":
    main()
