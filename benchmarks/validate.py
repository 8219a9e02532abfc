"""The validation table: the default `recon run` (and any variant) on every recording in
../shared/data, in two modes, on two disjoint segments of each: the table every automatic
decision is kept or dropped by (issue 44).

Modes:
- ``given``: the recording's folder as a dataset (its poses and calibration used as given,
  published lens included): `recon run DATASET --start S --max-frames N`.
- ``nothing``: what a user with only the footage has: the recording's frames written once
  as an mp4 at its frame rate (OpenCV's mp4v), or as an image folder where the recording is
  a set of keyframes (ScanNet) or an image set (the phone recording's 71 images); nothing
  else given: `recon run VIDEO --start S --max-frames N`. The phone video itself (its
  frames are not the model's) is scored on its focal length only.

Each run is scored by `recon eval OUT --gt DATASET` (given: no alignment; nothing: the
trajectory's Sim(3), the goal, and Sim(3)+ICP beside it, as Tanks and Temples does). Columns:
F@5cm and metric abs rel where the recording has sensor depth, ATE (SE(3), and Sim(3) as a
share of the path), the trajectory's scale error (not where the reference has no metric
scale: COLMAP's), the focal length's error against the published one, s/frame (the
report's stage seconds over the frames tracked) and the pose stage's, peak RSS, exit code
and the warnings said.

Usage: python benchmarks/validate.py [--variant "LABEL=RECON RUN ARGS" ...] [--recordings NAME ...]
    [--modes given nothing] [--segments 0 1] [--work DIR] [--json validate] [--markdown FILE]
The first variant (default: ``default``, no extra arguments) is the baseline the others are
compared with, row by row. In a variant's arguments ``{sensor_depth}`` stands for a folder of
the recording's own sensor depth, named as the footage's frames (nothing-given mode, where
the recording has depth; other rows skip that variant): ``--variant default= --variant
"sensor=--prior folder --prior-path {sensor_depth}"`` separates the depth network's error
from the pipeline's. Prints the table, writes benchmarks/results/<json>.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, parse_variant, say, table, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RUN_TIMEOUT_S = 1200


@dataclass(frozen=True)
class Recording:
    """One recording of ../shared/data and how it is run.

    folder: the dataset folder under DATA; segments: (first frame, frames) pairs, disjoint;
    footage: how the nothing-given mode sees it: "video" (its frames as an mp4 at ``fps``),
    "images" (its colour images as a folder), or "file:<path under DATA>" (a video of its own
    whose frames the dataset does not index: scored on the focal length alone); metric: the
    reference trajectory is metric (COLMAP's is not); modes: the modes it runs in."""

    name: str
    folder: str
    segments: tuple[tuple[int, int], ...]
    footage: str = "video"
    fps: float = 30.0
    metric: bool = True
    modes: tuple[str, ...] = ("given", "nothing")


RECORDINGS = {r.name: r for r in (
    Recording("7scenes", "7scenes-redkitchen", ((0, 100), (250, 100))),
    Recording("tum", "tum-fr1-rpy", ((0, 50), (50, 50))),
    Recording("scannet", "scannet-scene0005_00", ((0, 29), (29, 29)), footage="images"),
    Recording("record3d", "record3d-door-handle", ((0, 80), (200, 80)), fps=60.0),
    Recording("kitti", "kitti-odometry-seq1", ((0, 25), (25, 26)), fps=10.0),
    Recording("phone", "phone-beer", ((0, 35), (35, 36)), footage="images", metric=False),
    Recording("phone-video", "phone-beer", ((0, 150), (350, 150)), footage="file:phone-beer/Beer.mp4",
              metric=False, modes=("nothing",)),
)}


# --------------------------------------------------------------------------- inputs


def dataset_of(rec: Recording):
    from recon.io.datasets import open_dataset

    return open_dataset(DATA / rec.folder)


def write_video(rec: Recording, work: Path) -> Path:
    """The recording's frames in order as one mp4 at its frame rate (written once)."""
    import cv2

    path = work / f"{rec.name}.mp4"
    if path.is_file():
        return path
    dataset = dataset_of(rec)
    tmp = path.with_suffix(".tmp.mp4")
    writer = None
    for i in range(len(dataset)):
        bgr = cv2.cvtColor(dataset.rgb(i), cv2.COLOR_RGB2BGR)
        if writer is None:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), rec.fps, (bgr.shape[1], bgr.shape[0]))
        writer.write(bgr)
    writer.release()
    tmp.replace(path)
    return path


def image_folder(rec: Recording, work: Path) -> Path:
    """The recording's colour images, in its frame order, as a plain image folder (links)."""
    dataset = dataset_of(rec)
    folder = work / f"{rec.name}-images"
    if not folder.is_dir():
        tmp = work / f".{rec.name}-images.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        for k, path in enumerate(dataset.rgb_paths):
            (tmp / f"{k:06d}{Path(path).suffix}").symlink_to(Path(path).resolve())
        tmp.rename(folder)
    return folder


# In a variant's arguments: the recording's own depth maps as a `--prior folder`.
SENSOR_DEPTH = "{sensor_depth}"


def sensor_depth_folder(rec: Recording, work: Path) -> Path | None:
    """The recording's sensor depth of its segments' frames as a depth-map folder named as
    the nothing-given footage names its frames (``frame_000123`` in a video, the image
    folder's own stems), for ``--prior folder``: what the pipeline makes of a metric prior
    without the network's error. None where the recording has no depth or its own footage."""
    from recon.io.depth_maps import depth_png_bytes
    from recon.io.output_folder import frame_name

    dataset = dataset_of(rec)
    if not dataset.has_depth or rec.footage not in ("video", "images"):
        return None
    folder = work / f"{rec.name}-sensor-depth"
    if folder.is_dir():
        return folder
    tmp = work / f".{rec.name}-sensor-depth.tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    for first, count in rec.segments:
        for k in range(first, first + count):
            name = frame_name(k) if rec.footage == "video" else f"{k:06d}"
            (tmp / f"{name}.png").write_bytes(depth_png_bytes(dataset.depth(k)))
    tmp.rename(folder)
    return folder


def footage(rec: Recording, work: Path) -> Path:
    if rec.footage == "video":
        return write_video(rec, work)
    if rec.footage == "images":
        return image_folder(rec, work)
    return DATA / rec.footage.removeprefix("file:")


def footage_fps(rec: Recording) -> float:
    """The frame rate `recon run` reads the footage at (an image folder's default: 30)."""
    if rec.footage == "images":
        from recon.io.frames import DEFAULT_FOLDER_FPS

        return DEFAULT_FOLDER_FPS
    if rec.footage.startswith("file:"):
        import cv2

        return float(cv2.VideoCapture(str(DATA / rec.footage.removeprefix("file:"))).get(cv2.CAP_PROP_FPS))
    return rec.fps


def selection(rec: Recording, mode: str, first: int, count: int) -> list[str]:
    """`recon run` arguments selecting frames first .. first+count-1: --start half a frame
    before the first frame's timestamp (the dataset's own, else index / frame rate)."""
    args = ["--max-frames", str(count)]
    if first == 0:
        return args
    if mode == "given":
        from recon.io.frames import DatasetSource

        times = DatasetSource(dataset_of(rec)).timestamps
        start = times[first] - times[0] - 0.5 * (times[first] - times[first - 1])
    else:
        start = (first - 0.5) / footage_fps(rec)
    return ["--start", f"{start:.6f}", *args]


def true_focal(rec: Recording, working_width: int) -> float:
    """The published focal length (fx) at the run's working width (COLMAP's: the median over
    its per-image cameras, as the reader gives it)."""
    dataset = dataset_of(rec)
    return float(dataset.intrinsics[0]) * working_width / dataset.width


# --------------------------------------------------------------------------- one run


def recon(*args: str, code: Path | None = None, timeout: float = RUN_TIMEOUT_S) -> subprocess.CompletedProcess:
    """`recon ARGS` of this checkout, or with `code` the packages of another checkout (an
    earlier version, for the before table: its folder first on the import path)."""
    import os

    cmd = [str(Path(sys.executable).with_name("recon")), *args]
    # A crash (issue 46 saw a segmentation fault now and then) leaves the Python stack on stderr.
    env = dict(os.environ, PYTHONFAULTHANDLER="1", **({"PYTHONPATH": str(code)} if code is not None else {}))
    try:
        # Not from this checkout's folder, which would come first on the import path.
        return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env, cwd="/")
    except subprocess.TimeoutExpired as err:
        return subprocess.CompletedProcess(cmd, 124, "", f"timed out after {timeout:.0f} s\n{err.stderr or ''}")


def warnings_of(stderr: str) -> list[str]:
    return [line.removeprefix("recon: warning: ") for line in stderr.splitlines() if line.startswith("recon: warning:")]


def mesh_before_icp(ev: dict) -> dict:
    """The mesh scores of an eval.json under the trajectory's own alignment (the F@5cm
    column; the ICP-refined scores are beside it)."""
    return ev.get("mesh_before_icp", ev["mesh"])


def scores(rec: Recording, mode: str, out: Path) -> dict:
    """recon eval's figures of one output folder (those the recording has truth for)."""
    report = json.loads((out / "report.json").read_text())
    frames = report["frames"]
    tracked = frames.get("tracked", frames["count"])
    seconds = report["seconds"]
    width = report["frames"]["working_size"][0]
    row = {"frames": tracked, "depth_frames": frames.get("depth_frames", frames["count"]),
           "depth_by_gap": frames.get("depth_by_gap", 0),
           "s_per_frame": sum(seconds.values()) / max(tracked, 1),
           "pose_s_per_frame": seconds.get("poses", 0.0) / max(tracked, 1),
           "peak_rss_mb": report.get("memory", {}).get("peak_rss_mb"),
           **mesh_sizes(report, out),
           "focal": report["intrinsics"]["values"][0], "focal_source": report["intrinsics"]["source"],
           "focal_error_pct": 100.0 * (report["intrinsics"]["values"][0] / true_focal(rec, width) - 1.0),
           **focal_range(report, true_focal(rec, width)),
           "lens_k1": report.get("poses", {}).get("lens_k1"),
           "medea_skipped": report.get("medea", {}).get("skipped") or report.get("windows", {}).get("medea_skipped"),
           "polished": report.get("poses", {}).get("polish", {}).get("polished")}
    if rec.footage.startswith("file:") and mode == "nothing":
        return row  # frames the dataset does not index: the focal length is all there is to score
    align = "auto" if mode == "given" else "sim3+icp"
    done = recon("eval", str(out), "--gt", str(DATA / rec.folder), "--quiet", "--overwrite", "--mesh-align", align)
    if done.returncode != 0:
        row["eval_error"] = (done.stderr.strip().splitlines() or ["?"])[-1]
        return row
    ev = json.loads((out / "eval.json").read_text())
    if "depth" in ev:
        row["abs_rel"] = ev["depth"]["metric"]["abs_rel"]
    if "mesh" in ev:
        row["fscore"] = mesh_before_icp(ev)["fscore"]
        row["fscore_icp"] = ev["mesh"]["fscore"] if ev.get("mesh_icp", {}).get("accepted") else None
    if "trajectory" in ev:
        from recon.eval.trajectory import path_length
        from recon.io.pose_formats.trajectories import read_poses

        t = ev["trajectory"]
        dataset = dataset_of(rec)
        # The frames eval scores: those with depth (all of them, unless the run streamed).
        indices = np.asarray(report["frames"].get("depth_indices", report["frames"]["indices"]))
        path = path_length(dataset.poses[indices])
        estimated = read_poses(out / "trajectory.txt").poses
        given = dataset.poses[np.asarray(report["frames"]["indices"])]
        row.update(ate_se3=t["ate_se3"]["rmse"] if rec.metric else None, ate_sim3=t["ate_sim3"]["rmse"],
                   path_m=path, ate_sim3_pct=100.0 * t["ate_sim3"]["rmse"] / path if path > 0 else None,
                   scale_error=t["scale_error"] if rec.metric else None,
                   rot_err_deg=t["rotation_error"]["median_deg"] if "rotation_error" in t else None,
                   **(moved(estimated, given) if estimated.shape == given.shape else {}))
        if estimated.shape == given.shape:
            row.update(by_reference_piece(estimated, given, np.asarray(report["frames"]["indices"])))
    return row


# A reference step no hand-held camera makes between neighbouring frames of a video (the
# phone-beer COLMAP model turns 167-174 degrees between images 13/14, 34/35 and 52/53,
# which are video frames a third of a second apart and show the same wall).
REFERENCE_BREAK_DEG = 90.0


def by_reference_piece(estimated: np.ndarray, given: np.ndarray, indices: np.ndarray) -> dict:
    """Where the reference trajectory itself breaks (a step turning more than
    REFERENCE_BREAK_DEG), the Sim(3) ATE of each piece between its breaks on its own: the
    worst piece's, as a share of that piece's path, and the breaks (frame indices after them)."""
    from scipy.spatial.transform import Rotation

    from recon.eval.trajectory import ate_rmse, path_length

    turn = Rotation.from_matrix(np.transpose(given[:-1, :3, :3], (0, 2, 1)) @ given[1:, :3, :3]).magnitude()
    cuts = [int(k) + 1 for k in np.nonzero(np.degrees(turn) > REFERENCE_BREAK_DEG)[0]]
    if not cuts:
        return {}
    worst = 0.0
    for a, b in zip([0, *cuts], [*cuts, len(given)]):
        if b - a < 3:
            continue
        rmse = ate_rmse(estimated[a:b], given[a:b], "sim3")["rmse"]
        worst = max(worst, 100.0 * rmse / path_length(given[a:b]))
    return {"reference_breaks": [int(indices[c]) for c in cuts], "ate_sim3_pct_pieces": worst}


def mesh_sizes(report: dict, out: Path) -> dict:
    """The mesh's triangles (written and before the budget) and its files' sizes in MB."""
    fusion = report.get("fusion", {})
    files = {name: out / name for name in ("mesh.ply", "mesh.glb")}
    return {"triangles": fusion.get("triangles"), "triangles_full": fusion.get("triangles_full"),
            **{f"{name.replace('.', '_')}_mb": path.stat().st_size / 1e6 if path.is_file() else None
               for name, path in files.items()}}


def focal_range(report: dict, truth: float) -> dict:
    """The range an estimated focal length's warning gives (recon.poses.intrinsics.focal_choice), and
    whether it holds the true value: the acceptance of a focal length off by more than 10 %."""
    choice = report.get("poses", {}).get("diagnostics", {}).get("focal")
    if not choice:
        return {}
    return {"focal_range": [choice["low"], choice["high"]], "focal_range_said": choice["disagree"],
            "focal_range_holds": bool(choice["disagree"] and choice["low"] <= truth <= choice["high"])}


def moved(estimated: np.ndarray, given: np.ndarray) -> dict:
    """How far the written trajectory is from the given one: the largest camera-centre
    distance (m) and turn (degrees); 0 when the poses were used as given."""
    from scipy.spatial.transform import Rotation

    shift = np.linalg.norm(estimated[:, :3, 3] - given[:, :3, 3], axis=1)
    turn = Rotation.from_matrix(np.transpose(given[:, :3, :3], (0, 2, 1)) @ estimated[:, :3, :3]).magnitude()
    return {"trajectory_moved_m": float(shift.max()), "trajectory_turned_deg": float(np.degrees(turn.max()))}


def run_one(rec: Recording, mode: str, segment: int, variant: list[str], work: Path, tag: str,
            code: Path | None = None) -> dict:
    first, count = rec.segments[segment]
    source = DATA / rec.folder if mode == "given" else footage(rec, work)
    out = work / f"{rec.name}-{mode}-{segment}-{tag}"
    args = ["run", str(source), "-o", str(out), "--overwrite", "--quiet", "--rerun", "off",
            *selection(rec, mode, first, count), *variant]
    t0 = time.perf_counter()
    done = recon(*args, code=code)
    row = {"recording": rec.name, "mode": mode, "segment": f"{first}-{first + count - 1}", "exit": done.returncode,
           "wall_s": time.perf_counter() - t0, "warnings": warnings_of(done.stderr), "args": args[1:]}
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines() or ["?"]
        row["error"] = f"signal {-done.returncode}" if done.returncode < 0 else lines[-1]
        row["stderr_tail"] = lines[-40:]
        return row
    segments = json.loads((out / "report.json").read_text()).get("segments")
    if segments:  # --on-break segments: each stretch is scored on its own, the row is the worst
        parts = [scores(rec, mode, out / s["folder"]) for s in segments]
        row.update(max(parts, key=lambda p: p.get("ate_sim3_pct") or 0.0), segments=parts)
    else:
        row.update(scores(rec, mode, out))
    return row


# --------------------------------------------------------------------------- table


def fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


HEADERS = ["recording", "mode", "frames", "variant", "exit", "F@5cm", "(+ICP)", "abs rel", "ATE SE3 m",
           "ATE Sim3 %path", "scale err", "focal err % / poses moved", "s/frame", "poses s/fr", "peak MB",
           "triangles k (full) / GLB MB", "warn"]


def focal_cell(r: dict) -> str:
    """The focal error, and where it is over 10 %, whether the warning's range holds the truth."""
    error = r.get("focal_error_pct")
    if error is None or abs(error) <= 10:
        return fmt(error, "+.1f")
    verdict = ("range holds it" if r.get("focal_range_holds") else
               "range misses it" if r.get("focal_range_said") else "no range said")
    return f"{error:+.1f} ({verdict})"


def table_row(r: dict) -> list[str]:
    if r["exit"] != 0:
        return [r["recording"], r["mode"], r["segment"], r["variant"], str(r["exit"]), r.get("error", "")[:60],
                *["-"] * (len(HEADERS) - 6)]
    return [r["recording"], r["mode"], r["segment"], r["variant"], "0", fmt(r.get("fscore"), ".3f"),
            fmt(r.get("fscore_icp"), ".3f"), fmt(r.get("abs_rel"), ".4f"), fmt(r.get("ate_se3"), ".3f"),
            ate_cell(r), fmt(r.get("scale_error"), ".3f"),
            focal_cell(r) if r["mode"] == "nothing" else
            f"{fmt(r.get('trajectory_moved_m'), '.3f')} m {fmt(r.get('trajectory_turned_deg'), '.2f')} deg",
            fmt(r.get("s_per_frame"), ".3f"), fmt(r.get("pose_s_per_frame"), ".3f"),
            fmt(r.get("peak_rss_mb"), ".0f"), mesh_cell(r), str(len(r["warnings"]))]


def ate_cell(r: dict) -> str:
    cell = fmt(r.get("ate_sim3_pct"), ".1f")
    if r.get("reference_breaks"):
        cell += f" ({r['ate_sim3_pct_pieces']:.1f} between the reference's breaks at {r['reference_breaks']})"
    if r.get("segments"):
        cell += f" (worst of {len(r['segments'])} segments)"
    return cell


def mesh_cell(r: dict) -> str:
    if r.get("triangles") is None:
        return "-"
    full = r.get("triangles_full") or r["triangles"]
    return (f"{r['triangles'] / 1e3:.0f}" + (f" ({full / 1e3:.0f})" if full != r["triangles"] else "")
            + f" / {fmt(r.get('mesh_glb_mb'), '.1f')}")


def comparison(rows: list[dict], baseline: str) -> list[str]:
    """Per variant against the baseline, over the rows both have: F@5cm and abs rel
    differences (mean, worst) and the rows that fail where the baseline did not."""
    key = lambda r: (r["recording"], r["mode"], r["segment"])  # noqa: E731
    base = {key(r): r for r in rows if r["variant"] == baseline}
    lines = []
    for variant in dict.fromkeys(r["variant"] for r in rows if r["variant"] != baseline):
        pairs = [(base[key(r)], r) for r in rows if r["variant"] == variant and key(r) in base]
        both = lambda metric: [(b[metric], v[metric]) for b, v in pairs  # noqa: E731
                               if b.get(metric) is not None and v.get(metric) is not None]
        df = [b - v for b, v in both("fscore")]
        da = [v - b for b, v in both("abs_rel")]
        broke = [key(v) for b, v in pairs if b["exit"] == 0 and v["exit"] != 0]
        lines.append(f"{variant} against {baseline}: F@5cm lower by {np.mean(df) if df else 0:+.3f} on average, at "
                     f"most {max(df, default=0):+.3f} ({len(df)} rows); abs rel higher by "
                     f"{np.mean(da) if da else 0:+.4f} on average, at most {max(da, default=0):+.4f}; runs that fail "
                     f"only here: {broke or 'none'}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", type=parse_variant, action="append",
                        help="LABEL=ARGS: every run also with these `recon run` arguments (repeatable; the first is "
                             "the baseline; default: default=); {sensor_depth} in ARGS: a folder of the recording's "
                             "own depth maps (nothing-given rows with sensor depth only)")
    parser.add_argument("--recordings", nargs="*", default=list(RECORDINGS), choices=list(RECORDINGS))
    parser.add_argument("--modes", nargs="*", default=["given", "nothing"], choices=["given", "nothing"])
    parser.add_argument("--segments", nargs="*", type=int, default=[0, 1], choices=[0, 1])
    parser.add_argument("--work", type=Path, default=Path("/tmp/recon-validate"))
    parser.add_argument("--code", type=Path,
                        help="run `recon run` from this checkout's packages instead (e.g. a git worktree of an earlier "
                             "commit, for a before table); `recon eval` is always this checkout's")
    parser.add_argument("--json", default="validate")
    parser.add_argument("--markdown", type=Path, help="also write the table to this file")
    args = parser.parse_args()
    if not DATA.is_dir():
        sys.exit(f"validate.py: {DATA}: the recordings are not there")
    args.work.mkdir(parents=True, exist_ok=True)
    variants = args.variant or [("default", [])]
    rows = []
    t0 = time.perf_counter()
    for name in args.recordings:
        rec = RECORDINGS[name]
        for mode in (m for m in args.modes if m in rec.modes):
            for segment in args.segments:
                # Variants back to back on each row, so that the machine's drift touches them alike.
                for k, (label, variant) in enumerate(variants):
                    if any(SENSOR_DEPTH in a for a in variant):
                        folder = sensor_depth_folder(rec, args.work) if mode == "nothing" else None
                        if folder is None:
                            say(f"{name} {mode} segment {segment}: {label}: no sensor depth to give, not run")
                            continue
                        variant = [a.replace(SENSOR_DEPTH, str(folder)) for a in variant]
                    say(f"{name} {mode} segment {segment}: {label}")
                    row = {**run_one(rec, mode, segment, variant, args.work, str(k), args.code), "variant": label}
                    rows.append(row)
                    print("| " + " | ".join(table_row(row)) + " |", flush=True)
    text = table(HEADERS, [table_row(r) for r in rows])
    notes = comparison(rows, variants[0][0])
    minutes = (time.perf_counter() - t0) / 60
    print(f"\n{text}\n\n" + "\n".join(notes) + f"\n\n{minutes:.1f} min in all", flush=True)
    if args.markdown is not None:
        args.markdown.write_text(text + "\n\n" + "\n".join(f"- {n}" for n in notes) + "\n")
    path = write_json(args.json, {"machine": machine(), "minutes": minutes, "code": str(args.code or ROOT),
                                  "variants": [{"label": v, "args": a} for v, a in variants], "rows": rows,
                                  "comparison": notes})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
