"""The agreement of two runs of ``benchmarks/device.py``: their depth as fused, saved on one
machine (``--save-depth``) and compared where open3d and ``../shared`` are (``--compare``):
median depth difference, and each run's mesh F@5cm against 7-Scenes' sensor mesh.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def kitchen_dataset():
    """The agreement's frames: 7-Scenes redkitchen, every 4th of 0-399 (``../shared``), the
    frames ``device.py --make-inputs`` writes and ``compare_saved`` scores against."""
    from recon.io.datasets import open_dataset

    return open_dataset(ROOT.parent / "shared" / "data" / "7scenes-redkitchen").select(stride=4).with_valid_poses()

def save_fused(folder: Path, run: dict, chunk: int = 50) -> None:
    """One agreement run's depth as fused, in millimetres (uint16, 0 = none), as files of
    `chunk` frames (``fused-DEVICE-K.npz``: a GPU machine sends back files of 16 MiB at most)."""
    folder.mkdir(parents=True, exist_ok=True)
    from recon.io.depth_maps import depth_to_mm

    depth = depth_to_mm(run["fused"]["depth"])
    name = run["device"].replace(":", "")
    for k, start in enumerate(range(0, len(depth), chunk)):
        np.savez_compressed(folder / f"fused-{name}-{k:02d}.npz", fused_mm=depth[start:start + chunk],
                            poses=run["fused"]["poses"][start:start + chunk], intrinsics=run["fused"]["intrinsics"],
                            device=run["device"], gpu=str(run.get("gpu")))


def load_fused(prefix: Path) -> dict:
    """The files `save_fused` wrote for one run (``PREFIX-*.npz``), joined."""
    parts = [dict(np.load(p)) for p in sorted(prefix.parent.glob(prefix.name + "-*.npz"))]
    if not parts:
        raise SystemExit(f"no {prefix}-*.npz")
    return {"fused_mm": np.concatenate([p["fused_mm"] for p in parts]),
            "poses": np.concatenate([p["poses"] for p in parts]), "intrinsics": parts[0]["intrinsics"],
            "device": str(parts[0]["device"]), "gpu": str(parts[0]["gpu"]), "name": prefix.name}


def median_difference(a: np.ndarray, b: np.ndarray) -> float:
    both = (a > 0) & (b > 0)
    return float(np.median(np.abs(a[both] / b[both] - 1.0)))


def abs_rel(depth: np.ndarray, sensor_mm: np.ndarray) -> float:
    gt = sensor_mm.astype(np.float32) / 1000.0
    pred = depth[:, ::2, ::2]
    valid = (gt > 0) & (pred > 0)
    return float(np.mean(np.abs(pred[valid] - gt[valid]) / gt[valid]))


def compare_saved(prefixes: list[Path], inputs: Path | None) -> dict:
    """Median difference of two agreement runs' depth as fused (``--save-depth``: ``PREFIX``
    is e.g. ``DIR/fused-cuda``), and each one's mesh: that depth integrated again here on the
    CPU (the same function and inputs as the run's own fusion) and scored against the TSDF
    mesh of 7-Scenes' sensor depth."""
    from recon.eval.evaluate import reference_tsdf_mesh
    from recon.eval.mesh import mesh_metrics
    from recon.fusion import FusionOptions, fuse

    runs = [load_fused(p) for p in prefixes]
    data = kitchen_dataset()
    sensor = np.load(inputs / "kitchen" / "sensor_depth.npz")["depth_mm"] if inputs else None
    depths = [r["fused_mm"].astype(np.float32) / 1000.0 for r in runs]
    out: dict = {"runs": [], "median_difference_fused": median_difference(depths[1], depths[0])}
    reference = None
    for r, depth in zip(runs, depths):
        fused = fuse(depth, None, r["poses"], r["intrinsics"], FusionOptions(progress=False))
        if reference is None:
            reference = reference_tsdf_mesh(data, np.arange(len(data)), fused.voxel_size, 10.0, False)
        metrics = mesh_metrics(fused.mesh, reference)
        row = {"run": r["name"], "device": r["device"], "gpu": r["gpu"], "voxel_size": fused.voxel_size,
               "triangles": len(fused.mesh.triangles), "f_score": metrics.fscore,
               "precision": metrics.precision, "recall": metrics.recall}
        if sensor is not None:
            row["abs_rel_fused"] = abs_rel(depth, sensor)
        out["runs"].append(row)
        print(f"{r['name']} ({r['device']}, {r['gpu']}): mesh F@5cm {metrics.fscore:.4f}, "
              f"{row['triangles']} triangles, abs rel {row.get('abs_rel_fused')}", flush=True)
    out["f_score_difference"] = abs(out["runs"][0]["f_score"] - out["runs"][1]["f_score"])
    print(f"median depth difference (as fused): {out['median_difference_fused']:.5f}; "
          f"F@5cm difference {out['f_score_difference']:.4f}")
    return out
