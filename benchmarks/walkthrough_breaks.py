"""Does the front end break on the synthetic walk-through (issue 45)?

    python benchmarks/walkthrough_breaks.py [--width 320 --height 240] [--seed 0] [--window 60]
        [--corridor-length 5] [--turn-degrees 90 --turn-frames 8 --turn-blur 8] [--first 0]

Renders recon.synthetic.walkthrough (three furnished rooms and a plain corridor, ~400
frames at 30 fps: a textureless stretch, a fast blurred turn), gives it a simulated monocular
prior (recon.synthetic.simulate_prior, seed 1) and the true intrinsics, and runs the dense
front end (``estimate_poses(method="frontend")``). Reports the Sim(3) ATE over the whole walk
as a share of the path length, then the Sim(3) scale and ATE of each window of ``--window``
frames and of each named stretch fitted on its own: a scale break (the failure seen on a
hand-held HoloLens walk-through, where the scale jumped x0.66 and x7 between stretches with
exit code 0) shows as windows whose scale differs from the others. A tracking loss is
reported with its frame and the stretches holding it, and the frames before it are tracked
again (unless ``--no-prefix``) to show whether the scale had already broken. ``--first``
tracks the walk from a later frame (e.g. 210, room B: the fast turn on its own). Also
reports the front end's own frame states and, where it has one, its scale watch
(``diagnostics["scale_watch"]``). Last, the walk tracked as ``recon run`` does it
(``--on-break segments``: starting again after each loss, ``restart_after_loss``): the
breaks, how far each lies from the nearest cut (the nearer of where the segment before it
ends and where the next starts: frames between them whose tracking was failing before a loss
get no pose), the fit of each stretch between them and how
many of its frames the short-flow check marked (``--no-pieces`` skips it).

Writes benchmarks/results/walkthrough_breaks.json and prints tables.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, say, table, write_json  # noqa: E402

from recon.eval.trajectory import align, ate_rmse, explained_share, path_length, scale_error  # noqa: E402
from recon.poses import TrackingLostError, estimate_poses  # noqa: E402
from recon.synthetic import simulate_prior  # noqa: E402
from recon.synthetic.walkthrough import render_walkthrough  # noqa: E402

# A window whose scale differs from the median window's by more than this factor is a break.
BREAK_FACTOR = 1.15


def fit(est: np.ndarray, gt: np.ndarray) -> dict:
    """Sim(3) fit of est's camera centres onto gt's over one stretch (poses (n, 4, 4)):
    scale, ATE RMSE (m and % of the stretch's path), and the share of the ground truth's
    spread the fit explains (a scale is only meaningful when that is high)."""
    ate = ate_rmse(est, gt, "sim3")
    length = path_length(gt)
    rot, trans, scale = align(est, gt, "sim3")
    return {"scale": float(ate["scale"]), "ate_m": ate["rmse"], "path_m": length,
            "ate_pct": 100.0 * ate["rmse"] / max(length, 1e-9),
            "explained": explained_share(est, gt, rot, trans, scale)}


def overlapping(stretches: dict, first: int, stop: int) -> str:
    """Names of the stretches that overlap frames [first, stop)."""
    return ", ".join(name for name, (a, b) in stretches.items() if a < stop and b > first and b > a)


def windows(est: np.ndarray, gt: np.ndarray, size: int, stretches: dict, first: int = 0) -> list[dict]:
    """Per window of `size` frames (the last one takes the remainder) of est, gt (n, 4, 4),
    walk frames first .. first + n - 1: the fit and its scale relative to the median
    window's (ratio); break when the ratio is off by BREAK_FACTOR."""
    starts = list(range(0, len(gt) - size // 2, size)) or [0]
    bounds = [(a, min(b, len(gt))) for a, b in zip(starts, starts[1:] + [len(gt)])]
    rows = [{"first": first + a, "stop": first + b, "stretches": overlapping(stretches, first + a, first + b),
             **fit(est[a:b], gt[a:b])} for a, b in bounds]
    median = float(np.median([r["scale"] for r in rows]))
    for r in rows:
        r["ratio"] = r["scale"] / median
        r["break"] = not (1 / BREAK_FACTOR <= r["ratio"] <= BREAK_FACTOR)
    return rows


def track(walk, prior: np.ndarray, first: int, stop: int, window: int) -> dict:
    """The front end on walk frames [first, stop) and its fits (whole, per window, per
    stretch; frames and stretches in frames of the walk), or the frame where it lost the camera."""
    t0 = time.perf_counter()
    try:
        res = estimate_poses(walk.rgb[first:stop], prior[first:stop], walk.intrinsics, method="frontend",
                             progress=False)
    except TrackingLostError as err:
        lost = None if err.frame is None else first + err.frame
        say(f"frames {first}-{stop - 1}: tracking lost at frame {lost}: {err}")
        where = overlapping(walk.stretches, lost, lost + 1) if lost is not None else ""
        return {"first": first, "stop": stop, "pose_s": time.perf_counter() - t0,
                "lost": {"frame": lost, "message": str(err), "in": where}}
    seconds = time.perf_counter() - t0
    say(f"frames {first}-{stop - 1}: tracked in {seconds:.0f} s")
    est, gt = res.poses, walk.poses[first:stop]
    stretches = {name: (max(a, first), min(b, stop)) for name, (a, b) in walk.stretches.items()
                 if a < stop and b > first}
    status = res.diagnostics.get("frame_status", [])
    return {
        "first": first, "stop": stop, "pose_s": seconds, "lost": None, "overall": fit(est, gt),
        "metric_scale_error": scale_error(est, gt), "keyframes": len(res.keyframes),
        "frame_states": dict(Counter(status)),
        "untrusted": [first + i for i, s in enumerate(status) if s in ("recovered", "interpolated")],
        "windows": windows(est, gt, window, stretches, first), "stretches": stretches,
        "named": {name: fit(est[a - first : b - first], gt[a - first : b - first])
                  for name, (a, b) in stretches.items() if b - a >= 10},
        "scale_watch": res.diagnostics.get("scale_watch"),
    }


def in_pieces(walk, prior: np.ndarray) -> dict:
    """The front end as ``recon run`` asks for it (``--on-break segments``: tracking starts
    again where the camera was lost, ``restart_after_loss``): the breaks its scale watch
    calls (steps, creeps, restarts) with their distance to the nearest cut the scene was
    built with, and the Sim(3) fit of each stretch between them (the segments a run writes
    before it tries to join them)."""
    t0 = time.perf_counter()
    try:
        res = estimate_poses(walk.rgb, prior, walk.intrinsics, method="frontend", progress=False,
                             restart_after_loss=True)
    except TrackingLostError as err:
        return {"pose_s": time.perf_counter() - t0, "lost": {"frame": err.frame, "message": str(err)}}
    watch = res.diagnostics.get("scale_watch") or {"breaks": []}
    posed = np.isfinite(res.poses).all(axis=(1, 2))
    breaks = []
    for b in watch["breaks"]:
        # The segment before a break ends at its last posed frame (frames between it and the
        # break's `after` have no pose: tracking was failing there before a loss).
        ends = int(np.flatnonzero(posed[: b["after"]])[-1]) if posed[: b["after"]].any() else b["after"] - 1
        breaks.append({**b, "ends": ends, "to_cut": int(min(min(abs(ends + 1 - c), abs(b["after"] - c))
                                                            for c in walk.cuts))})
    bounds = [0, *[b["after"] for b in breaks], walk.num_frames]
    short = (res.diagnostics.get("motion_checks") or {}).get("short_flow", [])
    stretches = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        posed = np.arange(a, b)[np.isfinite(res.poses[a:b]).all(axis=(1, 2))]
        if len(posed) >= 3:
            names = overlapping(walk.stretches, a, b)
            marked = sum(max(0, min(b, last + 1) - max(a, first)) for first, last in short)
            stretches.append({"first": a, "stop": b, "posed": len(posed), "stretches": names,
                              "marked_short": int(marked), **fit(res.poses[posed], walk.poses[posed])})
    return {"pose_s": time.perf_counter() - t0, "lost": None, "pieces": res.diagnostics.get("pieces"),
            "breaks": breaks, "short_flow": short, "segments": stretches}


def report_pieces(run: dict) -> None:
    if run["lost"]:
        print(f"\nIn pieces: tracking lost at frame {run['lost']['frame']}: {run['lost']['message']}")
        return
    print("\nIn pieces (recon run's default, --on-break segments), breaks of the scale watch and the "
          "stretches between them:\n")
    print(table(["segment ends", "next starts", "kind", "factor", "frames to the nearest cut"],
                [[b.get("ends", b["after"] - 1), b["after"], b["kind"], f"{b['factor']:.2f}", b["to_cut"]]
                 for b in run["breaks"]]))
    print()
    print(table(["frames", "posed", "marked short", "path m", "Sim(3) ATE %", "scale", "stretches"],
                [[f"{s['first']}-{s['stop'] - 1}", s["posed"], s["marked_short"], f"{s['path_m']:.2f}",
                  f"{s['ate_pct']:.1f}", f"{s['scale']:.3f}", s["stretches"]] for s in run["segments"]]))
    print(f"\nFrames the short-flow check marked (recon.poses.checks.normal_flow): {run['short_flow'] or 'none'}")


def run(args) -> dict:
    t0 = time.perf_counter()
    walk = render_walkthrough(args.width, args.height, seed=args.seed, corridor_length=args.corridor_length,
                              turn_degrees=args.turn_degrees, turn_frames=args.turn_frames, turn_blur=args.turn_blur)
    render_s = time.perf_counter() - t0
    say(f"rendered {walk.num_frames} frames {args.width}x{args.height} in {render_s:.1f} s; "
        f"stretches {walk.stretches}; cuts {walk.cuts}")
    prior = simulate_prior(walk.depth, seed=1)
    out = {"machine": machine(), "args": vars(args), "frames": walk.num_frames, "render_s": render_s,
           "stretches": walk.stretches, "cuts": walk.cuts, "settings": walk.settings,
           "path_m": path_length(walk.poses),
           "whole": track(walk, prior, args.first, walk.num_frames, args.window)}
    lost = out["whole"]["lost"]
    # What the front end had before it lost the camera: had the scale already broken?
    if args.prefix and lost and lost["frame"] is not None and lost["frame"] - args.first >= 2 * args.window:
        out["before_loss"] = track(walk, prior, args.first, int(lost["frame"]), args.window)
    if args.pieces:
        out["pieces"] = in_pieces(walk, prior)
    return out


def report_run(run: dict, title: str, window: int) -> None:
    """Print one front-end run's fits, or where it lost the camera."""
    if run["lost"]:
        print(f"\n{title}: tracking lost at frame {run['lost']['frame']} (in: {run['lost']['in'] or '-'}): "
              f"{run['lost']['message']}")
        return
    w = run["overall"]
    print(f"\n{title} (frames {run['first']}-{run['stop'] - 1}, {w['path_m']:.2f} m): Sim(3) ATE {w['ate_m']:.3f} m = "
          f"{w['ate_pct']:.1f} % of the path, Sim(3) scale {w['scale']:.3f}, metric scale error "
          f"{run['metric_scale_error']:.3f}; keyframes {run['keyframes']}, frame states {run['frame_states']}, "
          f"{run['pose_s']:.0f} s")
    print(f"\nWindows of {window} frames (scale fitted per window; ratio to the median window; "
          f"break beyond x{BREAK_FACTOR}):\n")
    rows = [[f"{r['first']}-{r['stop'] - 1}", f"{r['scale']:.3f}", f"{r['ratio']:.2f}", f"{r['ate_m']:.3f}",
             f"{r['ate_pct']:.1f}", f"{r['explained']:.2f}", "BREAK" if r["break"] else "", r["stretches"]]
            for r in run["windows"]]
    print(table(["frames", "scale", "ratio", "ATE m", "ATE %", "explained", "", "stretches"], rows))
    print("\nNamed stretches (fitted on their own):\n")
    rows = [[name, f"{a}-{b - 1}", f"{f['scale']:.3f}", f"{f['ate_m']:.3f}", f"{f['ate_pct']:.1f}",
             f"{f['explained']:.2f}"]
            for name, f in run["named"].items() for a, b in [run["stretches"][name]]]
    print(table(["stretch", "frames", "scale", "ATE m", "ATE %", "explained"], rows))
    if run.get("scale_watch") is not None:
        print(f"\nFront end's scale watch: {run['scale_watch'].get('breaks', run['scale_watch'])}")


def report(out: dict, window: int) -> None:
    print(f"\nWalk-through: {out['frames']} frames, {out['path_m']:.2f} m; cuts {out['cuts']}; "
          f"stretches {out['stretches']}")
    report_run(out["whole"], "The walk", window)
    if "before_loss" in out:
        report_run(out["before_loss"], "The frames before the loss, tracked again", window)
    if "pieces" in out:
        report_pieces(out["pieces"])


def plain(obj):
    """JSON-ready copy of obj: numpy arrays and scalars as lists and numbers."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--window", type=int, default=60, help="frames per window of the per-window fit")
    parser.add_argument("--first", type=int, default=0, help="track from this frame of the walk on")
    parser.add_argument("--corridor-length", type=float, default=5.0)
    parser.add_argument("--turn-degrees", type=float, default=90.0)
    parser.add_argument("--turn-frames", type=int, default=8)
    parser.add_argument("--turn-blur", type=int, default=8)
    parser.add_argument("--no-prefix", dest="prefix", action="store_false",
                        help="when tracking is lost, do not track the frames before the loss again")
    parser.add_argument("--no-pieces", dest="pieces", action="store_false",
                        help="do not also track the walk in pieces, starting again after each loss (recon run's way)")
    parser.add_argument("--name", default="walkthrough_breaks", help="results file name")
    args = parser.parse_args()
    out = run(args)
    report(out, args.window)
    path = write_json(args.name, plain(out))
    pose_s = sum(out.get(k, {}).get("pose_s", 0.0) for k in ("whole", "before_loss", "pieces"))
    say(f"render {out['render_s']:.0f} s, poses {pose_s:.0f} s; wrote {path}")


if __name__ == "__main__":
    main()
