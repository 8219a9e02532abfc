"""`recon eval`: score an output folder of `recon run` against a dataset's ground truth.

This module owns the three evaluations of an output folder read back by
:func:`recon.io.output_folder.load_output`, each built from the metric modules: depth
(DeepVideoMVS protocol, as in the MEDeA paper; the ground truth resampled into the run's
camera by :func:`in_run_camera`), trajectory (ATE after SE(3) and Sim(3) Umeyama alignment,
RPE, scale error) and mesh (against a reference mesh or a TSDF of the sensor depth, aligned
per ``mesh_align``). A dataset without sensor depth gets ``"depth_missing"`` and
``"mesh_missing"`` notes instead. More: docs/eval.md#how-the-scores-are-computed
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import open3d as o3d

from recon.errors import ReconInputError
from recon.eval.depth import depth_metrics
from recon.eval.mesh import DEFAULT_THRESHOLD, icp_registered, mesh_metrics
from recon.eval.trajectory import ate_rmse, move_points, pose_alignment, rotation_error, rpe, scale_error
from recon.io.datasets import open_dataset
from recon.io.output_folder import load_output

log = logging.getLogger(__name__)


@dataclass
class EvalOptions:
    """min_depth, max_depth: evaluated ground-truth range in metres. threshold: mesh
    precision/recall distance. mesh_points: surface samples per mesh. reference_mesh: a mesh
    file to compare with instead of the sensor-depth TSDF. mesh_align: "auto" (Sim(3) from
    the trajectory when the poses were estimated, none for ground-truth poses), "none",
    "se3", "sim3" or "sim3+icp" (that Sim(3), then ICP with a scale onto the reference
    surface, as Tanks and Temples registers a reconstruction)."""

    min_depth: float = 1e-3
    max_depth: float = 10.0
    threshold: float = DEFAULT_THRESHOLD
    mesh_points: int = 200_000
    reference_mesh: Path | None = None
    mesh_align: Literal["auto", "none", "se3", "sim3", "sim3+icp"] = "auto"
    progress: bool = True


def _gt_depth_at(gt: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Ground truth (H, W) at the prediction's size (h, w), nearest neighbour."""
    if gt.shape == size:
        return gt
    return cv2.resize(gt, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)


def evaluate_depth(depth: np.ndarray, gt_depth: np.ndarray, options: EvalOptions) -> dict:
    """Metric and median-scaled depth metrics of depth (N, h, w) against gt (N, H, W)."""
    gt = np.stack([_gt_depth_at(g, depth.shape[1:]) for g in gt_depth])
    kw = dict(min_depth=options.min_depth, max_depth=options.max_depth)
    return {
        "metric": depth_metrics(depth, gt, **kw),
        "median_frame": depth_metrics(depth, gt, align="median_frame", **kw),
        "median_sequence": depth_metrics(depth, gt, align="median_sequence", **kw),
    }


def evaluate_trajectory(poses: np.ndarray, gt_poses: np.ndarray) -> dict:
    """ATE (SE(3), Sim(3)), RPE, orientation error and scale error of camera-to-world poses
    against gt."""
    keep = ("rmse", "mean", "median", "max", "scale", "n")
    out = {f"ate_{mode}": {k: v for k, v in ate_rmse(poses, gt_poses, mode).items() if k in keep}
           for mode in ("se3", "sim3")}
    out["rpe"] = {k: v for k, v in rpe(poses, gt_poses).items() if not isinstance(v, np.ndarray)}
    out["rotation_error"] = {k: v for k, v in rotation_error(poses, gt_poses).items() if k != "errors_deg"}
    out["scale_error"] = scale_error(poses, gt_poses)
    return out


def reference_tsdf_mesh(dataset, indices: np.ndarray, voxel_size: float | None, max_depth: float, progress: bool,
                        depth: np.ndarray | None = None, intrinsics=None):
    """TSDF mesh of the dataset's sensor depth with its ground-truth poses over `indices`.

    depth: that sensor depth (len(indices), H, W) when the caller has already read it, with
    its `intrinsics` (default: the dataset's).
    """
    from recon.fusion import FusionOptions, fuse

    if not dataset.has_depth or not dataset.has_poses:
        raise ReconInputError(
            f"{dataset.root}: needs sensor depth and poses for a reference mesh (or pass --reference-mesh)"
        )
    if depth is None:
        depth = dataset.load_depth_batch(indices)
    # The sensor's whole surface, however large: no weight threshold raised for memory.
    options = FusionOptions(voxel_size=voxel_size, max_depth=max_depth, progress=progress, max_extracted=0)
    camera = dataset.intrinsics if intrinsics is None else intrinsics
    return fuse(depth, None, dataset.poses[indices], camera, options).mesh


def in_run_camera(gt_depth: np.ndarray, report: dict) -> tuple[np.ndarray, tuple | None]:
    """Sensor depth (N, H, W) as the run saw its frames: when the run resampled them into the
    pinhole camera of a known lens (report.json ``intrinsics.undistorted``), the depth at the
    working size resampled the same way (nearest neighbour), with the run's intrinsics;
    otherwise unchanged, with None (the dataset's own intrinsics hold)."""
    camera = report.get("intrinsics", {})
    lens = camera.get("undistorted")
    if not lens:
        return gt_depth, None
    from recon.geometry.camera import undistortion_maps
    from recon.io.source import resize_depth

    width, height = report["frames"]["working_size"]
    maps = undistortion_maps(camera["values"], lens["distortion"], (height, width))
    moved = np.stack([cv2.remap(resize_depth(d, (height, width)), *maps, cv2.INTER_NEAREST,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=0) for d in gt_depth])
    return moved, tuple(camera["values"])


def evaluate_output(output, gt_path, options: EvalOptions | None = None) -> dict:
    """Evaluate an output folder of `recon run` against the dataset at `gt_path`.

    Returns a JSON-ready dict with "depth", "trajectory" and "mesh" sections (each present
    when the output and the dataset have what it needs) and "frames", "dataset"; a
    "depth_missing" or "mesh_missing" note says why the output's depth or mesh was not scored.
    """
    options = options or EvalOptions()
    out = load_output(output)
    dataset = open_dataset(gt_path)
    if out.indices.size and (out.indices.min() < 0 or out.indices.max() >= len(dataset)):
        raise ReconInputError(
            f"{out.path}: frame indices up to {int(out.indices.max())} do not fit {gt_path} ({len(dataset)} frames); "
            "was the output made from this dataset?"
        )
    result: dict = {"output": str(out.path),
                    "dataset": {"path": str(gt_path), "kind": dataset.kind, "frames": len(dataset)},
                    "frames": int(len(out.indices)),
                    "options": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(options).items()}}
    gt_depth = dataset.load_depth_batch(out.indices) if dataset.has_depth and out.depth is not None else None
    gt_camera = None
    if gt_depth is not None:
        gt_depth, gt_camera = in_run_camera(gt_depth, out.report)
        result["depth"] = evaluate_depth(out.depth, gt_depth, options)
    elif out.depth is not None:
        result["depth_missing"] = f"{gt_path} ({dataset.kind}) has no sensor depth: the depth maps are not scored"
    alignment, by_icp = None, False
    if out.poses is not None and dataset.has_poses:
        result["trajectory"] = evaluate_trajectory(out.poses, dataset.poses[out.indices])
        pose_source = str(out.report.get("poses", {}).get("source", ""))
        mode = options.mesh_align
        if mode == "auto":
            mode = "none" if pose_source in ("gt", "ground truth", "dataset") or "ground" in pose_source else "sim3"
        by_trajectory, by_icp = mode.removesuffix("+icp"), mode.endswith("+icp")
        if by_trajectory != "none":
            alignment = pose_alignment(out.poses, dataset.poses[out.indices], by_trajectory)
            result["mesh_scale"] = {"scale": alignment["scale"], "from": alignment["scale_from"],
                                    "explained": alignment["explained"], "fitted_scale": alignment["fitted_scale"]}
            if alignment["scale_from"] == "undetermined":
                log.warning("%s: the mesh is aligned with scale 1, not the trajectory's %.3f: that fit explains "
                            "%.0f%% of the camera centres' spread, too little to give a scale", out.path,
                            alignment["fitted_scale"], 100 * max(alignment["explained"], 0.0))
        result["mesh_align"] = mode
    has_mesh = out.mesh is not None and len(out.mesh.triangles) > 0
    if has_mesh and options.reference_mesh is None and not dataset.has_depth:
        result["mesh_missing"] = (f"{gt_path} ({dataset.kind}) has no sensor depth to fuse a reference mesh from: "
                                  "the mesh is not scored (pass --reference-mesh to score it)")
    elif has_mesh:
        if options.reference_mesh is not None:
            reference = o3d.io.read_triangle_mesh(str(options.reference_mesh))
            if len(reference.triangles) == 0:
                raise ReconInputError(f"{options.reference_mesh}: no triangles in the reference mesh")
        else:
            voxel = out.report.get("fusion", {}).get("voxel_size")
            reference = reference_tsdf_mesh(dataset, out.indices, voxel, options.max_depth, options.progress, gt_depth,
                                            gt_camera)
        mesh = (move_points(out.mesh.vertices, alignment), np.asarray(out.mesh.triangles))
        if by_icp:
            # The trajectory's alignment alone is scored too: both protocols from one
            # reference mesh, which costs more to build than either score.
            result["mesh_before_icp"] = mesh_metrics(mesh, reference, options.threshold, options.mesh_points).to_dict()
            mesh, result["mesh_icp"] = icp_registered(mesh, reference, options.mesh_points)
        result["mesh"] = mesh_metrics(mesh, reference, options.threshold, options.mesh_points).to_dict()
    else:
        # A run that meshed nothing writes no mesh file: say so rather than leave the table out.
        result["mesh_missing"] = f"no mesh in {out.path} (the run meshed nothing: see its warnings)"
    return result


def format_evaluation(result: dict) -> str:
    """The evaluation as short markdown tables."""
    lines = [f"evaluation of {result['output']} against {result['dataset']['path']} "
             f"({result['dataset']['kind']}, {result['frames']} frames)"]
    if "depth" in result:
        names = ("abs_diff", "abs_rel", "sq_rel", "rmse", "log_rmse", "delta1", "delta2", "delta3", "coverage")
        lines += ["", "| depth | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        for setting, metrics in result["depth"].items():
            lines.append(f"| {setting} | " + " | ".join(f"{metrics[n]:.4f}" for n in names) + " |")
    if "trajectory" in result:
        t = result["trajectory"]
        rot = f"{t['rotation_error']['median_deg']:.3f}" if "rotation_error" in t else "-"
        lines += ["", "| trajectory | ATE SE(3) rmse [m] | ATE Sim(3) rmse [m] | Sim(3) scale | RPE trans rmse [m] "
                      "| RPE rot rmse [deg] | orientation median [deg] |",
                  "|---|---|---|---|---|---|---|",
                  f"| | {t['ate_se3']['rmse']:.4f} | {t['ate_sim3']['rmse']:.4f} | {t['ate_sim3']['scale']:.4f} | "
                  f"{t['rpe']['trans_rmse']:.4f} | {t['rpe']['rot_rmse_deg']:.3f} | {rot} |"]
    if "mesh" in result:
        m = result["mesh"]
        lines += ["", f"| mesh (align {result.get('mesh_align', 'none')}) | accuracy [m] | completeness [m] "
                      f"| chamfer [m] | precision | recall | F-score@{m['threshold'] * 100:.0f}cm |",
                  "|---|---|---|---|---|---|---|",
                  f"| | {m['accuracy']:.4f} | {m['completeness']:.4f} | {m['chamfer']:.4f} | {m['precision']:.4f} | "
                  f"{m['recall']:.4f} | {m['fscore']:.4f} |"]
    if "mesh_icp" in result:
        icp = result["mesh_icp"]
        verdict = "" if icp["accepted"] else " (refused: too far from the trajectory's alignment, which is kept)"
        lines += ["", f"ICP after the trajectory's alignment: scale {icp['scale']:.4f}, rotation "
                      f"{icp['rotation_deg']:.2f} deg, translation {icp['translation_m']:.3f} m{verdict}; "
                      f"F-score@{result['mesh_before_icp']['threshold'] * 100:.0f}cm before ICP "
                      f"{result['mesh_before_icp']['fscore']:.4f}"]
    if "depth_missing" in result:
        lines += ["", f"depth: {result['depth_missing']}"]
    if "mesh_missing" in result:
        lines += ["", f"mesh: {result['mesh_missing']}"]
    return "\n".join(lines)
