"""The speed benchmark: `recon run` at its defaults, stage by stage, against a baseline.

Three inputs of 300 frames at 640x480, each run as a user runs it (a whole process, the
defaults, ``--quiet --rerun off``):

* ``rendered``: the synthetic room rendered to an mp4 (what `recon demo` renders), nothing given;
* ``kitchen-video``: 7-Scenes redkitchen frames 0-299 as a 30 fps mp4, nothing given (a
  streamed video with estimated poses);
* ``kitchen-given``: the same frames as the dataset folder, its poses and intrinsics given.

The table gives each stage's seconds per frame (the run's report.json; per tracked frame)
and the wall time per frame of the whole process, median over ``--repeats`` runs. With
``--baseline DIR`` (a checkout of an earlier commit, e.g. a git worktree) every run of
this checkout is paired with one of the baseline, the two in turn, so that the machine's
drift touches both alike; the ratio column is baseline / now (above 1: faster now). Without
it the medians are compared with the stored baseline of the same CPU model
(``results/speed_baseline.json``, written by ``--store-baseline``), when there is one.
``--colmap`` also times COLMAP's sparse SfM (pycolmap: SIFT, sequential matching,
incremental mapping) on every third frame of the kitchen video, the CPU user's alternative.

Usage: python benchmarks/speed.py [--inputs rendered kitchen-video kitchen-given]
    [--baseline DIR] [--repeats 1] [--colmap] [--store-baseline] [--work DIR] [--json speed]
Prints the table and the machine, writes benchmarks/results/<json>.json. Run it alone on
the machine: timings here vary up to 2x between identical runs otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import RESULTS, machine, say, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"
FRAMES = 300
INPUTS = ("rendered", "kitchen-video", "kitchen-given")
STAGES = ("decode", "prior", "poses", "store", "undistort", "medea", "refine", "fusion", "export", "logging")
BASELINE_FILE = RESULTS / "speed_baseline.json"
COLMAP_STEP = 3


def rendered_video(work: Path) -> Path:
    """The synthetic room's 300 frames as an mp4 (written once)."""
    path = work / "rendered.mp4"
    if not path.is_file():
        from recon.io.video import write_video
        from recon.synthetic import render_sequence

        seq = render_sequence(FRAMES, 640, 480, seed=0)
        tmp = work / "rendered.tmp.mp4"
        write_video(seq.rgb, tmp, 30.0)
        tmp.replace(path)
    return path


def kitchen_video(work: Path) -> Path:
    """7-Scenes redkitchen frames 0-299 as a 30 fps mp4 (written once, OpenCV's mp4v as
    benchmarks/validate.py writes its videos)."""
    path = work / "kitchen300.mp4"
    if not path.is_file():
        import cv2

        tmp = work / "kitchen300.tmp.mp4"
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (640, 480))
        for k in range(FRAMES):
            writer.write(cv2.imread(str(KITCHEN / f"frame-{k:06d}.color.jpg")))
        writer.release()
        tmp.replace(path)
    return path


def input_args(name: str, work: Path) -> list[str]:
    """`recon run` arguments of an input (the input first)."""
    if name == "rendered":
        return [str(rendered_video(work))]
    if name == "kitchen-video":
        return [str(kitchen_video(work))]
    return [str(KITCHEN), "--max-frames", str(FRAMES)]


# `recon` as the process to time, from whichever checkout is first on the import path (the
# command moved from recon.cli to recon.commands.cli after ef60f71).
LAUNCHER = """import sys
try:
    from recon.commands.cli import main
except ImportError:
    from recon.cli import main
sys.argv[0] = "recon"
sys.exit(main())
"""


def run_once(args: list[str], out: Path, code: Path | None) -> dict:
    """One `recon run` as a process (``code``: another checkout's packages first on the
    import path): its exit code, wall seconds, stage seconds per tracked frame, peak RSS."""
    env = dict(os.environ, **({"PYTHONPATH": str(code)} if code is not None else {}))
    cmd = [sys.executable, "-c", LAUNCHER, "run", *args, "-o", str(out), "--overwrite", "--quiet", "--rerun", "off"]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd="/")
    wall = time.perf_counter() - start
    row = {"exit": done.returncode, "wall_s": wall}
    if done.returncode != 0:
        row["error"] = (done.stderr.strip().splitlines() or ["?"])[-1]
        return row
    report = json.loads((out / "report.json").read_text())
    frames = report["frames"]
    tracked = frames.get("tracked", frames["count"])
    row.update(frames=tracked, depth_frames=frames.get("depth_frames", frames["count"]),
               stages={k: v / tracked for k, v in report["seconds"].items()},
               wall_per_frame=wall / tracked, peak_rss_mb=report.get("memory", {}).get("peak_rss_mb"),
               first_result_s=report.get("windows", {}).get("first_result_s"))
    return row


def colmap_seconds(work: Path) -> float:
    """COLMAP's sparse SfM on every COLMAP_STEP-th frame of the kitchen video, as a process:
    SIFT on the CPU, sequential matching, incremental mapping (frames written beforehand)."""
    import cv2

    images = work / "colmap-images"
    if not images.is_dir():
        tmp = work / "colmap-images.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        for k in range(0, FRAMES, COLMAP_STEP):
            cv2.imwrite(str(tmp / f"{k:06d}.jpg"), cv2.imread(str(KITCHEN / f"frame-{k:06d}.color.jpg")))
        tmp.rename(images)
    scratch = work / "colmap-run"
    subprocess.run(["rm", "-rf", str(scratch)], check=True)
    scratch.mkdir(parents=True)
    script = (
        "import pycolmap, sys\n"
        "db, images, out = sys.argv[1:4]\n"
        "pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, device=pycolmap.Device.cpu)\n"
        "pycolmap.match_sequential(db, device=pycolmap.Device.cpu)\n"
        "models = pycolmap.incremental_mapping(db, images, out)\n"
        "print(max((m.num_reg_images() for m in models.values()), default=0))\n"
    )
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", script, str(scratch / "db.db"), str(images), str(scratch)],
                          capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"COLMAP failed: {(done.stderr.strip().splitlines() or ['?'])[-1]}")
    say(f"COLMAP registered {done.stdout.strip().splitlines()[-1]} of {len(range(0, FRAMES, COLMAP_STEP))} images")
    return seconds


def medians(runs: list[dict]) -> dict:
    """Median wall and stage seconds per frame over the runs that finished."""
    ok = [r for r in runs if r["exit"] == 0]
    if not ok:
        return {}
    stages = {s: statistics.median(r["stages"].get(s, 0.0) for r in ok) for s in STAGES}
    return {"wall_per_frame": statistics.median(r["wall_per_frame"] for r in ok), "stages": stages,
            "total_per_frame": statistics.median(sum(r["stages"].values()) for r in ok),
            "peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in ok),
            "first_result_s": statistics.median([r["first_result_s"] for r in ok if r.get("first_result_s")] or [0]),
            "runs": len(ok)}


def stored_baseline(cpu: str) -> dict:
    """The stored medians of this CPU model, {} when none is stored."""
    if not BASELINE_FILE.is_file():
        return {}
    return json.loads(BASELINE_FILE.read_text()).get(cpu, {})


def stage_table(now: dict, before: dict, label: str) -> str:
    """Per input and stage: s/frame before, now, and the ratio before / now."""
    rows = []
    for name, m in now.items():
        b = before.get(name, {})
        for stage in (*STAGES, "total", "wall"):
            value = m["stages"].get(stage) if stage in STAGES else m[f"{stage}_per_frame"]
            old = (b.get("stages", {}).get(stage) if stage in STAGES else b.get(f"{stage}_per_frame"))
            if not value and not old:
                continue
            ratio = f"{old / value:.2f}x" if old and value else "-"
            rows.append([name, stage, "-" if old is None else f"{old:.3f}", f"{value:.3f}", ratio])
    return table(["input", "stage (s/frame)", label, "now", f"{label} / now"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", nargs="*", default=list(INPUTS), choices=INPUTS)
    parser.add_argument("--baseline", type=Path, help="a checkout of an earlier commit, run in turn with this one")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--colmap", action="store_true", help="also time COLMAP's sparse SfM on the kitchen video")
    parser.add_argument("--store-baseline", action="store_true",
                        help="store this run's medians (of --baseline's checkout when given) as this CPU's baseline")
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-speed"))
    parser.add_argument("--json", default="speed")
    args = parser.parse_args()
    if any(name.startswith("kitchen") for name in args.inputs) and not KITCHEN.is_dir():
        sys.exit(f"speed.py: {KITCHEN}: the recording is not there")
    args.work.mkdir(parents=True, exist_ok=True)
    info = machine()
    runs: dict[str, dict[str, list]] = {name: {"now": [], "baseline": []} for name in args.inputs}
    for repeat in range(args.repeats):
        for name in args.inputs:
            run_args = input_args(name, args.work)
            versions = [("baseline", args.baseline), ("now", None)] if args.baseline else [("now", None)]
            for version, code in versions[::1 if repeat % 2 == 0 else -1]:  # alternate who goes first
                say(f"{name}: {version} (run {repeat + 1} of {args.repeats})")
                row = run_once(run_args, args.work / f"out-{name}-{version}", code)
                runs[name][version].append(row)
                say(f"  exit {row['exit']}, {row['wall_s']:.1f} s" + (f": {row['error']}" if row["exit"] else ""))
    now = {name: medians(r["now"]) for name, r in runs.items() if medians(r["now"])}
    if args.baseline:
        before, label = {name: medians(r["baseline"]) for name, r in runs.items() if medians(r["baseline"])}, \
            "baseline"
    else:
        before, label = stored_baseline(info["cpu"]), "stored"
    colmap = colmap_seconds(args.work) if args.colmap else None
    print(f"\nmachine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} ({info['torch_threads']} threads)")
    print(stage_table(now, before, label))
    for name, m in now.items():
        print(f"{name}: first result after {m['first_result_s']:.1f} s; peak RSS {m['peak_rss_mb']:.0f} MB"
              if m.get("first_result_s") else f"{name}: peak RSS {m['peak_rss_mb']:.0f} MB")
    if colmap is not None:
        wall = now.get("kitchen-video", {}).get("wall_per_frame")
        print(f"COLMAP sparse SfM, every {COLMAP_STEP}rd frame of the kitchen video: {colmap:.1f} s; recon run to a "
              f"mesh: {wall * FRAMES:.1f} s" if wall else f"COLMAP: {colmap:.1f} s")
    if args.store_baseline:
        stored = json.loads(BASELINE_FILE.read_text()) if BASELINE_FILE.is_file() else {}
        stored[info["cpu"]] = {**(before if args.baseline else now),
                               "code": str(args.baseline or ROOT), "stored": time.strftime("%Y-%m-%d")}
        BASELINE_FILE.write_text(json.dumps(stored, indent=2))
        print(f"stored the baseline of {info['cpu']} in {BASELINE_FILE}")
    path = write_json(args.json, {"machine": info, "baseline": str(args.baseline) if args.baseline else label,
                                  "runs": runs, "now": now, "before": before, "colmap_s": colmap})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
