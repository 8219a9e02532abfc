"""Peak memory and mesh size at the defaults on every whole recording in ../shared/data.

`recon run` at its defaults (nothing but `--quiet --rerun off`) on each recording as a
whole, in the validation table's two modes (benchmarks/validate.py: ``given``, the dataset
folder with its poses and calibration; ``nothing``, the footage alone: the frames as an mp4,
an image folder, or the phone's own video). Each run's peak resident memory is the process's
own maximum (``wait4``'s ru_maxrss, which counts a run that streams and one that does not
alike, and one that fails), beside report.json's; the mesh's triangles (written, and before
the triangle budget) and the sizes of mesh.ply and mesh.glb; whether it streamed; the exit
code. The goal (issue 46): at most 3 GB and 1 M triangles everywhere.

Usage: python benchmarks/memory.py [--recordings NAME ...] [--modes given nothing]
    [--work DIR] [--code CHECKOUT] [--json memory]. Prints the table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, table, write_json  # noqa: E402
from benchmarks.validate import DATA, RECORDINGS, footage, mesh_sizes, warnings_of  # noqa: E402

GOAL_MB = 3000
GOAL_TRIANGLES = 1_000_000
TIMEOUT_S = 3600


def run_measured(args: list[str], code: Path | None = None) -> tuple[int, float, str]:
    """(exit code, peak RSS in MB of that process, stderr) of `recon ARGS` (with `code`: the
    packages of that checkout, as validate.py's --code)."""
    cmd = [str(Path(sys.executable).with_name("recon")), *args]
    env = dict(os.environ, PYTHONFAULTHANDLER="1", **({"PYTHONPATH": str(code)} if code is not None else {}))
    with open(os.devnull, "w") as devnull:
        proc = subprocess.Popen(cmd, stdout=devnull, stderr=subprocess.PIPE, text=True, cwd="/",
                                env=env)
        timer = threading.Timer(TIMEOUT_S, proc.kill)
        timer.start()
        stderr = proc.stderr.read()  # short (warnings); read to the end so the pipe never fills
        _, status, usage = os.wait4(proc.pid, 0)
        timer.cancel()
        proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_maxrss / 1024.0, stderr


def measure(name: str, mode: str, work: Path, code: Path | None = None) -> dict:
    rec = RECORDINGS[name]
    source = DATA / rec.folder if mode == "given" else footage(rec, work)
    out = work / f"{name}-{mode}"
    t0 = time.perf_counter()
    args = ["run", str(source), "-o", str(out), "--overwrite", "--quiet", "--rerun", "off"]
    status, peak, stderr = run_measured(args, code)
    row = {"recording": name, "mode": mode, "input": str(source), "exit": status, "peak_rss_mb": peak,
           "wall_s": time.perf_counter() - t0, "warnings": warnings_of(stderr)}
    report_path = out / "report.json"
    if status != 0 or not report_path.is_file():
        row["error"] = (stderr.strip().splitlines() or ["?"])[-1]
        return row
    report = json.loads(report_path.read_text())
    folders = [out / s["folder"] for s in report.get("segments") or []] or [out]
    sizes = [mesh_sizes(json.loads((f / "report.json").read_text()), f) for f in folders]
    row.update({
        "frames": report.get("frames", {}).get("count"),
        "streamed": "windows" in report or any("windows" in json.loads((f / "report.json").read_text())
                                               for f in folders),
        "report_peak_rss_mb": report.get("memory", {}).get("peak_rss_mb"),
        "segments": len(folders) if report.get("segments") else 0,
        "triangles": max((s["triangles"] or 0) for s in sizes),
        "triangles_full": max((s["triangles_full"] or 0) for s in sizes),
        "mesh_ply_mb": max((s["mesh_ply_mb"] or 0) for s in sizes),
        "mesh_glb_mb": max((s["mesh_glb_mb"] or 0) for s in sizes),
    })
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    names = [n for n in RECORDINGS if n != "phone-video"] + ["phone-video"]
    parser.add_argument("--recordings", nargs="*", default=names, choices=names)
    parser.add_argument("--modes", nargs="*", default=["given", "nothing"], choices=["given", "nothing"])
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-memory"))
    parser.add_argument("--code", type=Path, help="run `recon run` from this checkout's packages (validate.py --code)")
    parser.add_argument("--json", default="memory")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"memory.py: {DATA}: the recordings are not there")
    args.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.recordings:
        for mode in args.modes:
            if mode not in RECORDINGS[name].modes:
                continue
            print(f"[{time.strftime('%H:%M:%S')}] {name} {mode}", flush=True)
            rows.append(measure(name, mode, args.work, args.code))
            write_json(args.json, {"machine": machine(), "goal_mb": GOAL_MB, "rows": rows})

    def fmt(value, spec):
        return "-" if value is None else format(value, spec)

    print(table(["recording", "mode", "frames", "streamed", "exit", "peak RSS MB", "triangles k (full)",
                 "PLY / GLB MB", "s"],
                [[r["recording"], r["mode"], fmt(r.get("frames"), "d"), "yes" if r.get("streamed") else "no",
                  r["exit"], f"{r['peak_rss_mb']:.0f}",
                  f"{fmt(r.get('triangles', 0) / 1e3 if 'triangles' in r else None, '.0f')} "
                  f"({fmt(r.get('triangles_full', 0) / 1e3 if 'triangles_full' in r else None, '.0f')})",
                  f"{fmt(r.get('mesh_ply_mb'), '.1f')} / {fmt(r.get('mesh_glb_mb'), '.1f')}", f"{r['wall_s']:.0f}"]
                 for r in rows]))
    over = [r for r in rows if r["peak_rss_mb"] > GOAL_MB or (r.get("triangles") or 0) > GOAL_TRIANGLES]
    print(f"{len(rows) - len(over)} of {len(rows)} runs within {GOAL_MB} MB and {GOAL_TRIANGLES} triangles")
    print(f"written {write_json(args.json, {'machine': machine(), 'goal_mb': GOAL_MB, 'rows': rows})}")


if __name__ == "__main__":
    main()
