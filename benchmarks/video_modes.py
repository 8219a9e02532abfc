"""Videos with estimated poses, one-shot against streamed: what `--stream auto` chooses for a
video file (recon.pipeline.stream_reason) and why; with --variant, any two settings.

The recordings in ../shared/data are written once as 640x480 mp4 files at 30 fps (OpenCV's
mp4v, as a phone video would be decoded), then each clip below runs once per variant, by
default twice as `recon run VIDEO -o OUT --stream off|on` with nothing else given (the focal
length is searched, the poses estimated), one run after the other so that the machine's
drift touches both alike.
Each output is scored once by `recon eval OUT --gt DATASET --mesh-align sim3+icp`, which
gives the mesh's F-score aligned by the trajectory's Sim(3) (`mesh_before_icp`, what the
default `--mesh-align auto` scores) and then registered by its surface (`mesh`, Tanks and
Temples' second step; refused, and so equal to the first, when ICP would move it by more
than 1.25x or 10 degrees).

Clips: 7-Scenes redkitchen 0-399, 200-399, 100-299, every 2nd frame, 0-149 and 0-299; TUM
fr1/rpy 0-99 (near-pure rotation). s/frame is the report's stage seconds over the tracked
frames.

Usage: python benchmarks/video_modes.py [--clips NAME ...] [--variant "LABEL=RECON RUN ARGS" ...]
    [--work DIR] [--json video_modes]
e.g. --variant "straight-edge lens=" --variant "pinhole search=--pose-option plumb_line=false"
(stop 39). Prints a table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, parse_variant, table, write_json  # noqa: E402
from benchmarks.stream import ping_pong_video  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
SEVEN, TUM = DATA / "7scenes-redkitchen", DATA / "tum-fr1-rpy"
# name: (recording, `recon run` frame selection)
CLIPS = {
    "7scenes 0-399": (SEVEN, []),
    "7scenes 200-399": (SEVEN, ["--start", "6.66"]),
    "7scenes 100-299": (SEVEN, ["--start", "3.33", "--max-frames", "200"]),
    "7scenes 0-399 every 2nd": (SEVEN, ["--stride", "2"]),
    "7scenes 0-149": (SEVEN, ["--end", "5"]),
    "7scenes 0-299": (SEVEN, ["--max-frames", "300"]),
    "tum 0-99": (TUM, []),
}


def recording_video(dataset: Path, work: Path) -> Path:
    """The recording's frames, in order, as one mp4 at 30 fps (written once, with its
    trajectory beside it): stream.py's back-and-forth video as long as the recording."""
    from recon.io.frames import open_source

    return ping_pong_video(work / f"{dataset.name}.mp4", open_source(dataset).count, dataset)[0]


def recon(*args: str) -> None:
    cmd = [str(Path(sys.executable).with_name("recon")), *args]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {(done.stderr.strip().splitlines() or ['?'])[-1]}")


def run_clip(video: Path, dataset: Path, selection: list[str], variant: list[str], out: Path) -> dict:
    recon("run", str(video), "-o", str(out), "--overwrite", "--quiet", "--rerun", "off", *variant, *selection)
    report = json.loads((out / "report.json").read_text())
    recon("eval", str(out), "--gt", str(dataset), "--quiet", "--overwrite", "--mesh-align", "sim3+icp")
    scores = json.loads((out / "eval.json").read_text())
    frames = report["frames"]
    tracked = frames.get("tracked", frames["count"])
    trajectory = scores.get("trajectory", {}).get("ate_sim3", {})
    return {"frames": tracked, "depth_frames": frames.get("depth_frames", frames["count"]),
            "seconds": report["seconds"], "s_per_frame": sum(report["seconds"].values()) / tracked,
            "abs_rel": scores["depth"]["metric"]["abs_rel"], "fscore": scores["mesh_before_icp"]["fscore"],
            "fscore_icp": scores["mesh"]["fscore"], "icp": scores.get("mesh_icp"),
            "trajectory_scale": trajectory.get("scale"), "ate_sim3": trajectory.get("rmse"),
            "focal": report["intrinsics"]["values"][0], "lens_k1": report["poses"].get("lens_k1")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", nargs="*", default=list(CLIPS), choices=list(CLIPS))
    parser.add_argument("--variant", type=parse_variant, action="append",
                        help="LABEL=ARGS: a run of every clip with these `recon run` arguments (repeatable; "
                             "default: one-shot=--stream off, streamed=--stream on)")
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-video-modes"))
    parser.add_argument("--json", default="video_modes")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"recon: error: {DATA}: the recordings are not there")
    args.work.mkdir(parents=True, exist_ok=True)

    variants = args.variant or [("one-shot", ["--stream", "off"]), ("streamed", ["--stream", "on"])]
    results, rows = [], []
    for name in args.clips:
        dataset, selection = CLIPS[name]
        video = recording_video(dataset, args.work)
        for k, (label, variant) in enumerate(variants):
            r = {"clip": name, "run": label, "args": variant,
                 **run_clip(video, dataset, selection, variant, args.work / f"{name.replace(' ', '_')}-{k}")}
            results.append(r)
            icp = r["icp"] or {}
            rows.append([name, label, r["frames"], r["depth_frames"],
                         f"{r['s_per_frame']:.3f}", f"{r['abs_rel']:.4f}", f"{r['fscore']:.3f}",
                         f"{r['fscore_icp']:.3f}" if icp.get("accepted") else "refused",
                         f"{r['trajectory_scale']:.3f}", f"{r['ate_sim3']:.4f}", f"{r['focal']:.0f}",
                         f"{r['lens_k1']:+.3f}" if r["lens_k1"] is not None else "-"])
            print(rows[-1], flush=True)
            write_json(args.json, {"machine": machine(), "results": results})
    print(table(["clip", "run", "frames", "depth frames", "s/frame", "abs rel", "F@5cm Sim(3)", "F@5cm +ICP",
                 "trajectory scale", "ATE Sim(3)", "focal", "k1"], rows))


if __name__ == "__main__":
    main()
