"""MEDeA on the synthetic room: accuracy before/after, epochs per stage, seconds per frame.

    python benchmarks/medea_synthetic.py [--frames 120] [--device cpu] [--threads 2]
        [--presets paper fast] [--strides 3 4 6]

Presets: "paper" (MedeaConfig(), the paper's settings), "fast" (MedeaConfig.fast()), and
"fast-sK" for each --strides K: the fast preset scoring every K-th pixel per step, to show
what the pixel stride costs in accuracy.

Prints a table and writes benchmarks/results/medea_synthetic.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, table, write_json  # noqa: E402

from medea_core import MedeaConfig  # noqa: E402
from recon.commands.demo import depth_report  # noqa: E402
from recon.core.medea import adjust_sequence  # noqa: E402
from recon.synthetic import render_sequence, simulate_prior  # noqa: E402


def preset_config(name: str, device: str) -> MedeaConfig:
    if name == "paper":
        return MedeaConfig(device=device)
    if name == "fast":
        return MedeaConfig.fast(device=device)
    stride = int(name.removeprefix("fast-s"))
    return MedeaConfig.fast(device=device, pixel_stride=stride, feature_stride=stride)


def run_preset(name: str, seq, prior, device: str) -> dict:
    config = preset_config(name, device)
    start = time.perf_counter()
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=config, progress=False)
    total = time.perf_counter() - start
    return {
        "config": config.to_dict(),
        "keyframes": len(result.keyframes),
        "epochs": {k: h.epochs for k, h in result.history.items()},
        "stopped_early": {k: h.stopped_early for k, h in result.history.items()},
        "seconds": {**result.seconds, "total": total},
        "seconds_per_frame": total / len(prior),
        "after": depth_report(result.depth.numpy(), seq.depth, seq.poses, seq.intrinsics),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--presets", nargs="+", default=["paper", "fast"], choices=["paper", "fast"])
    parser.add_argument("--strides", nargs="*", type=int, default=[3, 4, 6],
                        help="also run the fast preset at these pixel strides")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    seq = render_sequence(num_frames=args.frames, width=args.width, height=args.height, seed=args.seed)
    prior = simulate_prior(seq.depth, seed=args.seed)
    before = depth_report(prior, seq.depth, seq.poses, seq.intrinsics)
    names = list(args.presets) + [f"fast-s{k}" for k in args.strides]
    runs = {name: run_preset(name, seq, prior, args.device) for name in names}

    n = args.frames
    print(f"MEDeA on the synthetic room: {n} frames at {args.width}x{args.height}, device {args.device}, "
          f"{args.threads} torch threads, {machine()['cpu']}")
    rows = []
    for name, run in runs.items():
        for step in ("prepare", "stage1", "propagate", "stage2", "total"):
            epochs = run["epochs"].get(step, "-")
            seconds = run["seconds"][step]
            rows.append([name, step, epochs, f"{seconds:.2f}", f"{seconds / n:.4f}"])
    print(table(["preset", "step", "epochs", "seconds", "s/frame"], rows))
    print()
    keys = ["abs_rel", "abs_diff", "sq_rel", "rmse", "delta1", "inconsistency"]
    headers = ["metric", "prior"] + [f"MEDeA {name}" for name in runs]
    rows = [[k, f"{before[k]:.4f}"] + [f"{run['after'][k]:.4f}" for run in runs.values()] for k in keys]
    print(table(headers, rows))
    path = write_json("medea_synthetic", {
        "machine": machine(),
        "frames": n,
        "size": [args.height, args.width],
        "device": args.device,
        "before": before,
        "runs": runs,
    })
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
