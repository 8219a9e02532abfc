"""Camera poses from video: accuracy and speed of the dense front end and the SfM fallback.

    python benchmarks/poses.py [--cases 7scenes tum synthetic synthetic-nok] [--methods frontend sfm]

Cases: ``7scenes`` (../shared/data/7scenes-redkitchen, 400 frames, the reader's colour
intrinsics fx = 525, FastDepth prior), ``tum`` (../shared/data/tum-fr1-rpy, 100 frames,
near-pure rotation, FastDepth prior), ``synthetic`` (the synthetic room, 120 frames
640x480, simulated prior), ``synthetic-nok`` (the same with intrinsics withheld:
focal-length error), ``7scenes-nok`` and ``tum-nok`` (the recordings with the focal length
estimated), ``synthetic-fast`` (60 frames of the room walked at 6x speed with motion blur).
A case may add a frame stride and a first frame: ``7scenes/12``, ``tum/3@1`` (issue 20's
fast motion made from the recordings).
``--k1`` (diagnostic): undistort the 7-Scenes frames with a radial coefficient first.
For each case and
method: Sim(3)-aligned ATE RMSE, metric (SE(3)-aligned) ATE RMSE, scale error, RPE (1
frame), path length, keyframes, lost frames and seconds per frame of pose estimation (the
depth prior's time is reported separately). Prints a table and writes
benchmarks/results/poses.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, machine, ping_pong, table, write_json  # noqa: E402

from recon.errors import ReconInputError  # noqa: E402
from recon.eval.trajectory import ate_rmse, path_length, rotation_error, rpe, scale_error  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.poses import estimate_poses  # noqa: E402
from recon.poses.options import parse_pose_option  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# Cases read from ../shared/data ("-nok": the focal length estimated, nothing given).
DATASET_CASES = ("7scenes", "7scenes-nok", "tum", "tum-nok")


def fastdepth(rgb: np.ndarray, intrinsics) -> tuple[np.ndarray, float]:
    from recon.priors import make_prior

    t0 = time.perf_counter()
    out = make_prior("fastdepth", progress=False)(rgb, np.asarray(intrinsics))
    return out.depth, time.perf_counter() - t0


def undistort_radial(rgb: np.ndarray, prior: np.ndarray, intrinsics, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """Frames (N, H, W, 3) and prior (N, H, W) resampled as if taken through a lens with
    radial coefficient k1 removed (same pinhole intrinsics). Diagnostic for --k1 only."""
    from recon.geometry.lens import undistort_images

    return undistort_images(rgb, intrinsics, k1), undistort_images(prior, intrinsics, k1, nearest=True)


def parse_case(name: str) -> tuple[str, int, int, int]:
    """'7scenes/12@100~3' -> ('7scenes', 12, 100, 3): base case, frame stride, first frame,
    passes."""
    name, _, passes = name.partition("~")
    base, _, start = name.partition("@")
    base, _, stride = base.partition("/")
    return base, int(stride or 1), int(start or 0), int(passes or 1)


def load_case(name: str, k1: float = 0.0):
    """rgb (N, H, W, 3), prior (N, h, w), intrinsics or None, gt poses (N, 4, 4), prior seconds.

    name: a base case, optionally with a frame stride, a first frame and passes ('tum/3',
    '7scenes/12@100', '7scenes/4~3'): fast motion made from the recordings (issue 20),
    revisits."""
    rgb, prior, intr, poses, secs = _load_frames(name, k1)
    order = ping_pong(len(rgb), parse_case(name)[3] * (len(rgb) - 1) + 1)
    return rgb[order], prior[order], intr, poses[order], secs


def _load_frames(name: str, k1: float):
    base, stride, start, _ = parse_case(name)
    if base in DATASET_CASES:
        ds = open_dataset(DATA / ("tum-fr1-rpy" if base.startswith("tum") else "7scenes-redkitchen"))
        if stride > 1 or start:
            ds = ds.subset(np.arange(start, len(ds), stride))
        rgb = ds.load_rgb_batch()
        prior, secs = fastdepth(rgb, ds.intrinsics)
        if k1 and base.startswith("7scenes"):
            rgb, prior = undistort_radial(rgb, prior, ds.intrinsics, k1)
        return rgb, prior, (None if base.endswith("-nok") else ds.intrinsics), ds.poses, secs
    from recon.synthetic import render_sequence, simulate_prior

    if base == "synthetic-fast":  # a fast hand-held walk: 6x the path speed, 4 sub-frames of blur
        seq = render_sequence(60, 640, 480, seed=2, speed=6, blur=4)
    else:
        seq = render_sequence(120, 640, 480, seed=0)
    prior = simulate_prior(seq.depth, seed=1)
    return seq.rgb, prior, (None if base == "synthetic-nok" else seq.intrinsics), seq.poses, 0.0


def motion_verdicts(diagnostics: dict) -> list[str]:
    """Why the front end's motion checks distrust its trajectory, and its translation share."""
    if "motion_checks" not in diagnostics:
        return []
    from recon.poses.checks.motion_checks import MotionChecks

    checks = MotionChecks.from_dict(diagnostics["motion_checks"])
    return [f"translation share {checks.translation_share:.2f}, median step {checks.median_step_share:.3f} of the "
            f"width, rotation-only frames {sum(b - a + 1 for a, b in checks.rotation_only)}", *checks.untrusted()]


def evaluate(res, gt: np.ndarray, true_intr) -> dict:
    sim3 = ate_rmse(res.poses, gt, "sim3")
    se3 = ate_rmse(res.poses, gt, "se3")
    rel = rpe(res.poses, gt, 1, scale=1.0)
    length = path_length(gt)
    out = {
        "ate_sim3_m": sim3["rmse"],
        "ate_metric_m": se3["rmse"],
        "ate_sim3_pct_path": 100 * sim3["rmse"] / max(length, 1e-9),
        "scale_error": scale_error(res.poses, gt),
        "rpe_trans_m": rel["trans_rmse"],
        "rpe_rot_deg": rel["rot_rmse_deg"],
        "orientation_median_deg": rotation_error(res.poses, gt)["median_deg"],
        "path_m": length,
        "seconds": res.seconds,
        "s_per_frame": res.seconds / len(res.poses),
        "keyframes": len(res.keyframes),
        "revisits": res.diagnostics.get("revisits", 0),
        "lost_frames": len(res.diagnostics.get("lost_frames", [])),
        "focal": res.intrinsics[0],
        "lens_k1": res.diagnostics.get("lens_k1"),
        # The front end's verdicts on its own trajectory (recon.poses.checks.scale_watch, motion_checks).
        "scale_breaks": len(res.diagnostics.get("scale_watch", {}).get("breaks", [])),
        "untrusted": motion_verdicts(res.diagnostics),
    }
    if true_intr is not None:
        out["focal_error_pct"] = 100 * (res.intrinsics[0] / true_intr[0] - 1)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="+", default=["7scenes", "tum", "synthetic", "synthetic-nok"])
    parser.add_argument("--methods", nargs="+", default=["frontend", "sfm"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--save", type=Path, help="also write each estimate's poses to DIR/<case>-<method>.npz")
    parser.add_argument("--k1", type=float, default=0.0,
                        help="diagnostic: undistort the 7-Scenes frames with this radial coefficient first (the "
                             "dataset publishes no colour calibration); rows are named 7scenes-k1=<value> and "
                             "kept apart from the plain rows")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a front-end setting (FrontendConfig field) for every case, e.g. revisit_flow=0")
    parser.add_argument("--json", default="poses", help="results file name (benchmarks/results/NAME.json)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    # Typed like the CLI's --pose-option (an int field such as global_iters stays an int).
    settings = dict(parse_pose_option(item) for item in args.set)
    tag = "".join(f" [{k}={v}]" for k, v in settings.items())
    results, rows = [], []
    for case in args.cases:
        if parse_case(case)[0] in DATASET_CASES and not DATA.is_dir():
            print(f"skipping {case}: {DATA} not found")
            continue
        rgb, prior, intr, gt, prior_s = load_case(case, args.k1)
        label = (f"{case}-k1={args.k1:g}" if args.k1 and case.startswith("7scenes") else case) + tag
        true_intr = intr
        if case == "synthetic-nok":
            from recon.synthetic import intrinsics_for

            true_intr = intrinsics_for(rgb.shape[2], rgb.shape[1])
        elif parse_case(case)[0] in ("7scenes-nok", "tum-nok"):
            true_intr = open_dataset(DATA / ("tum-fr1-rpy" if case.startswith("tum") else "7scenes-redkitchen")
                                     ).intrinsics
        for method in args.methods:
            if parse_case(case)[0].endswith("-nok") and method == "sfm":
                continue
            try:
                res = estimate_poses(rgb, prior, intr, method=method, progress=False,
                                     **(settings if method == "frontend" else {}))
                if args.save:
                    args.save.mkdir(parents=True, exist_ok=True)
                    np.savez(args.save / f"{label.replace('/', '-s')}-{method}.npz", poses=res.poses, gt=gt,
                             status=np.array(res.diagnostics.get("frame_status", [])))
                entry = {"case": label, "method": method, "frames": len(rgb), "prior_s_per_frame": prior_s / len(rgb),
                         **evaluate(res, gt, true_intr)}
            except ReconInputError as err:
                entry = {"case": label, "method": method, "frames": len(rgb), "error": str(err)}
            results.append(entry)
            print(entry, flush=True)
            if "error" in entry:
                rows.append([label, method, len(rgb), "failed: " + entry["error"][:60], "", "", "", "", "", "", ""])
                continue
            rows.append([
                label, method, len(rgb), f"{100 * entry['ate_sim3_m']:.2f}", f"{100 * entry['ate_metric_m']:.2f}",
                f"{100 * entry['scale_error']:.1f}", f"{entry['orientation_median_deg']:.2f}",
                f"{entry['s_per_frame']:.3f}", entry["keyframes"],
                entry["lost_frames"],
                f"{entry.get('focal_error_pct', float('nan')):+.2f}",
            ])
    print(table(["case", "method", "frames", "ATE Sim(3) cm", "ATE metric cm", "scale err %", "orientation deg",
                 "s/frame", "keyframes",
                 "lost",
                 "focal err %"], rows))
    # Merge with earlier runs of other cases/methods (one JSON for the whole table).
    previous = RESULTS / f"{args.json}.json"
    if previous.is_file():
        done = {(r["case"], r["method"]) for r in results}
        kept = [r for r in json.loads(previous.read_text()).get("results", []) if (r["case"], r["method"]) not in done]
        results = kept + results
    path = write_json(args.json, {"machine": machine(), "results": results})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
