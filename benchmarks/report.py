"""The benchmark report: paper-style tables A-D and the ablations for every real recording.

    python benchmarks/report.py                        # every recording in ../shared/data
    python benchmarks/report.py /data/scene0000_00     # ... plus extra RGB-D dataset folders
    python benchmarks/report.py --datasets tum-fr1-rpy --step tum-fr1-rpy=2
    python benchmarks/report.py --quick                # 12 frames each: a one-minute smoke run

Run it alone on the machine (`flock /tmp/recon-cpu.lock python benchmarks/report.py`): the
speed table is only as good as the machine is quiet. Frames: every `--step`-th frame
(default: the smallest step giving at most 100 frames; 7-Scenes 400 -> every 4th, TUM 100
-> every frame). Everything else is fixed so that the tables are comparable run to run:

* Depth prior: FastDepth with stride-8 encoder features, exactly as `recon run` builds it
  (computed once per recording, shared by every row). MEDeA: `MedeaConfig.fast()` (its
  feature loss is S), with feature loss S, M or none; table D runs `recon run`'s own
  (`recon.core.config.pipeline_medea`: the same, Stage I on overlapping keyframe pairs).
* Table A (paper Table 1): ground-truth poses, metric depth, no alignment. Rows: prior,
  MEDeA-S, MEDeA-M, MEDeA without feature loss, and sensor depth (the reference: 0 error
  against itself by construction; its multi-view inconsistency is the floor that real
  depth reaches). Columns: `recon.eval.depth.depth_metrics` (frame-averaged) and
  `multiview_inconsistency`.
* Table B (paper Table 2): poses estimated by `recon.poses.estimate_poses` (method "auto",
  as `recon run --poses estimate`; taken from the pipeline run of table D when there is
  one), MEDeA on them, depth median-scaled once per sequence (main columns) and per frame
  (extra columns); inconsistency under the estimated poses; ATE (Sim(3), SE(3)) and scale
  error of the poses.
* Table C: TSDF mesh of each depth source fused with ground-truth poses (Open3D, the same
  voxel size and depth range for all: the voxel `recon.fusion` would choose for the sensor
  depth) against `recon.eval.evaluate.reference_tsdf_mesh` (the sensor depth's TSDF mesh):
  accuracy, completeness, precision, recall, F-score at 5 cm. The sensor row must score
  F = 1 (sanity check). Rows with estimated poses are Sim(3)-aligned to ground truth first
  (the refinement's also SE(3)-aligned, and Sim(3)-aligned then registered by ICP).
* Table D: `recon.pipeline.run_pipeline` on the recording folder (same frame step), once
  with ground-truth poses and once estimating them, Rerun recording saved (so "logging" is
  timed), each in a fresh process: seconds per frame per stage and peak resident memory
  (`resource.getrusage(RUSAGE_SELF).ru_maxrss` of that process, imports included).
* Ablations (paper's ablation tables, on MEDeA-M as the paper does; `--ablation-base S`
  for the pipeline's default): without photometric, depth or feature loss, without scale
  propagation (`propagate_scale=False`: non-keyframes start at scale 1), Stage II only
  (`run_stage1=False`: every frame optimised from scale 1 with Stage II's schedule).

Every row shows the paper's number for the nearest setting and what differs. Goals are
checked at the end. Writes benchmarks/results/report.json and rewrites the section of
docs/benchmarks.md between `<!-- report:begin -->` and `<!-- report:end -->` (created
after the title if absent). `--quick` writes neither (JSON to a temporary file).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import machine, write_json  # noqa: E402
from priors import MAX_DEPTH  # noqa: E402
from report_tables import evaluate_recording  # noqa: E402
from report_text import (  # noqa: E402
    BEGIN,
    DOCS,
    END,
    GOALS,
    PAPER_ABLATION,
    PAPER_SECONDS,
    PAPER_SETUP,
    PAPER_T1,
    PAPER_T2,
    PRESET,
    goals,
    render,
    render_all,
    update_docs,
)

from recon.io.datasets import detect_kind, open_dataset  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
TARGET_FRAMES = 100


def default_datasets() -> list[Path]:
    """Every recording in DATA with sensor depth: tables A-C score depth and meshes against it."""
    if not DATA.is_dir():
        return []
    found = sorted(p for p in DATA.iterdir() if p.is_dir() and detect_kind(p) is not None)
    without = [p.name for p in found if not open_dataset(p).has_depth]
    if without:
        print(f"report: skipping {', '.join(without)} (no sensor depth to score against)", flush=True)
    return [p for p in found if p.name not in without]


def resolve_dataset(spec: str) -> Path:
    path = Path(spec)
    if path.is_dir():
        return path.resolve()
    if (DATA / spec).is_dir():
        return DATA / spec
    matches = [p for p in sorted(DATA.iterdir()) if p.is_dir() and p.name.startswith(spec)] if DATA.is_dir() else []
    if len(matches) == 1:
        return matches[0]
    sys.exit(f"report: no dataset folder {spec!r} (neither a path nor a recording in {DATA})")


def parse_steps(specs: list[str]) -> tuple[int | None, dict[str, int]]:
    """--step K (all) and --step NAME=K entries."""
    default, named = None, {}
    for spec in specs:
        if "=" in spec:
            name, value = spec.split("=", 1)
            named[name] = int(value)
        else:
            default = int(spec)
    return default, named


def git_commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                             text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "recon", "medea_core", "mvs_core",
                                "benchmarks/report.py", "benchmarks/report_runs.py", "benchmarks/report_tables.py",
                                "benchmarks/report_text.py"],
                               cwd=ROOT, capture_output=True, text=True).stdout.strip()
        return sha + ("+changes" if dirty else "")
    except OSError:
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("extra", nargs="*", help="extra RGB-D dataset folders (any layout open_dataset reads)")
    parser.add_argument("--datasets", nargs="*", default=None,
                        help=f"recordings: names in {DATA} or folders (default: every recording there)")
    parser.add_argument("--step", nargs="*", default=[],
                        help="frame step: K for all, or NAME=K per recording (default: at most 100 frames)")
    parser.add_argument("--ablation-base", choices=("M", "S"), default="M",
                        help="MEDeA row the ablations start from (M: as in the paper; S: the pipeline default)")
    parser.add_argument("--mesh-points", type=int, default=200_000, help="surface samples per mesh")
    parser.add_argument("--no-pipeline", action="store_true", help="skip table D (the pipeline runs)")
    parser.add_argument("--quick", action="store_true",
                        help="12 frames per recording, 20 + 5 MEDeA epochs; writes a temporary JSON, no docs")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-docs", action="store_true", help="do not rewrite docs/benchmarks.md")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    named = [resolve_dataset(s) for s in [*(args.datasets or []), *args.extra]]
    paths = named if args.datasets is not None else default_datasets() + named
    if not paths:
        sys.exit(f"report: no recordings (none with sensor depth in {DATA}; pass dataset folders)")
    # default_datasets() has left out those without depth already; a named one is refused.
    no_depth = [p.name for p in named if not open_dataset(p).has_depth]
    if no_depth:
        sys.exit(f"report: {', '.join(no_depth)} has no sensor depth; tables A-C need it")
    default_step, named_steps = parse_steps(args.step)
    start = time.perf_counter()
    payload = {"command": " ".join(["python benchmarks/report.py", *sys.argv[1:]]),
               "date": datetime.datetime.now().isoformat(timespec="seconds"), "commit": git_commit(),
               "machine": machine(), "preset": PRESET, "ablation_base": args.ablation_base, "max_depth": MAX_DEPTH,
               "goals": GOALS, "paper": {"table1": PAPER_T1, "table2": PAPER_T2, "ablation": PAPER_ABLATION,
                                         "seconds_per_frame": PAPER_SECONDS, "setup": PAPER_SETUP},
               "recordings": {}}
    with tempfile.TemporaryDirectory(prefix="recon-report-") as workdir:
        for path in paths:
            count = len(open_dataset(path))
            step = named_steps.get(path.name, default_step) or max(1, math.ceil(count / TARGET_FRAMES))
            record = evaluate_recording(path, step, args, Path(workdir))
            record["goals"] = goals(record)
            payload["recordings"][path.name] = record
            print("\n" + render(record), flush=True)
    payload["wall_minutes"] = (time.perf_counter() - start) / 60
    payload["load_average"] = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    payload["report_process_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if args.quick:
        out = Path(tempfile.gettempdir()) / "recon-report-quick.json"
        out.write_text(json.dumps(payload, indent=2, default=_json_default))
        print(f"quick run: wrote {out} (not report.json, docs untouched); {payload['wall_minutes']:.1f} min")
        return
    path = write_json("report", json.loads(json.dumps(payload, default=_json_default)))
    print(f"wrote {path}; {payload['wall_minutes']:.1f} min")
    if not args.no_docs:
        update_docs(render_all(payload))
        print(f"updated {DOCS} (between {BEGIN} and {END})")


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return str(value)


if __name__ == "__main__":
    main()
