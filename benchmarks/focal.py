"""The focal length of a video without intrinsics, measured on the real recordings' clips.

For each clip (the first 80 frames from a start frame: what the front end buffers for its
focal search, ``8 * calib_keyframes``) this runs what ``recon.poses.frontend`` runs before
tracking: the lens from straight edges (``plumb_line``), the flow-based focal search
through it (``calib.estimate_focal``), the focal length from vanishing points
(``vanishing.estimate_focal_vp``) and the front end's choice between the two
(``vanishing.agrees_with_search`` with ``FrontendConfig.vanishing_window``); each against
the focal length the dataset's reader gives (7-Scenes' colour camera ~525 px, TUM fr1's
calibration 517.3 px). The search's depth prior is FastDepth's, run at the reader's focal
length. Clips start every 50 frames of 7-Scenes redkitchen 0-399 (and at 320) and at 0,
10 and 20 of TUM fr1/rpy.

Usage: python benchmarks/focal.py [--clips 7scenes@0 tum@10 ...] [--json focal]
Prints a table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, say, table, write_json  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RECORDINGS = {"7scenes": DATA / "7scenes-redkitchen", "tum": DATA / "tum-fr1-rpy"}
CLIPS = [f"7scenes@{s}" for s in (0, 50, 100, 150, 200, 250, 300, 320)] + [f"tum@{s}" for s in (0, 10, 20)]


def measure_clip(name: str, prior_model) -> dict:
    from recon.io.datasets import open_dataset
    from recon.poses import vanishing
    from recon.poses.calib import estimate_focal
    from recon.poses.frontend_config import FrontendConfig
    from recon.poses.plumb_line import estimate_lens
    from recon.poses.result import PriorSource

    recording, start = name.split("@")
    dataset = open_dataset(RECORDINGS[recording])
    cfg = FrontendConfig()
    frames = [dataset.rgb(i) for i in range(int(start), min(int(start) + 8 * cfg.calib_keyframes, len(dataset)))]
    true_f = float(dataset.intrinsics[0])
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
    used = vanishing.agrees_with_search(vp, search.focal, cfg.vanishing_window)
    chosen = vp.focal if used else search.focal

    def error(f: float) -> float | None:
        return 100.0 * (f / true_f - 1.0) if f > 0 else None

    return {"clip": name, "frames": len(frames), "true_focal": true_f, "lens_corner_shift": lens.corner_shift,
            "lens_trusted": lens.trusted, "search_focal": search.focal, "search_error_pct": error(search.focal),
            "vp_focal": vp.focal, "vp_error_pct": error(vp.focal), "vp": vp.to_dict(), "vp_used": used,
            "chosen_focal": chosen, "chosen_error_pct": error(chosen),
            "seconds": {"lens": t1 - t0, "search": t2 - t1, "vanishing_points": t3 - t2}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clips", nargs="*", default=CLIPS)
    parser.add_argument("--json", default="focal")
    args = parser.parse_args()
    missing = [str(p) for p in RECORDINGS.values() if not p.is_dir()]
    if missing:
        sys.exit(f"focal.py: needs the recordings in ../shared/data; missing: {', '.join(missing)}")
    from recon.priors import make_prior

    torch.set_num_threads(2)
    prior_model = make_prior("fastdepth", features=False, progress=False)
    rows = []
    for name in args.clips:
        say(name)
        rows.append(measure_clip(name, prior_model))

    def pct(v: float | None) -> str:
        return "-" if v is None else f"{v:+.1f} %"

    print(table(["clip", "flow search", "vanishing points", "agreeing frames", "trusted", "used", "chosen",
                 "s (lens / search / vp)"],
                [[r["clip"], pct(r["search_error_pct"]), pct(r["vp_error_pct"]),
                  f"{r['vp']['agreeing']} / {r['vp']['frames']} ({r['vp']['share']:.2f})", r["vp"]["trusted"],
                  r["vp_used"], pct(r["chosen_error_pct"]),
                  " / ".join(f"{v:.1f}" for v in r["seconds"].values())] for r in rows]))
    path = write_json(args.json, {"machine": machine(), "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
