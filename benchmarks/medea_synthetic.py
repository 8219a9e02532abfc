"""MEDeA on the synthetic room: accuracy before/after, epochs per stage, seconds per frame.

    python benchmarks/medea_synthetic.py [--frames 120] [--device cpu] [--threads 2]

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
from recon.demo import depth_report  # noqa: E402
from recon.medea import adjust_sequence  # noqa: E402
from recon.synthetic import render_sequence, simulate_prior  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    seq = render_sequence(num_frames=args.frames, width=args.width, height=args.height, seed=args.seed)
    prior = simulate_prior(seq.depth, seed=args.seed)
    config = MedeaConfig(device=args.device)
    start = time.perf_counter()
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=config, progress=False)
    total = time.perf_counter() - start
    before = depth_report(prior, seq.depth, seq.poses, seq.intrinsics)
    after = depth_report(result.depth.numpy(), seq.depth, seq.poses, seq.intrinsics)

    n = args.frames
    stages = [["prepare", "-", f"{result.seconds['prepare']:.2f}", f"{result.seconds['prepare'] / n:.4f}"]]
    for name in ("stage1", "propagate", "stage2"):
        epochs = result.history[name].epochs if name in result.history else "-"
        stages.append([name, epochs, f"{result.seconds[name]:.2f}", f"{result.seconds[name] / n:.4f}"])
    stages.append(["total (incl. conversion)", "-", f"{total:.2f}", f"{total / n:.4f}"])
    print(f"MEDeA on the synthetic room: {n} frames at {args.width}x{args.height}, device {args.device}, "
          f"{args.threads} threads, {len(result.keyframes)} keyframes")
    print(table(["step", "epochs", "seconds", "s/frame"], stages))
    print()
    keys = ["abs_rel", "abs_diff", "sq_rel", "rmse", "delta1", "inconsistency"]
    rows = [[k, f"{before[k]:.4f}", f"{after[k]:.4f}", f"{(after[k] - before[k]) / before[k]:+.0%}"] for k in keys]
    print(table(["metric", "prior", "MEDeA", "change"], rows))
    path = write_json("medea_synthetic", {
        "machine": machine(),
        "frames": n,
        "size": [args.height, args.width],
        "device": args.device,
        "config": config.to_dict(),
        "keyframes": len(result.keyframes),
        "epochs": {k: h.epochs for k, h in result.history.items()},
        "stopped_early": {k: h.stopped_early for k, h in result.history.items()},
        "seconds": {**result.seconds, "total": total},
        "seconds_per_frame": total / n,
        "before": before,
        "after": after,
    })
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
