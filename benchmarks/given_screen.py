"""A fast screen of refinement and fusion variants on the validation table's given mode.

The same `recon run DATASET --start S --max-frames N VARIANT` runs and `recon eval` scores
as ``benchmarks/validate.py --modes given``, but in one process, with MEDeA's result kept
between the variants of a segment: MEDeA is deterministic on the CPU
(tests/test_medea_core.py), so a variant that does not touch MEDeA's inputs or settings gets
the very depth it would compute again. What it saves is MEDeA's share of each run (about
half), so that a refinement or fusion setting is screened on every segment in minutes;
the winner is then confirmed by validate.py itself.

Usage: python benchmarks/given_screen.py --variant "LABEL=ARGS" [...] [--recordings ...]
    [--segments 0 1] [--work DIR] [--json given_screen]
The first variant is the baseline; prints a row per run and the comparison, writes
benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import pickle
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, parse_variant, say, table, write_json  # noqa: E402
from benchmarks.validate import DATA, HEADERS, RECORDINGS, comparison, scores, selection, table_row  # noqa: E402

# Recordings whose given mode has a reference mesh to score against.
SCORED = ("7scenes", "tum", "scannet", "record3d")


def memoised_medea():
    """Patch the pipeline's MEDeA call with one that keeps its result by its inputs: the
    frames, prior, poses, intrinsics, features and settings (a digest of their bytes)."""
    import recon.core.stages as stages
    import recon.drivers.oneshot as oneshot

    original = stages.adjust_with_medea
    cache: dict[str, tuple] = {}

    def key_of(seq, config, use_features) -> str:
        digest = hashlib.blake2b(digest_size=16)
        for array in (seq.rgb, seq.prior_depth, seq.poses, seq.features if use_features else None):
            if array is not None:
                digest.update(memoryview(array.tobytes() if not array.flags.c_contiguous else array).cast("B"))
        digest.update(pickle.dumps((tuple(seq.intrinsics), repr(config), use_features)))
        return digest.hexdigest()

    def adjust(seq, config, use_features=True, progress=True):
        key = key_of(seq, config, use_features)
        if key not in cache:
            cache[key] = original(seq, config, use_features, progress)
        depth, result = cache[key]
        return depth.copy(), result

    stages.adjust_with_medea = adjust
    oneshot.adjust_with_medea = adjust
    return cache


def run_in_process(args: list[str]) -> tuple[int, str]:
    """`recon ARGS` in this process: (exit code, what it wrote to stderr)."""
    import faulthandler

    from recon.commands.cli import main

    faulthandler.enable()  # before stderr is replaced: main() enables it on a real file only
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(args)
    return code, err.getvalue()


def run_segment(rec, segment: int, variant: list[str], work: Path, tag: str) -> dict:
    first, count = rec.segments[segment]
    out = work / f"{rec.name}-given-{segment}-{tag}"
    args = ["run", str(DATA / rec.folder), "-o", str(out), "--overwrite", "--quiet", "--rerun", "off",
            *selection(rec, "given", first, count), *variant]
    t0 = time.perf_counter()
    code, stderr = run_in_process(args)
    row = {"recording": rec.name, "mode": "given", "segment": f"{first}-{first + count - 1}", "exit": code,
           "wall_s": time.perf_counter() - t0, "args": args[1:],
           "warnings": [line for line in stderr.splitlines() if "warning" in line]}
    if code != 0:
        row["error"] = (stderr.strip().splitlines() or ["?"])[-1]
        return row
    row.update(scores(rec, "given", out))
    import json

    ev = json.loads((out / "eval.json").read_text())
    mesh = ev.get("mesh_before_icp", ev.get("mesh", {}))
    row.update(precision=mesh.get("precision"), recall=mesh.get("recall"))
    report = json.loads((out / "report.json").read_text())
    row["refine_s_per_frame"] = report["seconds"].get("refine", 0.0) / max(row.get("frames") or 1, 1)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", type=parse_variant, action="append", required=True,
                        help="LABEL=ARGS: `recon run` arguments of one variant (repeatable; the first is the baseline)")
    parser.add_argument("--recordings", nargs="*", default=list(SCORED), choices=list(RECORDINGS))
    parser.add_argument("--segments", nargs="*", type=int, default=[0, 1], choices=[0, 1])
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-given-screen"))
    parser.add_argument("--json", default="given_screen")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"given_screen.py: {DATA}: the recordings are not there")
    args.work.mkdir(parents=True, exist_ok=True)
    memoised_medea()
    rows, t0 = [], time.perf_counter()
    for name in args.recordings:
        rec = RECORDINGS[name]
        for segment in args.segments:
            for k, (label, variant) in enumerate(args.variant):
                say(f"{name} given segment {segment}: {label}")
                row = {**run_segment(rec, segment, variant, args.work, str(k)), "variant": label}
                rows.append(row)
                print("| " + " | ".join(table_row(row)) + f" | P {row.get('precision')} R {row.get('recall')} "
                      f"refine {row.get('refine_s_per_frame', 0):.3f} s/frame |", flush=True)
    notes = comparison(rows, args.variant[0][0])
    minutes = (time.perf_counter() - t0) / 60
    print(f"\n{table(HEADERS, [table_row(r) for r in rows])}\n\n" + "\n".join(notes) + f"\n\n{minutes:.1f} min in all")
    path = write_json(args.json, {"machine": machine(), "minutes": minutes,
                                  "variants": [{"label": v, "args": a} for v, a in args.variant], "rows": rows,
                                  "comparison": notes})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
