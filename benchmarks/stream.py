"""Long videos: peak memory and seconds per frame of the streamed pipeline against the
one-shot (batch) pipeline, on one long 640x480 video.

The video: 7-Scenes redkitchen frames 0-399 played forwards, backwards, forwards, ... (a
camera walking the kitchen back and forth), written once as an mp4 at 30 fps; runs use its
first 300, 1200 and 3600 frames (``--max-frames``). Every run is a separate `recon run`
process with estimated poses (the streaming front end / the one-shot front end), the
FastDepth prior from ``--weights`` (default ../shared/weights/fastdepth), MEDeA (fast
preset), the refinement, fusion, export; peak resident memory is the process's VmHWM as its
report.json records it.

Rows:
* ``stream``: the defaults of a long input (depth frames by motion, windows of 48);
* ``stream, all frames``: every tracked frame gets depth (the one-shot run's work);
* ``batch``: `--stream off` (every frame in memory at once; only where it fits).

Usage: python benchmarks/stream.py [--lengths 300 1200 3600] [--batch-lengths 300 1200]
Prints a table, writes benchmarks/results/stream.json. Run it alone on the machine
(timings on a shared CPU are not comparable).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def ping_pong_video(path: Path, frames: int, dataset: Path) -> Path:
    """The back-and-forth walk (module docstring) as an mp4 of `frames` frames."""
    from recon.io.frames import open_source
    from recon.io.video import write_video

    if path.is_file():
        return path
    source = open_source(dataset, width=640)
    clip = np.stack([f.rgb for f in source])
    order = np.concatenate([np.arange(len(clip)), np.arange(len(clip) - 2, 0, -1)])
    picks = np.resize(order, frames)
    write_video(clip[picks], path, fps=30.0)
    return path


def run(video: Path, out: Path, frames: int, mode: str, extra: list[str], weights: Path) -> dict:
    cmd = [str(Path(sys.executable).with_name("recon")), "run", str(video), "-o", str(out), "--overwrite", "--quiet",
           "--max-frames", str(frames), "--stream", mode, "--weights", str(weights), "--rerun", "off", *extra]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall}
    report = json.loads((out / "report.json").read_text())
    frames_run = report["frames"].get("tracked", report["frames"]["count"])
    return {"wall_s": wall, "s_per_frame": wall / frames_run, "frames": frames_run,
            "depth_frames": report["frames"].get("depth_frames", report["frames"]["count"]),
            "peak_rss_mb": report["memory"]["peak_rss_mb"], "seconds": report["seconds"],
            "triangles": report["fusion"]["triangles"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", type=int, nargs="+", default=[300, 1200, 3600])
    parser.add_argument("--batch-lengths", type=int, nargs="*", default=[300, 1200])
    parser.add_argument("--all-frames-lengths", type=int, nargs="*", default=[300])
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-stream-bench"))
    parser.add_argument("--weights", type=Path, default=SHARED / "weights" / "fastdepth")
    parser.add_argument("--dataset", type=Path, default=SHARED / "data" / "7scenes-redkitchen")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    longest = max(args.lengths + args.batch_lengths + args.all_frames_lengths)
    video = ping_pong_video(args.work / f"pingpong_{longest}.mp4", longest, args.dataset)

    plan = [("stream", n, "on", []) for n in args.lengths]
    plan += [("stream, all frames", n, "on", ["--depth-frames", "all"]) for n in args.all_frames_lengths]
    plan += [("batch", n, "off", ["--frame-budget", str(n)]) for n in args.batch_lengths]
    rows, results = [], []
    for label, n, mode, extra in plan:
        result = {"run": label, "length": n, **run(video, args.work / f"out_{mode}_{n}_{len(extra)}", n, mode, extra,
                                                   args.weights)}
        results.append(result)
        print(json.dumps({k: v for k, v in result.items() if k != "seconds"}), flush=True)
        rows.append([label, n, result.get("depth_frames", "-"), f"{result.get('peak_rss_mb', float('nan')):.0f}",
                     f"{result.get('s_per_frame', float('nan')):.3f}", result.get("error", "")])
    print(table(["run", "frames", "depth frames", "peak RSS MB", "s/frame", "error"], rows))
    write_json("stream", {"machine": machine(), "video": str(video), "results": results})


if __name__ == "__main__":
    main()
