"""Depth priors on real RGB-D recordings: CPU time per frame, and accuracy before/after MEDeA.

    python benchmarks/priors.py [--datasets 7scenes tum] [--step7 4] [--steptum 2] [--preset fast]
                                [--variants none S8 S4 M8 M4] [--no-speed] [--no-medea]

Speed: end-to-end CPU time per frame of each prior at its default resolution (uint8
frames in, full-size depth out), best of a few rounds (the machine may be shared).

Accuracy: on subsampled ../shared/data/7scenes-redkitchen and tum-fr1-rpy, the FastDepth
prior and MEDeA (ground-truth poses) with each feature variant, scored against sensor
depth: abs rel, abs diff, delta<1.25, metric and per-frame median scaled, plus the
multi-view inconsistency. Two oracle rows bound what MEDeA's model can reach: the prior
times each frame's true median scale, and times the 8x10 log-scale grid pooled from the
ground truth (the best grid in MEDeA's own sense).

Results merge into benchmarks/results/priors.json (keyed by dataset and row), so the
datasets can be run separately.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, best_ms_per_item, machine, table, write_json  # noqa: E402

from medea_core import MedeaConfig, adjust_depth, median_pool_to_grid  # noqa: E402
from recon.core.medea import adjust_sequence  # noqa: E402
from recon.eval.depth import depth_metrics, multiview_inconsistency  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.io.datasets.sevenscenes import DEPTH_INTRINSICS  # noqa: E402
from recon.priors import FastDepthPrior, make_prior  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FOLDERS = {"7scenes": "7scenes-redkitchen", "tum": "tum-fr1-rpy"}
MAX_DEPTH = 10.0  # Kinect v1 range; farther readings are unreliable

# MEDeA rows: label -> (FastDepth feature layer or None, MedeaConfig overrides).
VARIANTS = {
    "none": (None, {}),
    "S8": ("stride8", {"feature_loss": "S"}),
    "S4": ("stride4", {"feature_loss": "S"}),
    "M8": ("stride8", {"feature_loss": "M"}),
    "M4": ("stride4", {"feature_loss": "M"}),
    "S8-photo": ("stride8", {"feature_loss": "S", "use_photometric": False}),
    "S8-depth": ("stride8", {"feature_loss": "S", "use_depth": False}),
    "photo": (None, {"use_depth": False}),
}
VARIANT_TEXT = {
    "none": "MEDeA, no feature term",
    "S8": "MEDeA-S, stride-8 features",
    "S4": "MEDeA-S, stride-4 features",
    "M8": "MEDeA-M, stride-8 features",
    "M4": "MEDeA-M, stride-4 features",
    "S8-photo": "MEDeA-S (stride 8) w/o photometric",
    "S8-depth": "MEDeA-S (stride 8) w/o depth",
    "photo": "MEDeA, photometric term only",
}


def load(name: str, step: int, colour_focal: float | None = None):
    """Frames (N, H, W, 3) uint8, sensor depth (N, H, W) m, GT poses (N, 4, 4), intrinsics (4,).

    colour_focal: 7-Scenes colour focal length overriding the reader's (525 px); the sensor
    depth is re-registered into that colour camera by the reader.
    """
    options = {"colour_intrinsics": (colour_focal, colour_focal, 320.0, 240.0)} if colour_focal else {}
    dataset = open_dataset(DATA / FOLDERS[name], **options).with_valid_poses().select(stride=step)
    rgb, depth, intrinsics = dataset.load_rgb_batch(), dataset.load_depth_batch(), np.asarray(dataset.intrinsics)
    return rgb, depth, dataset.poses, intrinsics


def scores(depth: np.ndarray, gt: np.ndarray, poses, intrinsics) -> dict:
    metric = depth_metrics(depth, gt, max_depth=MAX_DEPTH)
    scaled = depth_metrics(depth, gt, max_depth=MAX_DEPTH, align="median_frame")
    keys = ("abs_rel", "abs_diff", "delta1")
    return {
        "metric": {k: metric[k] for k in (*keys, "coverage")},
        "median_scaled": {k: scaled[k] for k in keys},
        "gt_over_pred_median": scaled["scale"],
        "inconsistency": multiview_inconsistency(torch.from_numpy(depth), torch.from_numpy(poses),
                                                 torch.as_tensor(intrinsics, dtype=torch.float32)),
    }


def oracles(prior: np.ndarray, gt: np.ndarray, grid=(8, 10)) -> dict[str, np.ndarray]:
    """The prior corrected with ground truth: per-frame median scale, and the pooled log-scale grid."""
    valid = (gt > 0) & (gt <= MAX_DEPTH) & (prior > 0)
    ratio = torch.from_numpy(np.where(valid, gt / np.where(valid, prior, 1.0), 1.0)).float()
    mask = torch.from_numpy(valid)
    per_frame = np.array([np.median(r[m]) if m.any() else 1.0 for r, m in zip(ratio.numpy(), valid)])
    log_grid = median_pool_to_grid(ratio, mask, grid).log()
    return {
        "oracle: per-frame scale": prior * per_frame[:, None, None].astype(np.float32),
        "oracle: 8x10 grid": adjust_depth(torch.from_numpy(prior), log_grid).numpy(),
    }


def medea_config(preset: str, overrides: dict) -> MedeaConfig:
    config = MedeaConfig.fast() if preset == "fast" else MedeaConfig()
    for key, value in overrides.items():
        setattr(config, key, value)
    return config


def accuracy(name: str, step: int, preset: str, variants: list[str], results: dict,
             colour_focal: float | None = None) -> None:
    rgb, gt, poses, intrinsics = load(name, step, colour_focal)
    label = name if not colour_focal else f"{name} (colour fx {colour_focal:g})"
    priors = {layer: FastDepthPrior(features=True, feature_layer=layer, progress=False)
              for layer in ("stride8", "stride4")}
    outputs = {layer: prior(rgb, intrinsics) for layer, prior in priors.items()}
    base = outputs["stride8"]
    common = {"frames": len(rgb), "every": step, "network_input": list(base.info["network_input"]),
              "intrinsics": intrinsics.tolist()}

    def record(row: str, depth: np.ndarray, extra: dict) -> None:
        results[f"{label}/{row}"] = r = {"dataset": label, "row": row, **common, **extra,
                                         **scores(depth, gt, poses, intrinsics)}
        print(f"{label} {row}: abs rel {r['metric']['abs_rel']:.4f} (median scaled {r['median_scaled']['abs_rel']:.4f})"
              f" inconsistency {r['inconsistency']:.4f}", flush=True)

    record("prior", base.depth, {})
    for row, depth in oracles(base.depth, gt).items():
        record(row, depth, {})
    for variant in variants:
        layer, overrides = VARIANTS[variant]
        config = medea_config(preset, overrides)
        features = None if layer is None else outputs[layer].features
        result = adjust_sequence(rgb, base.depth, poses, intrinsics, features=features, config=config, progress=False)
        depth = result.depth.numpy() if isinstance(result.depth, torch.Tensor) else np.asarray(result.depth)
        record(variant if preset == "fast" else f"{variant} ({preset})", depth, {
            "preset": preset, "feature_layer": layer,
            "feature_channels": None if features is None else int(features.shape[1]),
            "seconds_per_frame": sum(result.seconds.values()) / len(rgb), "seconds": result.seconds,
            "epochs": {stage: h.epochs for stage, h in result.history.items()},
        })
        save(results, {})


# ---------------------------------------------------------------------------- speed


def speed(hf_model: str | None) -> dict[str, float]:
    dataset = open_dataset(DATA / FOLDERS["7scenes"]).select(stride=25, max_frames=8)
    rgb, intrinsics = dataset.load_rgb_batch(), np.asarray(dataset.intrinsics)
    count = len(rgb)
    timings = {}
    for label, options in (
        ("fastdepth (focal -> 224x224)", {}),
        ("fastdepth + stride-8 features", {"features": True}),
        ("fastdepth + stride-4 features", {"features": True, "feature_layer": "stride4"}),
        ("fastdepth at 480x640", {"resize": "480x640"}),
    ):
        prior = FastDepthPrior(batch_size=count, progress=False, **options)
        timings[label] = best_ms_per_item(lambda: prior(rgb, intrinsics), count)

    def sensor():  # reading the 16-bit PNGs is the prior's whole cost
        depth = dataset.load_depth_batch()
        return make_prior("sensor", depth=depth)(rgb)

    timings["sensor (16-bit PNG read)"] = best_ms_per_item(sensor, count)
    with tempfile.TemporaryDirectory() as folder:
        depth = dataset.load_depth_batch()
        for k, d in enumerate(depth):
            np.save(Path(folder) / f"{k:03d}.npy", np.where(d > 0, d, 1.0))
        prior = make_prior("folder", path=folder, progress=False)
        timings["folder (.npy read + checks)"] = best_ms_per_item(lambda: prior(rgb), count)
        prior = make_prior("folder", path=folder, kind="disparity", align_to="fastdepth", progress=False)
        timings["folder disparity aligned to fastdepth"] = best_ms_per_item(lambda: prior(rgb, intrinsics), count)
    if hf_model:
        prior = make_prior("hf", model=hf_model, progress=False)
        timings[f"hf ({Path(hf_model).name})"] = best_ms_per_item(lambda: prior(rgb), count, rounds=1)
    return timings


def colour_focal_check(focals=range(495, 606, 10), gaps=(4, 8, 16)) -> dict[int, float]:
    """Mean colour disagreement on 7-Scenes for each candidate colour focal length.

    3D points from the raw sensor depth (depth camera, fx = 585) are projected
    into the colour images of frames i and i+gap (ground-truth poses) with a candidate
    colour focal; the right focal makes the two colours agree best.
    """
    dataset = open_dataset(DATA / FOLDERS["7scenes"], colour_intrinsics=DEPTH_INTRINSICS).select(stride=2)
    rgb = torch.from_numpy(dataset.load_rgb_batch()).permute(0, 3, 1, 2).float() / 255.0
    depth = torch.from_numpy(dataset.load_depth_batch())[:, ::4, ::4]
    poses = torch.from_numpy(dataset.poses).float()
    fx, fy, cx, cy = dataset.intrinsics
    height, width = rgb.shape[-2:]
    v, u = torch.meshgrid(torch.arange(0, height, 4.0), torch.arange(0, width, 4.0), indexing="ij")
    pairs = torch.tensor([(i, i + g) for g in gaps for i in range(0, len(dataset) - g, 6)])
    i, j = pairs[:, 0], pairs[:, 1]
    z = depth[i].flatten(1)
    points_i = torch.stack([(u.flatten() - cx) / fx * z, (v.flatten() - cy) / fy * z, z], 1)  # (P, 3, M)
    i_to_j = torch.linalg.inv(poses[j]) @ poses[i]
    points_j = i_to_j[:, :3, :3] @ points_i + i_to_j[:, :3, 3:]

    def colours(images, points, f):
        x = (f * points[:, 0] / points[:, 2] + cx) / (width - 1) * 2 - 1
        y = (f * points[:, 1] / points[:, 2] + cy) / (height - 1) * 2 - 1
        grid = torch.stack([x, y], -1)[:, None]
        inside = (grid.abs() <= 1).all(-1)[:, 0]
        return torch.nn.functional.grid_sample(images, grid, align_corners=True)[:, :, 0], inside

    result = {}
    for f in focals:
        c_i, in_i = colours(rgb[i], points_i, f)
        c_j, in_j = colours(rgb[j], points_j, f)
        valid = (z > 0) & (points_j[:, 2] > 0.1) & in_i & in_j
        result[int(f)] = float((c_i - c_j).abs().mean(1)[valid].mean())
    return result


def feature_cost(step: int, preset: str, rounds: int = 3, epochs: tuple[int, int] = (20, 5)) -> dict:
    """Seconds per epoch of each stage with and without the feature term, on 7-Scenes.

    Early stopping makes whole-run times depend on when each variant converges; here every
    variant runs exactly ``epochs`` (stage I, stage II) and the rounds are interleaved so
    that a busy machine slows all variants alike. Best round per variant.
    """
    rgb, _, poses, intrinsics = load("7scenes", step)
    features = {layer: FastDepthPrior(features=True, feature_layer=layer, progress=False)(rgb, intrinsics)
                for layer in ("stride8", "stride4")}
    prior = features["stride8"].depth
    best: dict[str, dict[str, float]] = {}
    for _ in range(rounds):
        for variant in ("none", "S8", "S4", "M8", "M4"):
            layer, overrides = VARIANTS[variant]
            config = medea_config(preset, overrides)
            for stage, count in zip((config.stage1, config.stage2), epochs):
                stage.epochs, stage.patience = count, count + 1
            result = adjust_sequence(rgb, prior, poses, intrinsics, config=config, progress=False,
                                     features=None if layer is None else features[layer].features)
            per_epoch = {stage: h.seconds / h.epochs for stage, h in result.history.items()}
            row = best.setdefault(variant, per_epoch)
            for stage, value in per_epoch.items():
                row[stage] = min(row[stage], value)
    return best


# ---------------------------------------------------------------------------- output


def save(results: dict, timing: dict, cost: dict | None = None) -> Path:
    path = RESULTS / "priors.json"
    payload = json.loads(path.read_text()) if path.is_file() else {}
    payload.setdefault("accuracy", {}).update(results)
    if timing:
        payload["speed_ms_per_frame"] = timing
        payload["speed_machine"] = {**machine(), "load_average_at_end": os.getloadavg()}
    if cost:
        payload["medea_seconds_per_epoch"] = cost
    payload["machine"] = {**machine(), "load_average_at_end": os.getloadavg()}
    payload["max_depth"] = MAX_DEPTH
    return write_json("priors", payload)


def accuracy_table(results: dict) -> str:
    headers = ["dataset (frames)", "row", "abs rel", "abs diff", "d1.25", "abs rel (med)", "abs diff (med)",
               "d1.25 (med)", "inconsist.", "MEDeA s/frame"]
    rows = []
    for r in results.values():
        m, s = r["metric"], r["median_scaled"]
        seconds = r.get("seconds_per_frame")
        label = VARIANT_TEXT.get(r["row"].split(" (")[0], r["row"])
        if "preset" in r:
            label += f" [{r['preset']}]"
        rows.append([f"{r['dataset']} ({r['frames']}, every {r['every']})", label, f"{m['abs_rel']:.3f}",
                     f"{m['abs_diff']:.3f}", f"{100 * m['delta1']:.1f}", f"{s['abs_rel']:.3f}", f"{s['abs_diff']:.3f}",
                     f"{100 * s['delta1']:.1f}", f"{r['inconsistency']:.3f}",
                     "" if seconds is None else f"{seconds:.2f}"])
    return table(headers, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", nargs="*", default=list(FOLDERS), choices=list(FOLDERS))
    parser.add_argument("--step7", type=int, default=4, help="every k-th 7-Scenes frame (400 in all)")
    parser.add_argument("--steptum", type=int, default=2, help="every k-th TUM frame (100 in all)")
    parser.add_argument("--preset", choices=("fast", "paper"), default="fast",
                        help="MedeaConfig.fast() or paper defaults")
    parser.add_argument("--variants", nargs="*", default=["none", "S8", "S4", "M8", "M4"], choices=list(VARIANTS))
    parser.add_argument("--colour-focal7", type=float, default=0.0,
                        help="7-Scenes colour focal (px) overriding the reader's 525; 0: the reader's")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--hf-model", help="a local Hugging Face depth model folder to time as well")
    parser.add_argument("--no-speed", action="store_true")
    parser.add_argument("--no-medea", action="store_true", help="prior and oracle rows only")
    parser.add_argument("--feature-cost", action="store_true", help="time MEDeA epochs with/without features")
    parser.add_argument("--check-focal", action="store_true", help="estimate the 7-Scenes colour focal length")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if not DATA.is_dir():
        sys.exit(f"{DATA} not found")

    timing = {}
    if not args.no_speed:
        timing = speed(args.hf_model)
        print(table(["prior (7-Scenes 640x480 frames, end to end)", "ms/frame"],
                    [[label, f"{value:.1f}"] for label, value in timing.items()]), flush=True)
        save({}, timing)
    if args.check_focal:
        check = colour_focal_check()
        print(table(["7-Scenes colour focal [px]", "mean |I_i - I_j| at sensor-depth points"],
                    [[f, f"{e:.4f}"] for f, e in check.items()]), flush=True)
        payload = json.loads((RESULTS / "priors.json").read_text()) if (RESULTS / "priors.json").is_file() else {}
        write_json("priors", {**payload, "7scenes_colour_focal_check": check})
    if args.feature_cost:
        cost = feature_cost(args.step7, args.preset)
        print(table(["MEDeA variant (7-Scenes)", "stage I s/epoch", "stage II s/epoch"],
                    [[VARIANT_TEXT[v], f"{c['stage1']:.3f}", f"{c['stage2']:.3f}"] for v, c in cost.items()]),
              flush=True)
        save({}, {}, {"preset": args.preset, "every": args.step7, **cost})
    results: dict = {}
    for name in args.datasets:
        step = args.step7 if name == "7scenes" else args.steptum
        focal = args.colour_focal7 if name == "7scenes" else None
        accuracy(name, step, args.preset, [] if args.no_medea else args.variants, results, focal)
    path = save(results, {})
    print(accuracy_table(json.loads(path.read_text())["accuracy"]))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
