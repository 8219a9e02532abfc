"""The synthetic walk-through through ``recon run`` as a user runs it (issue 62).

    python benchmarks/walkthrough_run.py [--width 640 --height 480] [--seed 0] [--work DIR]
        [--intrinsics] [--json walkthrough_run] [--output OUT] [-- EXTRA RECON RUN ARGS]

Renders recon.synthetic.walkthrough (three rooms and a plain corridor, ~400 frames at 30 fps)
to an mp4 video, runs ``recon run`` on it with nothing given (``--intrinsics``: the true
intrinsics given) and the CLI's defaults (FastDepth on the rendered frames), and scores what
came back against the rendered trajectory: each segment (or the one trajectory) fitted on its
own under Sim(3), its ATE as a share of its path, its metric scale against the truth, and
whether the run marked it (a warning naming it, the second opinion's verdict, the short-flow
check, an untrusted metric scale). A segment more than 2 % of its path off that nothing marks
(a mark on its path, not only on its size) is the failure this table is for.

``--output`` scores the folder of an earlier run of the same command instead (its stderr as
this script saved it beside the results, OUT/stderr.txt). Writes benchmarks/results/<json>.json
and prints the table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, say, table, write_json  # noqa: E402

from recon.eval.trajectory import ate_rmse, path_length  # noqa: E402
from recon.io.pose_formats.trajectories import read_poses  # noqa: E402
from recon.poses.second_opinion import MAX_DISAGREEMENT  # noqa: E402

FPS = 30.0
# A segment further off than this share of its path must be marked.
MARK_PCT = 2.0


def render(width: int, height: int, seed: int, work: Path) -> tuple[Path, np.ndarray, tuple, list[int]]:
    """The walk rendered to work/walk.mp4: (video, true poses (N, 4, 4), intrinsics, cuts)."""
    from recon.io.video import write_video
    from recon.synthetic.walkthrough import render_walkthrough

    walk = render_walkthrough(width, height, seed=seed)
    video = work / "walk.mp4"
    write_video(walk.rgb, video, FPS)
    return video, walk.poses, walk.intrinsics, list(walk.cuts)


def marks_of(report: dict, first: int, last: int) -> dict:
    """What the run's summary report says of frames first..last: ``path`` (marks on the
    trajectory's shape: a stretch the second opinion found in disagreement, short-flow or rotation-only
    stretches overlapping them, an inconsistent SfM scale spread) and ``scale`` (a metric
    scale the depth prior cannot vouch for: the size, not the shape)."""
    poses = report.get("poses", {})
    path, scale = [], []
    opinion = poses.get("second_opinion") or {}
    if opinion.get("verdict") == "one only":
        path.append("second opinion: SfM gave none")
    for s in opinion.get("by_stretch", []):  # the stretches compared that overlap these frames
        if s["frames"][0] <= last and s["frames"][1] >= first and s["disagreement"] > MAX_DISAGREEMENT:
            path.append(f"FE and SfM disagree {100 * s['disagreement']:.1f} % on {s['frames'][0]}-{s['frames'][1]}")
    checks = poses.get("motion_checks") or {}
    for kind, spans in (("short flow", checks.get("short_flow", [])), ("turning", checks.get("rotation_only", []))):
        hit = [f"{a}-{b}" for a, b in spans if a <= last and b >= first]
        if hit:
            path.append(f"{kind} {', '.join(hit)}")
    if (poses.get("scale_spread") or {}).get("consistent") is False:
        path.append("SfM scale spread")
    if (poses.get("metric_scale") or {}).get("trusted") is False:
        scale.append("metric scale untrusted")
    return {"path": path, "scale": scale}


def score(out: Path, folder: Path, gt: np.ndarray) -> dict:
    """One segment's (or the run's) trajectory against the truth."""
    report = json.loads((folder / "report.json").read_text())
    summary = json.loads((out / "report.json").read_text())
    indices = np.asarray(report["frames"]["indices"])
    est = read_poses(folder / "trajectory.txt").poses
    truth = gt[indices]
    fit = ate_rmse(est, truth, "sim3")
    length = path_length(truth)
    metric = ate_rmse(est, truth, "se3")
    first, last = int(indices[0]), int(indices[-1])
    return {"folder": folder.name, "first": first, "last": last, "frames": len(indices), "path_m": length,
            "ate_m": fit["rmse"], "ate_pct": 100.0 * fit["rmse"] / max(length, 1e-9), "sim3_scale": fit["scale"],
            "ate_se3_m": metric["rmse"], "marks": marks_of(summary, first, last)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon_walkthrough_run"))
    parser.add_argument("--intrinsics", action="store_true", help="give the true intrinsics")
    parser.add_argument("--json", default="walkthrough_run")
    parser.add_argument("--output", type=Path, help="score this output folder of an earlier run instead of running")
    parser.add_argument("extra", nargs="*", help="more `recon run` arguments (after --)")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    video, gt, intrinsics, cuts = render(args.width, args.height, args.seed, args.work)
    say(f"rendered {len(gt)} frames {args.width}x{args.height} in {time.perf_counter() - t0:.0f} s; cuts {cuts}")
    out = args.work / ("given_intrinsics" if args.intrinsics else "nothing")
    command = [sys.executable, "-m", "recon", "run", str(video), "-o", str(out), "--overwrite", "--quiet",
               "--rerun", "off", *args.extra]
    if args.intrinsics:
        command += ["--intrinsics", ",".join(f"{v:g}" for v in intrinsics)]
    t0 = time.perf_counter()
    if args.output:  # an earlier run of the same command
        out = args.output
        done = subprocess.CompletedProcess(command, 0 if (out / "report.json").is_file() else 2, "",
                                           (out / "stderr.txt").read_text() if (out / "stderr.txt").is_file() else "")
    else:
        done = subprocess.run(command, capture_output=True, text=True)
        if out.is_dir():
            (out / "stderr.txt").write_text(done.stderr)
    wall = time.perf_counter() - t0
    warnings = [line for line in done.stderr.splitlines() if "warning" in line.lower()]
    result = {"machine": machine(), "args": {k: str(v) for k, v in vars(args).items()}, "command": command[2:],
              "exit": done.returncode, "wall_s": wall, "cuts": cuts, "path_m": path_length(gt),
              "warnings": warnings, "stderr_tail": done.stderr.splitlines()[-5:]}
    if done.returncode == 0:
        report = json.loads((out / "report.json").read_text())
        folders = [out / s["folder"] for s in report.get("segments") or []] or [out]
        result["segments"] = [score(out, f, gt) for f in folders]
        result["covered"] = sum(s["frames"] for s in result["segments"]) / len(gt)
        result["unmarked_over"] = [s["folder"] for s in result["segments"]
                                   if s["ate_pct"] > MARK_PCT and not s["marks"]["path"]]
        result["pose_method"] = report.get("poses", {}).get("method")
        result["joins"] = [{k: j.get(k) for k in ("break", "joined", "how", "scale")}
                           for j in report.get("poses", {}).get("joins", [])]
    write_json(args.json, result)
    print(f"\nexit {done.returncode} in {wall / 60:.1f} min; {len(gt)} frames, {result['path_m']:.1f} m")
    if done.returncode != 0:
        print("\n".join(result["stderr_tail"]))
        return
    print(table(["segment", "frames", "path m", "Sim(3) ATE %", "Sim(3) scale", "path marked", "scale marked"],
                [[s["folder"], f"{s['first']}-{s['last']}", f"{s['path_m']:.2f}", f"{s['ate_pct']:.1f}",
                  f"{s['sim3_scale']:.2f}", "; ".join(s["marks"]["path"]) or "-", "; ".join(s["marks"]["scale"]) or "-"]
                 for s in result["segments"]]))
    print(f"\njoins: {result.get('joins') or 'none'}")
    print(f"\ncovered {100 * result['covered']:.0f} % of the frames; over {MARK_PCT} % and unmarked: "
          f"{result['unmarked_over'] or 'none'}")


if __name__ == "__main__":
    main()
