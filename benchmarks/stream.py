"""Long videos: peak memory and seconds per frame of the streamed pipeline against the
one-shot (batch) pipeline, on one long 640x480 video.

The video: 7-Scenes redkitchen frames 0-399 played forwards, backwards, forwards, ... (a
camera walking the kitchen back and forth), written once as an mp4 at 30 fps with its
ground-truth trajectory as a TUM file; runs use its first 300, 1200 and 3600 frames
(``--max-frames``). Every run is a separate `recon run` process with the poses from that
file (not polished), the FastDepth prior from ``--weights`` (default
../shared/weights/fastdepth), MEDeA (fast preset), the refinement, fusion and export; peak
resident memory is the process's VmHWM as its report.json records it. Rows with estimated
poses run the streaming front end.

Rows:
* ``stream``: the defaults of a long input (depth frames by motion, windows of 48);
* ``stream, all frames``: every tracked frame gets depth (the one-shot run's work);
* ``batch``: `--stream off` (every frame in memory at once; only where it fits);
* ``stream, estimated poses``: the streaming front end instead of the pose file;
* ``batch, estimated poses``: `--stream off` with the poses estimated (every frame gets
  depth; the one-shot run a user gets on a video up to the frame budget).

Usage: python benchmarks/stream.py [--lengths 300 1200 3600] [--batch-lengths 300 1200]
[--batch-estimate-lengths 300] [--rounds N]. Prints a table, writes
benchmarks/results/stream.json. Run it alone on the machine (timings on a shared CPU are
not comparable). With ``--rounds N`` the whole plan runs N times in turn (interleaved, so
that the machine's drifts hit every row alike) and the table gives each row's median, and
the ratio of every streamed row's s/frame to the batch row's of the same length and pose
source.
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

from benchmarks.common import machine, ping_pong, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def ping_pong_video(path: Path, frames: int, dataset: Path) -> tuple[Path, Path]:
    """The back-and-forth walk (module docstring) as an mp4 of `frames` frames, and its
    ground-truth trajectory as a TUM file beside it (one pose per video frame)."""
    from recon.io.frames import open_source
    from recon.io.pose_formats.trajectories import write_poses
    from recon.io.video import write_video

    poses_path = path.with_suffix(".tum.txt")
    if path.is_file() and poses_path.is_file():
        return path, poses_path
    source = open_source(dataset, width=640)
    clip = np.stack([f.rgb for f in source])
    picks = ping_pong(len(clip), frames)
    write_video(clip[picks], path, fps=30.0)
    write_poses(poses_path, source.poses[picks], "tum", timestamps=np.arange(frames) / 30.0)
    return path, poses_path


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
            "frame_store_mb": report["memory"].get("frame_store_mb"),
            "triangles": report["fusion"]["triangles"], "blocks": report["fusion"]["blocks_used"],
            "anchors": [w.get("anchored_to") for w in report.get("windows", {}).get("each", [])]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lengths", type=int, nargs="*", default=[300, 1200, 3600])
    parser.add_argument("--batch-lengths", type=int, nargs="*", default=[300, 1200])
    parser.add_argument("--all-frames-lengths", type=int, nargs="*", default=[300])
    parser.add_argument("--estimate-lengths", type=int, nargs="*", default=[300])
    parser.add_argument("--batch-estimate-lengths", type=int, nargs="*", default=[])
    parser.add_argument("--extra", default="", help="more `recon run` options for every run, e.g. \"--refine none "
                        "--depth-frames 12\" for a quick memory-growth series (say so with the figures)")
    parser.add_argument("--rounds", type=int, default=1, help="run the plan this many times, interleaved")
    parser.add_argument("--json", default="stream", help="results file name under benchmarks/results/")
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-stream-bench"))
    parser.add_argument("--weights", type=Path, default=SHARED / "weights" / "fastdepth")
    parser.add_argument("--dataset", type=Path, default=SHARED / "data" / "7scenes-redkitchen")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    longest = max(args.lengths + args.batch_lengths + args.all_frames_lengths + args.estimate_lengths
                  + args.batch_estimate_lengths)
    video, poses = ping_pong_video(args.work / f"pingpong_{longest}.mp4", longest, args.dataset)
    # Given poses (the ground truth as a pose file) and no polish (the default), so that stream
    # and batch do the same work; estimated poses in rows of their own.
    given = ["--poses", str(poses), "--intrinsics", "525,525,320,240", "--set", "polish=false", *args.extra.split()]
    plan = [("stream", n, "on", given) for n in args.lengths]
    plan += [("batch", n, "off", [*given, "--frame-budget", str(n)]) for n in args.batch_lengths]
    estimated = ["--poses", "estimate", "--intrinsics", "525,525,320,240", *args.extra.split()]
    plan += [("stream, estimated poses", n, "on", estimated) for n in args.estimate_lengths]
    plan += [("batch, estimated poses", n, "off", [*estimated, "--frame-budget", str(n)])
             for n in args.batch_estimate_lengths]
    plan += [("stream, all frames", n, "on", [*given, "--depth-frames", "all"]) for n in args.all_frames_lengths]
    results = []
    for round_ in range(args.rounds):
        for label, n, mode, extra in plan:
            folder = args.work / f"out_{args.json}_{label.replace(' ', '').replace(',', '_')}_{n}"
            result = {"run": label, "length": n, "round": round_, **run(video, folder, n, mode, extra, args.weights)}
            results.append(result)
            print(json.dumps({k: v for k, v in result.items() if k != "seconds"}), flush=True)
            # Written after every run: a long series stopped part-way keeps what it measured.
            write_json(args.json, {"machine": machine(), "video": str(video), "extra": args.extra,
                                   "rounds": args.rounds, "results": results, "summary": summarise(results)})
    rows = [[r["run"], r["length"], r["depth_frames"], f"{r['peak_rss_mb']:.0f}", f"{r['s_per_frame']:.3f}",
             "-" if r["vs_batch"] is None else f"{r['vs_batch']:.3f}", r["blocks"], r["triangles"], r["error"]]
            for r in summarise(results)]
    print(table(["run", "frames", "depth frames", "peak RSS MB", "s/frame (median)", "vs batch", "TSDF blocks",
                 "triangles", "error"], rows))


def summarise(results: list[dict]) -> list[dict]:
    """One row per (run, length): medians over the rounds, and the median over rounds of the
    ratio of its s/frame to the batch row's of the same length, round and pose source (None
    without one)."""
    def median(values):
        values = [v for v in values if v is not None]
        return float(np.median(values)) if values else None

    batch = {(r["run"], r["length"], r["round"]): r.get("s_per_frame") for r in results
             if r["run"].startswith("batch")}

    def reference(r: dict) -> tuple:
        kind = "batch, estimated poses" if r["run"].endswith("estimated poses") else "batch"
        return kind, r["length"], r["round"]

    out = []
    for key in dict.fromkeys((r["run"], r["length"]) for r in results):
        runs = [r for r in results if (r["run"], r["length"]) == key]
        ratios = [r["s_per_frame"] / batch[reference(r)] for r in runs
                  if r.get("s_per_frame") and batch.get(reference(r)) and not r["run"].startswith("batch")]
        out.append({"run": key[0], "length": key[1], "rounds": len(runs),
                    "depth_frames": runs[-1].get("depth_frames", "-"),
                    "peak_rss_mb": median([r.get("peak_rss_mb") for r in runs]) or float("nan"),
                    "s_per_frame": median([r.get("s_per_frame") for r in runs]) or float("nan"),
                    "vs_batch": median(ratios), "blocks": runs[-1].get("blocks", "-"),
                    "triangles": runs[-1].get("triangles", "-"),
                    "error": "; ".join(r["error"] for r in runs if "error" in r)})
    return out


if __name__ == "__main__":
    main()
