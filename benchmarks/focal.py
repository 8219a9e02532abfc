"""The focal length of footage without intrinsics, measured on every recording with known
intrinsics.

For each clip (up to 80 frames from a start frame: what the front end buffers for its
focal search, ``8 * calib_keyframes``; fewer where the recording or segment is shorter)
this runs what ``recon.poses.frontend.streaming`` runs before tracking: the lens from straight edges
(``plumb_line``), the flow-based focal search through it (``calib.estimate_focal``), the
focal length from vanishing points (``vanishing.estimate_focal_vp``) and the front end's
choice between them (``recon.poses.intrinsics.focal_choice``); each against the focal length the
recording publishes (7-Scenes' colour camera ~525 px, TUM fr1's calibration, ScanNet's,
Record3D's ARKit K, KITTI's P0, the phone model's median COLMAP camera), at the working
width of 640 px the pipeline uses. The frames are the recordings' own images (the phone
video's decoded frames for ``phone-video``), resized to that width. The search's depth
prior is FastDepth's.

Usage: python benchmarks/focal.py [--clips 7scenes@0 tum@10 ...] [--json focal]
       python benchmarks/focal.py --rechoose results/focal_probe.json results/focal_curves.json
           (the current rule applied again to measured estimates: seconds, not 40 minutes)
Prints a table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, say, table, write_json  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
WIDTH = 640
# recording: (dataset folder, footage: None = the dataset's images, else a video under DATA)
RECORDINGS = {"7scenes": ("7scenes-redkitchen", None), "tum": ("tum-fr1-rpy", None),
              "scannet": ("scannet-scene0005_00", None), "record3d": ("record3d-door-handle", None),
              "kitti": ("kitti-odometry-seq1", None), "phone": ("phone-beer", None),
              "phone-video": ("phone-beer", "phone-beer/Beer.mp4")}
# recording@start[+frames]: at most 80 frames (the focal search's buffer) unless told.
CLIPS = ([f"7scenes@{s}" for s in (0, 100, 200, 300)] + ["tum@0", "tum@20", "scannet@0+29", "scannet@29+29"]
         + [f"record3d@{s}" for s in (0, 100, 200)] + ["kitti@0+25", "kitti@25+26", "phone@0+35", "phone@35+36"]
         + [f"phone-video@{s}" for s in (0, 200, 400, 600)])


def clip_frames(recording: str, start: int, count: int) -> tuple[list[np.ndarray], float]:
    """The clip's frames at the working width and the published focal length at that width."""
    from recon.io.datasets import open_dataset
    from recon.io.frames import open_source
    from recon.io.source import resize_rgb, size_at_width

    folder, video = RECORDINGS[recording]
    dataset = open_dataset(DATA / folder)
    true_f = float(dataset.intrinsics[0]) * WIDTH / dataset.width
    if video is not None:
        source = open_source(DATA / video, width=WIDTH)
        frames = [f.rgb for _, f in zip(range(start + count), source)][start:]
        return frames, true_f
    shape = size_at_width(dataset.height, dataset.width, WIDTH)
    stop = min(start + count, len(dataset))
    return [resize_rgb(dataset.rgb(i), shape) for i in range(start, stop)], true_f


def measure_clip(name: str, prior_model) -> dict:
    from recon.poses.config import FrontendConfig
    from recon.poses.intrinsics import vanishing
    from recon.poses.intrinsics.calib import estimate_focal
    from recon.poses.intrinsics.plumb_line import estimate_lens
    from recon.poses.result import PriorSource

    recording, _, span = name.partition("@")
    start, _, count = span.partition("+")
    cfg = FrontendConfig()
    frames, true_f = clip_frames(recording, int(start), int(count) if count else 8 * cfg.calib_keyframes)
    height, width = frames[0].shape[:2]
    prior = PriorSource(prior_model(np.stack(frames), np.array((true_f, true_f, (width - 1) / 2, (height - 1) / 2)))
                        .depth)
    t0 = time.perf_counter()
    lens = estimate_lens(frames)
    t1 = time.perf_counter()
    search = estimate_focal(frames, prior, cfg, lens if lens.trusted else None)
    t2 = time.perf_counter()
    vp = vanishing.estimate_focal_vp(frames, lens)
    t3 = time.perf_counter()
    return {"clip": name, "frames": len(frames), "true_focal": true_f, "lens_corner_shift": lens.corner_shift,
            "lens_trusted": lens.trusted, "seconds": {"lens": t1 - t0, "search": t2 - t1, "vanishing_points": t3 - t2},
            **judged(search, vp, true_f)}


def judged(search, vp, true_f: float) -> dict:
    """The two estimates, the front end's choice between them (recon.poses.intrinsics.focal_choice) and
    issue 44's verdict: within 10 %, or a warning whose range holds the true value."""
    from recon.poses.config import FrontendConfig
    from recon.poses.intrinsics import focal_choice

    choice = focal_choice.choose_focal(search, vp, FrontendConfig())

    def error(f: float) -> float | None:
        return 100.0 * (f / true_f - 1.0) if f > 0 else None

    holds = choice.disagree and choice.low <= true_f <= choice.high
    return {"search_focal": search.focal, "search_error_pct": error(search.focal),
            "search_evaluations": search.evaluations,
            "vp_focal": vp.focal, "vp_error_pct": error(vp.focal), "vp": vp.to_dict(), "choice": choice.to_dict(),
            "chosen_focal": choice.focal, "chosen_error_pct": error(choice.focal), "range_holds_truth": holds,
            "accepted": abs(error(choice.focal)) <= 10.0 or holds}


def swept_to_a_minimum(evaluations: list[tuple[float, float]]) -> bool:
    """Whether the search's sweep (its first evaluations, recon.poses.intrinsics.calib.candidate_focals
    in order) had its best score inside, not at an end; True where fewer were recorded."""
    from recon.poses.intrinsics.calib import candidate_focals

    sweep = len(candidate_focals(640, 480))
    if len(evaluations) < sweep:
        return True
    scores = [score for _, score in evaluations[:sweep]]
    return 0 < scores.index(min(scores)) < sweep - 1


def rechosen(paths: list[Path]) -> list[dict]:
    """The rows of earlier runs' JSON with the current rule applied again to their estimates
    (the search's evaluations taken from whichever file has them): a rule change costs
    seconds, not the 40 minutes of measuring every clip again."""
    from recon.poses.intrinsics.calib import FocalSearch
    from recon.poses.intrinsics.vanishing import VanishingFocal

    rows: dict[str, dict] = {}
    for path in paths:
        for row in json.loads(path.read_text())["rows"]:
            if row["clip"] not in rows or row.get("search_evaluations"):
                rows[row["clip"]] = row
    out = []
    for row in sorted(rows.values(), key=lambda r: CLIPS.index(r["clip"]) if r["clip"] in CLIPS else len(CLIPS)):
        evaluations = [tuple(e) for e in row.get("search_evaluations") or [(row["search_focal"], 1.0)]]
        search = FocalSearch(row["search_focal"], evaluations, swept_to_a_minimum(evaluations))
        out.append({**row, **judged(search, VanishingFocal(**row["vp"]), row["true_focal"])})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", nargs="*", default=CLIPS)
    parser.add_argument("--json", default="focal")
    parser.add_argument("--rechoose", nargs="+", type=Path, metavar="JSON",
                        help="measure nothing: apply the current rule again to these earlier results' estimates")
    args = parser.parse_args()
    if args.rechoose:
        return report(rechosen(args.rechoose), args.json)
    missing = [folder for folder, _ in RECORDINGS.values() if not (DATA / folder).is_dir()]
    if missing:
        sys.exit(f"focal.py: needs the recordings in ../shared/data; missing: {', '.join(missing)}")
    from recon.priors import make_prior

    torch.set_num_threads(2)
    prior_model = make_prior("fastdepth", features=False, progress=False)
    rows = []
    for name in args.clips:
        say(name)
        rows.append(measure_clip(name, prior_model))
    report(rows, args.json)


def report(rows: list[dict], name: str) -> None:
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{v:+.1f} %"

    print(table(["clip", "flow search", "vanishing points", "agreeing frames", "trusted", "chosen", "from",
                 "range said (true in it)", "accepted", "s (lens / search / vp)"],
                [[r["clip"], pct(r["search_error_pct"]), pct(r["vp_error_pct"]),
                  f"{r['vp']['agreeing']} / {r['vp']['frames']} ({r['vp']['share']:.2f})", r["vp"]["trusted"],
                  pct(r["chosen_error_pct"]), r["choice"]["source"],
                  f"{r['choice']['low']:.0f}-{r['choice']['high']:.0f} ({r['range_holds_truth']})"
                  if r["choice"]["disagree"] else "-", r["accepted"],
                  " / ".join(f"{v:.1f}" for v in r["seconds"].values())] for r in rows]))
    accepted = sum(r["accepted"] for r in rows)
    print(f"{accepted} of {len(rows)} clips within 10 % or with a warning whose range holds the true focal length")
    path = write_json(name, {"machine": machine(), "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
