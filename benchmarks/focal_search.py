"""The focal search of this checkout against an earlier commit's, on the same clips.

For each clip (as in benchmarks/focal.py: up to 80 frames from a start frame at 640 px,
FastDepth as the prior, the plumb-line lens where trusted) ``calib.estimate_focal`` runs
twice on the same flows and BA: once with this checkout's ``search_focal`` and once with
the one in ``recon/poses/intrinsics/calib.py`` at ``--baseline`` (read with ``git show``).
The table gives both focal lengths against the recording's, the evaluations of the cost
each needed and the seconds (the two in turn, so that drift touches both alike).

Usage: python benchmarks/focal_search.py --baseline REV [--clips 7scenes@0 ...] [--json focal_search]
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, say, table, write_json  # noqa: E402
from benchmarks.focal import clip_frames  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CALIB = "recon/poses/intrinsics/calib.py"
# One or two clips of each recording (benchmarks/focal.py names them).
DEFAULT_CLIPS = ["7scenes@0", "7scenes@300", "tum@0", "tum@20", "scannet@0+29", "scannet@29+29", "record3d@0",
                 "record3d@100", "kitti@0+25", "kitti@25+26", "phone@0+35", "phone-video@0", "phone-video@200"]


def baseline_search(rev: str):
    """``search_focal`` of calib.py at git revision `rev`."""
    source = subprocess.run(["git", "show", f"{rev}:{CALIB}"], cwd=ROOT, check=True, capture_output=True,
                            text=True).stdout
    path = Path(tempfile.mkdtemp()) / "calib_baseline.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("calib_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["calib_baseline"] = module
    spec.loader.exec_module(module)
    return module.search_focal


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", required=True, help="git revision whose search_focal is compared")
    parser.add_argument("--clips", nargs="*", default=DEFAULT_CLIPS)
    parser.add_argument("--json", default="focal_search")
    args = parser.parse_args()
    from recon.poses.config import FrontendConfig
    from recon.poses.intrinsics import calib
    from recon.poses.intrinsics.plumb_line import estimate_lens
    from recon.poses.result import PriorSource
    from recon.priors import make_prior

    torch.set_num_threads(2)
    prior_model = make_prior("fastdepth", features=False, progress=False)
    searches = {"baseline": baseline_search(args.baseline), "now": calib.search_focal}
    rows = []
    try:
        for name in args.clips:
            say(name)
            recording, _, span = name.partition("@")
            start, _, count = span.partition("+")
            frames, true_f = clip_frames(recording, int(start), int(count) if count else 80)
            height, width = frames[0].shape[:2]
            intrinsics = np.array((true_f, true_f, (width - 1) / 2, (height - 1) / 2))
            prior = PriorSource(prior_model(np.stack(frames), intrinsics).depth)
            lens = estimate_lens(frames)
            row = {"clip": name, "true_focal": true_f}
            for label, search in searches.items():
                calib.search_focal = search
                t0 = time.perf_counter()
                result = calib.estimate_focal(frames, prior, FrontendConfig(), lens if lens.trusted else None)
                row[label] = {"focal": result.focal, "error_pct": 100.0 * (result.focal / true_f - 1.0),
                              "evaluations": len(result.evaluations), "seconds": time.perf_counter() - t0,
                              "bracketed": result.bracketed}
            rows.append(row)
    finally:
        calib.search_focal = searches["now"]
    print(f"machine: {machine()}")
    print(table(["clip", "true f", "baseline f (error)", "now f (error)", "evaluations", "seconds"],
                [[r["clip"], f"{r['true_focal']:.1f}",
                  f"{r['baseline']['focal']:.1f} ({r['baseline']['error_pct']:+.1f} %)",
                  f"{r['now']['focal']:.1f} ({r['now']['error_pct']:+.1f} %)",
                  f"{r['baseline']['evaluations']} / {r['now']['evaluations']}",
                  f"{r['baseline']['seconds']:.1f} / {r['now']['seconds']:.1f}"] for r in rows]))
    total = {k: sum(r[k]["evaluations"] for r in rows) for k in searches}
    print(f"evaluations in all: baseline {total['baseline']}, now {total['now']}")
    print(f"wrote {write_json(args.json, {'machine': machine(), 'baseline': args.baseline, 'rows': rows})}")


if __name__ == "__main__":
    main()
