"""Every check that can stop a run, cut a segment or mark a result, judged on right answers
and on wrong ones: how often it fires on a trajectory known to be right, and how often on
one known to be wrong (issue 62).

It reads a table of ``benchmarks/validate.py`` run with two variants, the default and
``--on-break keep`` (which returns whatever the estimators made, with every check said as a
warning): the keep run's trajectory, scored against the recording's truth (Sim(3) ATE as a
share of the path; between the reference's own breaks where it has them), says whether the
row's trajectory is right (within ``RIGHT`` of its path) or wrong (beyond ``WRONG``); the
default run says what each check did there (the metric-scale check is judged on the
trajectory's metric scale instead: ``SCALE_RIGHT``, ``SCALE_WRONG``) (refused: exit 2 with its words; cut: a
trajectory written in segments; marked: written with its words as a warning). A check that
fires on a right trajectory is a false alarm: one that refuses or cuts it is a bug.

For each run that stops where ``--on-break keep`` returns a result, its time against that
full run's (issue 62: a run that will stop says so within a fifth of a full run's time).

Usage: python benchmarks/check_alarms.py RESULTS.json [--json check_alarms]
Prints the table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, table, write_json  # noqa: E402

RIGHT = 2.0  # % of the path: a right trajectory (issue 62's bar)
WRONG = 3.0  # % of the path: a wrong one
# The metric-scale check is judged on the scale, not the shape: right within 15 % of the
# true scale (FastDepth's own error on 7-Scenes is 12-13 %), wrong beyond 30 % (issue 62:
# "a scale more than 30 % off is always marked").
SCALE_RIGHT, SCALE_WRONG = 0.15, 0.30
ON_SCALE = ("metric scale",)
# check: the words it says (in the error of a stop, or in a warning).
CHECKS = {
    "lens on its bound": "the lens term the trajectory was fitted with ended on its bound",
    "frames far apart": "neighbouring frames lie a median",
    "focal length not found": "the focal length was not found",
    "focal length contradicted": "and the vanishing points' (",
    "turns on the spot": "the camera turns on the spot",
    "metric scale": "does not follow the scene's geometry",
    "SfM scale spread": "disagree in scale by",
    "tracking lost": "tracking lost at frame",
    "SfM registration": "SfM registered only",
    "scale break": "the map's scale against the depth prior's",
    "short flow": "the dense flow made the camera's steps short",
    "front end and SfM disagree": "the front end and SfM disagree",
}


def error_share(row: dict) -> float | None:
    """The trajectory's error as a share of its path (%), between the reference's breaks
    where it has them; None where not scored."""
    if row.get("exit") != 0:
        return None
    return row.get("ate_sim3_pct_pieces", row.get("ate_sim3_pct"))


def scale_truth(row: dict) -> str:
    """right / wrong / between / unscored by the trajectory's metric scale error."""
    e = row.get("scale_error") if row.get("exit") == 0 else None
    if e is None:
        return "unscored"
    return "right" if e <= SCALE_RIGHT else "wrong" if e > SCALE_WRONG else "between"


def said(row: dict) -> tuple[str, str]:
    """(what the run stopped with, what it warned), one text each."""
    return row.get("error") or "", " ".join(row.get("warnings", []))


def judge(rows: list[dict], baseline: str = "default", kept: str = "keep") -> tuple[list[dict], list[dict]]:
    """Per check: fires and actions on right and wrong trajectories; and per row what was
    said. rows: validate.py's rows with both variants."""
    by_key = {}
    for r in rows:
        by_key.setdefault((r["recording"], r["segment"]), {})[r["variant"]] = r
    per_row, counts = [], {name: {"right": [], "wrong": [], "unscored": []} for name in CHECKS}
    for (recording, segment), variants in sorted(by_key.items()):
        if baseline not in variants or kept not in variants:
            continue
        share = error_share(variants[kept])
        truth = "unscored" if share is None else "right" if share <= RIGHT else "wrong" if share > WRONG else "between"
        stop, warned = said(variants[baseline])
        cut = bool(variants[baseline].get("segments"))
        fired = []
        for name, words in CHECKS.items():
            action = "refused" if words in stop else ("cut" if cut and name in ("scale break", "tracking lost")
                                                      else "marked") if words in warned else None
            if action is None:
                continue
            fired.append(f"{name} ({action})")
            judged = scale_truth(variants[kept]) if name in ON_SCALE else truth
            if judged in counts[name]:
                counts[name][judged].append(f"{recording} {segment}: {action}")
        per_row.append({"recording": recording, "segment": segment, "kept_error_pct": share, "truth": truth,
                        "kept_scale_error": variants[kept].get("scale_error") if share is not None else None,
                        "exit": variants[baseline]["exit"], "fired": fired,
                        # A run that stops should say so early: its time against the full run's.
                        "stop_time_share": (variants[baseline]["wall_s"] / variants[kept]["wall_s"]
                                            if variants[baseline]["exit"] != 0 and variants[kept]["exit"] == 0
                                            else None)})
    per_check = [{"check": name, **{k: v for k, v in c.items()}} for name, c in counts.items()]
    return per_check, per_row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, help="a benchmarks/validate.py JSON with default and keep variants")
    parser.add_argument("--json", default="check_alarms")
    args = parser.parse_args()
    source = json.loads(args.results.read_text())
    per_check, per_row = judge(source["rows"])
    print(table(["recording", "frames", "keep's error % path", "truth", "keep's scale error", "default exit",
                 "stop's time / full run's", "what fired (what it did)"],
                [[r["recording"], r["segment"], "-" if r["kept_error_pct"] is None else f"{r['kept_error_pct']:.1f}",
                  r["truth"], "-" if r["kept_scale_error"] is None else f"{r['kept_scale_error']:.2f}", r["exit"],
                  "-" if r["stop_time_share"] is None else f"{r['stop_time_share']:.2f}",
                  "; ".join(r["fired"]) or "-"] for r in per_row]))
    print()
    print(table(["check", "fired on right", "fired on wrong", "fired, unscored"],
                [[c["check"], "; ".join(c["right"]) or "0", "; ".join(c["wrong"]) or "0",
                  str(len(c["unscored"]))] for c in per_check]))
    # Whatever the check, a trajectory within RIGHT of its path that is refused or cut is a bug.
    bugs = [f"{r['recording']} {r['segment']}: {f}" for r in per_row if r["truth"] == "right"
            for f in r["fired"] if f.endswith(("(refused)", "(cut)"))]
    print("\ntrajectories within 2 % of their path refused or cut:", "; ".join(bugs) or "none")
    path = write_json(args.json, {"machine": machine(), "source": str(args.results), "right_pct": RIGHT,
                                  "wrong_pct": WRONG, "checks": per_check, "rows": per_row, "bugs": bugs})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
