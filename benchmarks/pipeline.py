"""End-to-end pipeline benchmark: seconds per frame per stage on a rendered 640x480 video,
and mesh quality against the synthetic room's ground-truth mesh.

Two runs on the same rendered sequence (default 300 frames at 640x480, written as mp4):

* ``speed``: what `recon run VIDEO --poses FILE` costs: decode, FastDepth prior (with
  encoder features for MEDeA), poses from a file (ground truth; "given poses", polished
  against the frames), MEDeA (fast preset), the MVS refinement (``refine``), TSDF fusion,
  export (PLY, GLB, TUM, 16-bit PNG + npy depth) and Rerun logging (saved .rrd). With
  ``--estimate`` a third run estimates the poses instead, when the pose estimator is
  installed: `recon run VIDEO` at its defaults, which streams a video with estimated poses
  (depth for the frames the camera moved to reach, ``recon.pipeline.stream_reason``).
* ``quality``: `recon demo` at the same size: the simulated prior (ground truth distorted
  like a network) adjusted by MEDeA with ground-truth poses, then refined; mesh accuracy,
  completeness, precision, recall and F-score at 5 cm for the refined depth (the written
  mesh), MEDeA's depth and the raw prior.

Usage: python benchmarks/pipeline.py [--frames 300] [--skip-quality] [--estimate]
Prints tables, writes benchmarks/results/pipeline.json. Timings on a shared machine are
approximate.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, table, write_json  # noqa: E402
from recon.commands.demo import DemoOptions, pose_estimator_available, run_demo, write_demo_inputs  # noqa: E402
from recon.io.output_folder import OutputFolder  # noqa: E402
from recon.pipeline import STAGES, PipelineConfig, run_pipeline  # noqa: E402
from recon.synthetic import render_sequence  # noqa: E402


def stage_rows(name: str, seconds: dict, frames: int) -> list[list]:
    total = sum(seconds.values())
    rows = [[name, stage, f"{seconds.get(stage, 0.0):.1f}", f"{seconds.get(stage, 0.0) / frames:.3f}"]
            for stage in (*STAGES, *(k for k in seconds if k not in STAGES))]  # a streamed run adds "store"
    return rows + [[name, "total", f"{total:.1f}", f"{total / frames:.3f}"]]


def speed_run(seq, workdir: Path, poses: str, progress: bool) -> dict:
    inputs = write_demo_inputs(OutputFolder(workdir / "inputs", overwrite=True), seq, None)
    config = PipelineConfig(
        input=inputs["video"], output=workdir / f"out-{poses}", width=None, intrinsics=seq.intrinsics,
        poses=str(inputs["poses"]) if poses == "given" else "estimate", prior="fastdepth", rerun="save",
        progress=progress,
    )
    start = time.perf_counter()
    result = run_pipeline(config)
    wall = time.perf_counter() - start
    mesh = result.fusion.mesh
    # With estimated poses a video is streamed (recon.pipeline.stream_reason): every frame is
    # tracked, the frames the camera moved to reach get depth.
    frames = result.report["frames"]
    tracked = frames.get("tracked", frames["count"])
    return {
        "poses": poses, "frames": tracked, "depth_frames": frames.get("depth_frames", frames["count"]),
        "streamed": bool(result.report.get("streamed")), "seconds": result.seconds, "wall": wall,
        "seconds_per_frame": result.seconds_per_frame, "end_to_end_per_frame": wall / tracked,
        "mesh": {"vertices": len(mesh.vertices), "triangles": len(mesh.triangles), "voxel": result.fusion.voxel_size},
        "medea": result.report.get("medea") or result.report["windows"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--quality-frames", type=int, help="frames of the quality run (default: --frames)")
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--skip-quality", action="store_true")
    parser.add_argument("--estimate", action="store_true", help="also time a run with pose estimation")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(2)

    payload: dict = {"machine": machine(), "frames": args.frames, "size": [args.width, args.height], "runs": {}}
    rows: list[list] = []
    with tempfile.TemporaryDirectory(prefix="recon-bench-") as tmp:
        tmp = Path(tmp)
        if not args.skip_speed:
            start = time.perf_counter()
            seq = render_sequence(args.frames, args.width, args.height, seed=0)
            payload["seconds_render"] = time.perf_counter() - start
            modes = ["given"] + (["estimate"] if args.estimate else [])
            for mode in modes:
                if mode == "estimate" and not pose_estimator_available():
                    payload["runs"]["estimate"] = "pose estimator not installed"
                    continue
                run = speed_run(seq, tmp, mode, args.progress)
                payload["runs"][f"speed_{mode}_poses"] = run
                rows += stage_rows(f"{mode} poses", run["seconds"], run["frames"])
                print(f"{mode} poses: {run['wall']:.1f} s wall, {run['end_to_end_per_frame']:.3f} s/frame end to end",
                      flush=True)
            del seq
        if not args.skip_quality:
            report = run_demo(DemoOptions(output=tmp / "quality", frames=args.quality_frames or args.frames,
                                          width=args.width, height=args.height, poses="gt", rerun="off",
                                          progress=args.progress),
                              say=lambda _: None)
            payload["runs"]["quality"] = {"frames": len(report.result.frames), "evaluation": report.evaluation,
                                          "seconds": report.result.seconds}
            rows += stage_rows("quality (sim. prior)", report.result.seconds, len(report.result.frames))

    print(table(["run", "stage", "seconds", "s/frame"], rows))
    quality = payload["runs"].get("quality")
    if quality:
        ev = quality["evaluation"]
        mrows = []
        for label, key in (("refined depth", "mesh_refined"), ("MEDeA depth", "mesh_adjusted"),
                           ("raw prior", "mesh_prior")):
            if key not in ev:
                continue
            m = ev[key]
            mrows.append([label, f"{m['accuracy']:.4f}", f"{m['completeness']:.4f}", f"{m['precision']:.3f}",
                          f"{m['recall']:.3f}", f"{m['fscore']:.3f}"])
        print(table(["depth fused", "accuracy [m]", "completeness [m]", "precision", "recall", "F-score @5cm"], mrows))
        refined = f" -> refined {ev['depth_refined']['abs_rel']:.4f}" if "depth_refined" in ev else ""
        print(f"depth abs rel: prior {ev['depth_prior']['abs_rel']:.4f} -> MEDeA {ev['depth_adjusted']['abs_rel']:.4f}"
              f"{refined}")
    print(f"wrote {write_json('pipeline', payload)}")


if __name__ == "__main__":
    main()
