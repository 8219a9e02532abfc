"""The refinement (``mvs_core``) on CPU and on CUDA: seconds per frame and agreement.

The refinement is pure torch, so it runs wherever torch does; this script times it per
device on one recorded input and checks that the devices agree (same reconstructed pixels,
same depth up to float rounding). It needs neither open3d nor ``../shared`` at run time,
so the input travels to a GPU machine as one file:

    python benchmarks/refine_device.py --make-input out/refine_input.npz        # here, needs ../shared
    python benchmarks/refine_device.py --input out/refine_input.npz --devices cpu cuda

The input holds MEDeA's depth (fast preset, FastDepth features, ground-truth poses) of
7-Scenes redkitchen, every 4th frame of 0-399, stored at half size (depth float16) to stay
small; it is brought back to the full 640x480 (nearest) before the run, as the pipeline
would hand it over. Prints a table, writes benchmarks/results/refine_device.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import machine, table, write_json  # noqa: E402

from mvs_core import MvsConfig  # noqa: E402
from recon.core.refine import refine_sequence  # noqa: E402


def write_input(path: Path, rgb, depth, poses, intrinsics) -> None:
    """Half-size frames (uint8) and depth (float16) with the full size, poses and intrinsics."""
    height, width = depth.shape[-2:]
    half = (width // 2, height // 2)
    small_rgb = F.interpolate(torch.as_tensor(rgb).permute(0, 3, 1, 2).float(), size=half[::-1], mode="bilinear",
                              antialias=True, align_corners=False).round().clamp(0, 255).byte().permute(0, 2, 3, 1)
    small_depth = torch.as_tensor(depth)[:, None].float()
    small_depth = F.interpolate(small_depth, size=half[::-1], mode="nearest")[:, 0].half()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, rgb=small_rgb.numpy(), depth=small_depth.numpy(), poses=np.asarray(poses, np.float64),
                        intrinsics=np.asarray(intrinsics, np.float64), size=np.array([height, width]))


def read_input(path: Path):
    """(rgb (N, H, W, 3) uint8, depth (N, H, W) float32, poses, intrinsics) at the full size."""
    data = np.load(path)
    height, width = (int(v) for v in data["size"])
    rgb = F.interpolate(torch.as_tensor(data["rgb"]).permute(0, 3, 1, 2).float(), size=(height, width),
                        mode="bilinear", align_corners=False).round().clamp(0, 255).byte().permute(0, 2, 3, 1)
    depth = F.interpolate(torch.as_tensor(data["depth"]).float()[:, None], size=(height, width), mode="nearest")[:, 0]
    return rgb.numpy(), depth.numpy(), data["poses"], tuple(float(v) for v in data["intrinsics"])


def make_input(path: Path) -> None:
    from refine_study import load_set

    from medea_core import MedeaConfig
    from recon.core.medea import adjust_sequence

    rgb, _, poses, intrinsics, prior, features = load_set("7s4")
    depth = adjust_sequence(rgb, prior, poses, tuple(intrinsics), features, MedeaConfig.fast(),
                            progress=False).depth.numpy()
    write_input(path, rgb, depth, poses, intrinsics)
    print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")


def timed_run(rgb, depth, poses, intrinsics, config: MvsConfig):
    if config.device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    result = refine_sequence(rgb, depth, poses, intrinsics, config, progress=False)
    if config.device.startswith("cuda"):
        torch.cuda.synchronize()
    return time.perf_counter() - start, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--make-input", type=Path, help="build the input file from ../shared and stop")
    parser.add_argument("--input", type=Path, default=ROOT / "out" / "refine_input.npz")
    parser.add_argument("--devices", nargs="+", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per device (after one warm-up)")
    parser.add_argument("--threads", type=int, default=2, help="CPU threads")
    parser.add_argument("--scales", nargs="+", type=float, default=[MvsConfig().image_scale],
                        help="image_scale settings to time (the default first)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.make_input:
        make_input(args.make_input)
        return
    if not args.input.is_file():
        sys.exit(f"recon: error: no input at {args.input}; build it with --make-input {args.input}")
    rgb, depth, poses, intrinsics = read_input(args.input)
    rows, reference = [], {}
    for scale in args.scales:
        for device in args.devices:
            config = replace(MvsConfig(), device=device, image_scale=scale)
            timed_run(rgb[:8], depth[:8], poses[:8], intrinsics, config)  # warm-up: kernels, allocator
            times = []
            for _ in range(args.repeats):
                seconds, result = timed_run(rgb, depth, poses, intrinsics, config)
                times.append(seconds)
            peak = torch.cuda.max_memory_allocated() / 2**30 if device.startswith("cuda") else None
            row = {"device": device, "image_scale": scale, "frames": len(depth),
                   "seconds_per_frame": float(np.median(times)) / len(depth), "runs": times,
                   "reconstructed": float(result.reconstructed.float().mean()), "peak_gpu_gib": peak}
            if scale not in reference:
                reference[scale] = result
            else:
                base = reference[scale]
                both = base.reconstructed & result.reconstructed
                either = base.reconstructed | result.reconstructed
                rel = (result.depth[both] - base.depth[both]).abs() / base.depth[both]
                row["mask_agreement"] = float(both.sum() / either.sum().clamp(min=1))
                row["median_rel_difference"] = float(rel.median()) if rel.numel() else None
                row["p99_rel_difference"] = float(rel.quantile(0.99)) if rel.numel() else None
            rows.append(row)
            print(f"{device} scale {scale}: {row['seconds_per_frame']:.4f} s/frame", flush=True)
    speed = {(r["image_scale"], r["device"]): r["seconds_per_frame"] for r in rows}
    print(table(["device", "image scale", "s/frame", "speed-up vs cpu", "reconstructed", "mask agreement",
                 "median rel diff", "peak GPU GiB"],
                [[r["device"], r["image_scale"], f"{r['seconds_per_frame']:.4f}",
                  f"{speed.get((r['image_scale'], 'cpu'), np.nan) / r['seconds_per_frame']:.1f}x",
                  f"{r['reconstructed']:.3f}", f"{r.get('mask_agreement', 1.0):.4f}",
                  f"{r.get('median_rel_difference') or 0:.2e}",
                  "-" if r["peak_gpu_gib"] is None else f"{r['peak_gpu_gib']:.2f}"] for r in rows]))
    info = machine()
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name()
    print(f"machine: {info}")
    write_json("refine_device", {"machine": info, "input": str(args.input), "config": asdict(MvsConfig()),
                                 "threads": args.threads, "rows": rows})


if __name__ == "__main__":
    main()
