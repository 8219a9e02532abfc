"""The pipeline on CPU and on CUDA: seconds per stage, and whether both devices give the
same depth (issue 23).

Parts (``--parts``; the first three by default), each per device in one process:

* ``prior``: FastDepth with features by batch size and memory layout, after a warm-up;
* ``agreement``: ``recon run`` (``run_pipeline``) on 7-Scenes redkitchen, every 4th frame
  of 0-399 (100 frames, colour focal 525 px), ground-truth poses given: the median
  relative difference between the devices' depth (MEDeA's and the refined), and each
  device's abs rel against the sensor;
* ``speed``: ``recon run`` on a rendered 640x480 video (default 300 frames) with
  estimated poses (the main job; ``--on-break keep``, since FastDepth's depth of the
  rendered room fails the metric-scale check that stops the default run) and with the
  ground-truth poses given;
* ``poses``: the front end and the polish of given poses with their bundle adjustment on
  each of ``--pose-devices``: seconds, and how far the cameras end from the first's;
* ``profile``: the front end on the rendered video under cProfile on each device: where
  the pose stage's seconds go (flow, bundle adjustment, the rest).

``--save-depth DIR`` writes what each agreement run fused (the depth as TSDF fusion
integrates it: the refined depth where its confidence passes, uint16 mm), so that runs
made on different machines can be compared where open3d is installed: ``--compare
DIR/fused-cpu DIR2/fused-cuda`` gives their median depth difference, and fuses each on
the CPU to score its mesh (F@5cm) against the sensor's (7-Scenes in ../shared;
``device_compare``).

The inputs need neither open3d nor ``../shared`` at run time, so they travel to a GPU
machine as one folder (frames as JPEG, quality 95: both devices decode the same pixels):

    python benchmarks/device.py --make-inputs gpu_inputs/                 # here
    python benchmarks/device.py --inputs gpu_inputs/ --devices cpu cuda   # there
    bash benchmarks/device_check.sh gpu_inputs/ out/                       # or every check there at once

Where open3d is not installed (the GPU machine), TSDF fusion, export and Rerun logging
are not run: a stand-in returns an empty mesh (``device_setup``), and the table says so. Their cost does
not depend on the device except fusion, which Open3D runs on ``CUDA:0`` when its build
has CUDA. Prints tables, writes benchmarks/results/device.json (or --json).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from device_compare import abs_rel, compare_saved, kitchen_dataset, median_difference, save_fused  # noqa: E402
from device_setup import FUSED, set_up  # noqa: E402

STAGES = ("decode", "store", "prior", "poses", "undistort", "medea", "refine", "fusion", "export", "logging")


# --------------------------------------------------------------------------- inputs


def make_inputs(folder: Path, frames: int) -> None:
    """The rendered video with its poses, and 7-Scenes as JPEG frames + TUM poses + sensor depth."""
    import cv2

    from recon.commands.demo import write_demo_inputs
    from recon.io.output_folder import OutputFolder
    from recon.io.pose_formats.trajectories import write_poses
    from recon.synthetic import render_sequence

    folder.mkdir(parents=True, exist_ok=True)
    seq = render_sequence(num_frames=frames, width=640, height=480)
    write_demo_inputs(OutputFolder(folder / "synthetic", overwrite=True), seq, None)
    json.dump({"intrinsics": [float(v) for v in seq.intrinsics]}, open(folder / "synthetic" / "camera.json", "w"))

    data = kitchen_dataset()
    rgb, depth = data.load_rgb_batch(), data.load_depth_batch()
    kitchen = folder / "kitchen"
    (kitchen / "frames").mkdir(parents=True, exist_ok=True)
    for i, frame in enumerate(rgb):
        cv2.imwrite(str(kitchen / "frames" / f"{i:04d}.jpg"), frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    write_poses(kitchen / "poses.txt", np.asarray(data.poses), "tum", timestamps=np.arange(len(rgb)) / 30.0)
    half = (depth[:, ::2, ::2] * 1000).round().clip(0, 65535).astype(np.uint16)
    np.savez_compressed(kitchen / "sensor_depth.npz", depth_mm=half)
    json.dump({"intrinsics": [float(v) for v in np.asarray(data.intrinsics).reshape(-1, 4)[0]]},
              open(kitchen / "camera.json", "w"))


# --------------------------------------------------------------------------- runs


def run(input_path: Path, poses: str, intrinsics, device: str, workdir: Path, threads: int | None,
        medea_eps: float | None = None, on_break: str = "segments", stream: str = "off",
        pose_threads: int | None = None) -> dict:
    """One ``recon run`` in this process. stream "off" (the one-shot run, whose depth arrays
    the agreement compares) or "auto" (the default: a video with estimated poses streams)."""
    from recon.pipeline import PipelineConfig, run_pipeline

    if threads:
        torch.set_num_threads(threads)
    config = PipelineConfig(input=input_path, output=workdir / f"out-{device}-{poses.replace('/', '_')[-20:]}",
                            overwrite=True, intrinsics=tuple(intrinsics), poses=poses, rerun="off", progress=False,
                            device=device, stream=stream, on_break=on_break)
    config.medea.device = device
    if pose_threads:
        config.pose_options["torch_threads"] = pose_threads  # FrontendConfig.torch_threads
    if medea_eps is not None:
        config.medea.stage1.adam_eps = medea_eps
    if device.startswith("cuda"):
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    FUSED.clear()
    result = run_pipeline(config)
    wall = time.perf_counter() - start
    peak = torch.cuda.max_memory_allocated() / 2**30 if device.startswith("cuda") else None
    record = {"fused": dict(FUSED), "device": device, "threads": torch.get_num_threads(), "wall": wall,
              "frames": result.frame_count, "streamed": not hasattr(result, "adjusted_depth"),
              "depth_frames": int(getattr(result, "depth_frames", result.frame_count)),
              "peak_gpu_gib": peak, "seconds": dict(result.seconds)}
    if not record["streamed"]:
        record.update(depth=np.asarray(result.depth, np.float32),
                      medea_depth=np.asarray(result.adjusted_depth, np.float32),
                      epochs={k: int(h.epochs) for k, h in (result.medea.history.items() if result.medea else [])})
    return record


def warm_up(device: str) -> None:
    """Pays a process's one-time costs on `device` before a timed run: CUDA's start and
    kernel selection for FastDepth (seconds the first run of a process would count)."""
    if not device.startswith("cuda"):
        return
    from recon.priors.fastdepth import FastDepthPrior

    frames = np.random.default_rng(0).integers(0, 255, (8, 480, 640, 3), dtype=np.uint8)
    start = time.perf_counter()
    FastDepthPrior(features=True, device=device, progress=False)(frames, (525.0, 525.0, 320.0, 240.0))
    torch.cuda.synchronize()
    print(f"warm-up on {device}: {time.perf_counter() - start:.1f} s", flush=True)


def kept(run: dict) -> dict:
    """A run's record for the JSON: everything but its arrays."""
    return {k: v for k, v in run.items() if "depth" not in k and k != "fused"}


def prior_variants(frames: np.ndarray, intrinsics, devices: list[str], threads: int) -> list[dict]:
    """FastDepth (+ stride-8 features) seconds per frame by device, batch size and memory layout,
    after a warm-up batch (the first CUDA call pays for kernel selection)."""
    from recon.priors.fastdepth import FastDepthPrior

    rows = []
    for device in devices:
        torch.set_num_threads(threads if device == "cpu" else torch.get_num_threads())
        for batch_size in (8, 32):
            for channels_last in (True, False):
                prior = FastDepthPrior(features=True, batch_size=batch_size, device=device, progress=False,
                                       channels_last=channels_last)
                prior(frames[:batch_size], intrinsics)
                times = []
                for _ in range(3):
                    if device.startswith("cuda"):
                        torch.cuda.synchronize()
                    start = time.perf_counter()
                    prior(frames, intrinsics)
                    times.append((time.perf_counter() - start) / len(frames))
                rows.append({"device": device, "batch_size": batch_size, "channels_last": channels_last,
                             "seconds_per_frame": min(times)})
                print(f"prior {device} batch {batch_size} channels_last {channels_last}: {min(times):.4f} s/frame",
                      flush=True)
    return rows


def pose_devices(folder: Path, devices: list[str], threads: int) -> dict:
    """The front end (poses estimated) and the polish of given poses with their bundle
    adjustment on each device: seconds, and how far the cameras end up from the first
    device's (the rest, DIS flow and bookkeeping, runs on the CPU either way)."""
    import cv2

    from recon.io.pose_formats.trajectories import read_poses
    from recon.poses import estimate_poses
    from recon.poses.given.polish import polish_poses
    from recon.priors.fastdepth import FastDepthPrior

    camera = np.asarray(json.loads((folder / "camera.json").read_text())["intrinsics"])
    frames = np.stack([cv2.imread(str(p))[..., ::-1] for p in sorted((folder / "frames").glob("*.jpg"))])
    given = read_poses(folder / "poses.txt").poses
    prior = FastDepthPrior(progress=False, device=devices[-1])(frames, camera).depth
    torch.set_num_threads(threads)
    out: dict = {}
    for job in ("frontend", "polish"):
        results = {}
        for device in devices:
            start = time.perf_counter()
            if job == "frontend":
                poses = estimate_poses(frames, prior, camera, method="frontend", device=device, progress=False).poses
            else:
                poses = polish_poses(frames, prior, given, camera, progress=False, device=device).poses
            results[device] = {"seconds_per_frame": (time.perf_counter() - start) / len(frames), "poses": poses}
        first = results[devices[0]]["poses"]
        for device, r in results.items():
            gap = np.linalg.norm(r.pop("poses")[:, :3, 3] - first[:, :3, 3], axis=1)
            r.update(centre_gap_median_m=float(np.median(gap)), centre_gap_max_m=float(gap.max()))
            print(f"{job} BA on {device}: {r['seconds_per_frame']:.4f} s/frame, cameras {r['centre_gap_max_m']:.2e} m "
                  f"(max) from {devices[0]}'s", flush=True)
        out[job] = results
    return out


def profile_frontend(folder: Path, devices: list[str], threads: int, top: int = 40) -> dict:
    """The front end on the rendered video under cProfile, per device: seconds per frame and
    the functions with the most cumulative time (printed), and the share of the main parts."""
    import cProfile
    import io
    import pstats

    from recon.core.stages import decode, select_frames
    from recon.poses import estimate_poses
    from recon.priors.fastdepth import FastDepthPrior

    frames = decode(select_frames(folder / "input" / "synthetic.mp4", frame_budget=None), progress=False).rgb
    camera = np.asarray(json.loads((folder / "camera.json").read_text())["intrinsics"])
    torch.set_num_threads(threads)
    prior = FastDepthPrior(progress=False, device=devices[-1])(frames, camera).depth
    parts = {"flow (DIS)": "calc' of 'cv2", "bundle adjustment": "ba.py", "non-keyframes": "filler.py",
             "motion-only": "motion_only.py"}
    out = {}
    for device in devices:
        profile = cProfile.Profile()
        start = time.perf_counter()
        profile.enable()
        estimate_poses(frames, prior, camera, method="frontend", device=device, progress=False)
        profile.disable()
        seconds = time.perf_counter() - start
        text = io.StringIO()
        stats = pstats.Stats(profile, stream=text).sort_stats("cumulative")
        stats.print_stats(top)
        print(f"front end on {device}: {seconds / len(frames):.4f} s/frame\n{text.getvalue()}", flush=True)
        shares = {}
        for name, needle in parts.items():
            # the outermost matching function's cumulative time (nested calls are counted once)
            cum = [v[3] for k, v in stats.stats.items() if needle in f"{k[0]}' of '{k[2]}" or needle in k[0]]
            shares[name] = max(cum, default=0.0) / len(frames)
        out[device] = {"seconds_per_frame": seconds / len(frames), "parts_seconds_per_frame": shares}
    return out


def stage_table(runs: list[dict], fused: bool) -> str:
    from common import table

    headers = ["stage"] + [f"{r['label']} s/frame" for r in runs]
    rows = []
    for stage in STAGES:
        cells = [f"{r['seconds'].get(stage, 0.0) / r['frames']:.4f}" for r in runs]
        if not fused and stage in ("fusion", "export", "logging"):
            cells = ["not run" for _ in runs]
        rows.append([stage] + cells)
    rows.append(["total (run)"] + [f"{r['wall'] / r['frames']:.4f}" for r in runs])
    late = ("fusion", "export", "logging")
    rows.append(["total without " + ", ".join(late)]
                + [f"{(r['wall'] - sum(r['seconds'].get(k, 0.0) for k in late)) / r['frames']:.4f}" for r in runs])
    if any(r.get("video_frames") for r in runs):
        rows.append(["total per frame of the video"]
                    + [f"{r['wall'] / r['video_frames']:.4f}" if r.get("video_frames") else "-" for r in runs])
        rows.append(["frames processed / of the video"] + [f"{r['frames']}/{r.get('video_frames', '-')}" for r in runs])
    rows.append(["peak GPU memory GiB"] + [f"{r['peak_gpu_gib']:.2f}" if r.get("peak_gpu_gib") is not None else "-"
                                           for r in runs])
    return table(headers, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--make-inputs", type=Path, help="write the inputs to this folder and stop")
    parser.add_argument("--frames", type=int, default=300, help="frames of the rendered video (--make-inputs)")
    parser.add_argument("--inputs", type=Path, help="the folder --make-inputs wrote")
    parser.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
    parser.add_argument("--pose-devices", nargs="+", help="devices of the poses part (default: --devices)")
    parser.add_argument("--cpu-threads", type=int, default=2, help="torch threads of the CPU runs (default 2)")
    parts = ["prior", "agreement", "speed", "poses", "profile"]
    parser.add_argument("--parts", nargs="+", default=parts[:3], choices=parts)
    parser.add_argument("--pose-threads", type=int,
                        help="the front end's torch threads in the speed part (FrontendConfig.torch_threads; default: "
                             "torch's, all cores): on the H200 machine its 16 threads are a suspect for the pose stage "
                             "taking 0.129 s/frame against 0.089 with 2")
    parser.add_argument("--prior-fixed-batch", action="store_true",
                        help="pad every FastDepth call to its full batch (an experiment: "
                             "device_setup.fixed_prior_batches)")
    parser.add_argument("--stream", choices=["auto", "off"], default="auto",
                        help="the speed part's runs: auto (the default of recon run: a video with estimated poses "
                             "streams) or off (one-shot)")
    parser.add_argument("--medea-eps", type=float, help="Adam epsilon of MEDeA's Stage I (default: the preset's)")
    parser.add_argument("--save-depth", type=Path, help="write each agreement run's fused and MEDeA depth here")
    parser.add_argument("--compare", type=Path, nargs=2, metavar="PREFIX",
                        help="compare two runs saved by --save-depth (e.g. DIR/fused-cpu DIR/fused-cuda): their "
                             "depth, and each one's mesh F@5cm; needs open3d and ../shared")
    parser.add_argument("--json", type=Path, help="where to write the results (default benchmarks/results/device.json)")
    args = parser.parse_args()
    if args.make_inputs:
        make_inputs(args.make_inputs, args.frames)
        return
    from common import machine

    if args.compare:
        result = {"machine": machine(), "compare": compare_saved(args.compare, args.inputs)}
        out = args.json or ROOT / "benchmarks" / "results" / "device_compare.json"
        out.write_text(json.dumps(result, indent=1))
        print(f"wrote {out}")
        return
    fused = set_up(args.prior_fixed_batch)
    payload: dict = {"machine": machine(), "medea_eps": args.medea_eps, "open3d": fused, "torch": torch.__version__,
                     "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    out_json = args.json or ROOT / "benchmarks" / "results" / "device.json"

    def save() -> None:
        out_json.parent.mkdir(parents=True, exist_ok=True)
        out_json.write_text(json.dumps(payload, indent=1))

    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        for part in args.parts:
            if part == "prior":
                import cv2

                kitchen = args.inputs / "kitchen"
                camera = np.asarray(json.loads((kitchen / "camera.json").read_text())["intrinsics"])
                paths = sorted((kitchen / "frames").glob("*.jpg"))[:64]
                frames = np.stack([cv2.imread(str(p))[..., ::-1] for p in paths])
                payload["prior"] = prior_variants(frames, camera, args.devices, args.cpu_threads)
            elif part == "profile":
                payload["profile"] = profile_frontend(args.inputs / "synthetic", args.pose_devices or args.devices,
                                                      args.cpu_threads)
            elif part == "poses":
                payload["poses"] = pose_devices(args.inputs / "kitchen", args.pose_devices or args.devices,
                                                args.cpu_threads)
                save()
            elif part == "agreement":
                kitchen = args.inputs / "kitchen"
                camera = json.loads((kitchen / "camera.json").read_text())["intrinsics"]
                sensor = np.load(kitchen / "sensor_depth.npz")["depth_mm"]
                runs = []
                for device in args.devices:
                    threads = args.cpu_threads if device == "cpu" else None
                    r = run(kitchen / "frames", str(kitchen / "poses.txt"), camera, device, workdir, threads,
                            args.medea_eps)
                    r["label"] = device
                    r["gpu"] = payload["gpu"] if device.startswith("cuda") else None
                    if args.save_depth:
                        save_fused(args.save_depth, r)
                    r["abs_rel"] = {"medea": abs_rel(r["medea_depth"], sensor), "refined": abs_rel(r["depth"], sensor)}
                    runs.append(r)
                    print(f"7-Scenes on {device}: {r['wall']:.1f} s, MEDeA epochs {r['epochs']}, "
                          f"abs rel {r['abs_rel']}", flush=True)
                record = {"runs": [kept(r) for r in runs]}
                if len(runs) == 2:
                    record["median_difference"] = {
                        "medea": median_difference(runs[0]["medea_depth"], runs[1]["medea_depth"]),
                        "refined": median_difference(runs[0]["depth"], runs[1]["depth"]),
                    }
                    print(f"median depth difference {runs[0]['label']} vs {runs[1]['label']}: "
                          f"{record['median_difference']}", flush=True)
                payload["agreement"] = record
                save()
                print(stage_table(runs, fused), flush=True)
            else:
                from recon.io.pose_formats.trajectories import read_poses

                video = args.inputs / "synthetic" / "input" / "synthetic.mp4"
                poses_file = args.inputs / "synthetic" / "input" / "poses_gt.txt"
                camera = json.loads((args.inputs / "synthetic" / "camera.json").read_text())["intrinsics"]
                runs = []
                for device in args.devices:
                    warm_up(device)
                    for poses in ("estimate", str(poses_file)):
                        threads = args.cpu_threads if device == "cpu" else None
                        # FastDepth does not see the rendered room as a room (the metric-scale check
                        # stops the default run): the estimated run keeps its scale to be timed.
                        r = run(video, poses, camera, device, workdir, threads, on_break="keep", stream=args.stream,
                                pose_threads=args.pose_threads)
                        r["label"] = f"{device} {'estimated' if poses == 'estimate' else 'given'}"
                        r["video_frames"] = len(read_poses(poses_file).poses)
                        runs.append(r)
                        payload["speed"] = {"runs": [kept(r) for r in runs]}
                        save()
                        print(f"video, {r['label']} poses: {r['wall'] / r['frames']:.4f} s/frame, "
                              f"{ {k: round(v, 1) for k, v in r['seconds'].items()} }", flush=True)
                payload["speed"] = {"runs": [kept(r) for r in runs]}
                print(stage_table(runs, fused), flush=True)
            save()
    print(f"wrote {out_json}")


if __name__ == "__main__":
    main()
