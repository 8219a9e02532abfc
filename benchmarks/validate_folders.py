"""Summarise the run folders a `benchmarks/validate.py --work DIR` left behind, from each
folder's report.json and eval.json: F@5cm with its precision and recall, abs rel, the
frames that got depth, the streamed windows' refined shares, peak RSS. For a table that
was stopped before it wrote its JSON, or to read what the table does not print.

    python benchmarks/validate_folders.py DIR [DIR ...] --label DIR=LABELS --json NAME

LABELS: the variants' labels in the order validate.py ran them (its folders end in
-<variant number>), comma separated.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import machine, table, write_json  # noqa: E402
from benchmarks.validate import fmt, mesh_before_icp  # noqa: E402

HEADERS = ["recording", "frames", "variant", "F@5cm", "precision", "recall", "abs rel", "depth frames",
           "windows' refined share", "voxel mm", "peak MB"]


def summarise(folder: Path, labels: list[str]) -> dict | None:
    """One row of a run folder named <recording>-<mode>-<segment>-<variant number>; None
    when the run wrote no report."""
    report_path, eval_path = folder / "report.json", folder / "eval.json"
    if not report_path.is_file():
        return None
    name, mode, segment, variant = folder.name.rsplit("-", 3)
    report = json.loads(report_path.read_text())
    scores = json.loads(eval_path.read_text()) if eval_path.is_file() else {}
    mesh = mesh_before_icp(scores) if "mesh" in scores else {}
    depth = scores.get("depth", {}).get("metric", {})
    frames = report["frames"]
    windows = report.get("windows", {}).get("each", [])
    return {"recording": name, "mode": mode, "segment": int(segment),
            "variant": labels[int(variant)] if int(variant) < len(labels) else variant,
            "frames": f"{frames['indices'][0]}-{frames['indices'][-1]}" if frames.get("indices") else "",
            "fscore": mesh.get("fscore"), "precision": mesh.get("precision"), "recall": mesh.get("recall"),
            "abs_rel": depth.get("abs_rel"), "depth_frames": frames.get("depth_frames", frames.get("count")),
            "tracked": frames.get("tracked", frames.get("count")),
            "refined_share": [round(w["refined_share"], 3) for w in windows if w.get("refined_share") is not None],
            "voxel_mm": 1000.0 * report.get("fusion", {}).get("voxel_size", float("nan")),
            "peak_rss_mb": report.get("memory", {}).get("peak_rss_mb")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path)
    parser.add_argument("--label", action="append", default=[], help="DIR=LABEL,LABEL,...")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    labels = {Path(k).resolve(): v.split(",") for k, v in (item.split("=", 1) for item in args.label)}
    rows = []
    for work in args.dirs:
        for folder in sorted(p for p in work.iterdir() if p.is_dir()):
            row = summarise(folder, labels.get(work.resolve(), []))
            if row is not None:
                rows.append(row)
    rows.sort(key=lambda r: (r["recording"], r["segment"], r["variant"]))
    print(table(HEADERS, [[r["recording"], r["frames"], r["variant"], fmt(r["fscore"], ".3f"),
                           fmt(r["precision"], ".3f"), fmt(r["recall"], ".3f"), fmt(r["abs_rel"], ".4f"),
                           f"{r['depth_frames']} of {r['tracked']}", " ".join(f"{s:.2f}" for s in r["refined_share"]),
                           fmt(r["voxel_mm"], ".1f"), fmt(r["peak_rss_mb"], ".0f")] for r in rows]))
    if args.json:
        print(f"wrote {write_json(args.json, {'machine': machine(), 'rows': rows})}")


if __name__ == "__main__":
    main()
