"""FastDepth preprocessing options on real RGB-D recordings: accuracy and speed.

    python benchmarks/fastdepth_preprocessing.py [--step7 10] [--steptum 4] [--threads 2]

For each option (network input size / crop, focal-length normalisation, input resampling)
runs the FastDepth prior on a subsample of ../shared/data/7scenes-redkitchen and
../shared/data/tum-fr1-rpy, scores the full-resolution output against sensor depth
(metric, and per-frame median scaled), times it, prints a table and writes
benchmarks/results/fastdepth_preprocessing.json.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import best_ms_per_item, machine, table, write_json  # noqa: E402

from recon.eval.depth import depth_metrics  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.priors import FastDepthPrior  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MAX_DEPTH = 10.0  # Kinect v1 range; farther readings are unreliable

# name -> FastDepthPrior options. Fixed sizes are multiples of 32 (the network's stride).
OPTIONS = {
    "nyu_crop224+focal_fill": dict(resize="nyu_crop"),
    "focal": dict(resize="focal"),
    "focal/nearest": dict(resize="focal", interpolation="nearest"),
    "128x160": dict(resize="128x160"),
    "224x224": dict(resize="224x224"),
    "256x256": dict(resize="256x256"),
    "224x288": dict(resize="224x288"),
    "256x320": dict(resize="256x320"),
    "480x640": dict(resize="480x640"),
}


def load(folder: str, step: int):
    """RGB (N, 480, 640, 3) uint8, sensor depth (N, 480, 640) metres, intrinsics (4,)."""
    dataset = open_dataset(DATA / folder).select(stride=step)
    return dataset.load_rgb_batch(), dataset.load_depth_batch(), np.asarray(dataset.intrinsics)


def ms_per_frame(prior: FastDepthPrior, rgb: np.ndarray, intrinsics, repeats: int = 5) -> float:
    """End to end (uint8 frames in, full-size depth out) over one batch, best of ``repeats``."""
    batch = rgb[: prior.batch_size]
    return best_ms_per_item(lambda: prior(batch, intrinsics), len(batch), repeats)


# Speed settings: (label, FastDepthPrior options); frames are 640x480 7-Scenes (fx = 585).
SPEED = [
    ("default (focal -> 224x224), batch 8", dict(batch_size=8)),
    ("default, batch 1", dict(batch_size=1)),
    ("default, NCHW (no channels-last)", dict(batch_size=8, channels_last=False)),
    ("default + stride-8 features", dict(batch_size=8, features=True)),
    ("default + stride-4 features", dict(batch_size=8, features=True, feature_layer="stride4")),
    ("480x640, batch 8", dict(batch_size=8, resize="480x640")),
    ("480x640, batch 1", dict(batch_size=1, resize="480x640")),
    ("480x640, NCHW", dict(batch_size=8, resize="480x640", channels_last=False)),
    ("480x640 + stride-8 features", dict(batch_size=8, resize="480x640", features=True)),
]


def speed(rgb: np.ndarray, intrinsics, rounds: int = 3) -> dict[str, float]:
    """ms/frame per SPEED setting: best over ``rounds`` interleaved rounds (load changes over time)."""
    priors = {label: FastDepthPrior(progress=False, **options) for label, options in SPEED}
    best: dict[str, float] = {}
    for _ in range(rounds):
        for label, prior in priors.items():
            value = ms_per_frame(prior, rgb, intrinsics, repeats=2)
            best[label] = min(best.get(label, np.inf), value)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step7", type=int, default=10, help="every k-th 7-Scenes frame (400 in all)")
    parser.add_argument("--steptum", type=int, default=4, help="every k-th TUM frame (100 in all)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--options", nargs="*", default=list(OPTIONS))
    parser.add_argument("--no-speed", action="store_true", help="skip the speed table")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if not DATA.is_dir():
        sys.exit(f"{DATA} not found")

    datasets = {"7scenes": load("7scenes-redkitchen", args.step7), "tum": load("tum-fr1-rpy", args.steptum)}
    results = {}
    for name in args.options:
        for scaling in (False, True):
            label = f"{name}{' +fscale' if scaling else ''}"
            prior = FastDepthPrior(**OPTIONS[name], focal_scaling=scaling, batch_size=args.batch, progress=False)
            row = {"options": {**OPTIONS[name], "focal_scaling": scaling}}
            for dname, (rgb, gt, intrinsics) in datasets.items():
                out = prior(rgb, intrinsics)
                metric = depth_metrics(out.depth, gt, max_depth=MAX_DEPTH)
                scaled = depth_metrics(out.depth, gt, max_depth=MAX_DEPTH, align="median_frame")
                row[dname] = {
                    "frames": len(rgb),
                    "network_input": list(out.info["network_input"]),
                    "metric": {k: metric[k] for k in ("abs_rel", "abs_diff", "delta1", "coverage")},
                    "median_scaled": {k: scaled[k] for k in ("abs_rel", "abs_diff", "delta1")},
                    "gt_over_pred_median": scaled["scale"],
                }
            # Focal scaling is one multiplication: time only the scaled variant.
            if scaling:
                row["ms_per_frame"] = ms_per_frame(prior, datasets["7scenes"][0], datasets["7scenes"][2])
            else:
                row["ms_per_frame"] = None
            row["mean_metric_abs_rel"] = float(np.mean([row[d]["metric"]["abs_rel"] for d in datasets]))
            results[label] = row
            print(f"{label}: 7scenes {row['7scenes']['metric']['abs_rel']:.4f}  "
                  f"tum {row['tum']['metric']['abs_rel']:.4f}", flush=True)

    for label, row in results.items():
        if row["ms_per_frame"] is None:
            row["ms_per_frame"] = results[f"{label} +fscale"]["ms_per_frame"]
    headers = ["option", "net input (7s/tum)", "7s absrel", "7s absdiff", "7s d1", "7s absrel med", "7s d1 med",
               "tum absrel", "tum absdiff", "tum d1", "tum absrel med", "tum d1 med", "mean absrel", "ms/frame"]
    rows = []
    for label, r in results.items():
        s, t = r["7scenes"], r["tum"]
        rows.append([
            label, f"{'x'.join(map(str, s['network_input']))}/{'x'.join(map(str, t['network_input']))}",
            f"{s['metric']['abs_rel']:.3f}", f"{s['metric']['abs_diff']:.3f}", f"{s['metric']['delta1']:.3f}",
            f"{s['median_scaled']['abs_rel']:.3f}", f"{s['median_scaled']['delta1']:.3f}",
            f"{t['metric']['abs_rel']:.3f}", f"{t['metric']['abs_diff']:.3f}", f"{t['metric']['delta1']:.3f}",
            f"{t['median_scaled']['abs_rel']:.3f}", f"{t['median_scaled']['delta1']:.3f}",
            f"{r['mean_metric_abs_rel']:.3f}", f"{r['ms_per_frame']:.1f}",
        ])
    print(table(headers, rows))
    best = min(results, key=lambda k: results[k]["mean_metric_abs_rel"])
    print(f"lowest mean metric abs rel: {best}")
    timing = {} if args.no_speed else speed(datasets["7scenes"][0], datasets["7scenes"][2])
    if timing:
        print(table(["setting (7-Scenes 640x480 frames, end to end)", "ms/frame"],
                    [[label, f"{value:.1f}"] for label, value in timing.items()]))
    path = write_json("fastdepth_preprocessing", {
        "machine": {**machine(), "load_average_at_end": os.getloadavg()},
        "data": {"7scenes": f"every {args.step7}th of 400 frames", "tum": f"every {args.steptum}th of 100 frames"},
        "max_depth": MAX_DEPTH,
        "batch_size": args.batch,
        "results": results,
        "speed_ms_per_frame": timing,
        "best_by_mean_metric_abs_rel": best,
    })
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
