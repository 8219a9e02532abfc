"""The built-in sample, end to end: render the synthetic room to a video file, run the
whole pipeline on it (`recon run`), and score the result against the scene's ground truth.

The demo writes its inputs under ``OUT/input/`` (the video, the simulated prior, the
ground-truth poses) so the run can be repeated by hand, and adds an ``evaluation`` block to
report.json (depth errors and the mesh against the ground-truth mesh). Poses:
``"estimate"`` (the front end), ``"gt"`` (the rendered trajectory) or ``"auto"`` (estimate
when the estimator is installed, else ground truth with a warning).
More: docs/running.md#the-demo-recon-demo
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import numpy as np

from medea_core import MedeaConfig

from ..choices import DEMO_PRIORS, POSE_CHOICES
from ..core.config import pipeline_medea
from ..errors import ReconInputError
from ..eval.depth import depth_metrics, multiview_inconsistency
from ..eval.mesh import mesh_metrics, visible_mask
from ..fusion import FusionOptions, fuse
from ..io.output_folder import REPORT_JSON, OutputFolder, atomic_write_bytes, frame_name, json_bytes, npy_bytes
from ..pipeline import PipelineConfig, PipelineResult, run_pipeline
from ..synthetic import SyntheticSequence, render_sequence, simulate_prior
from .cli_args import build_parser
from .cli_config import command_line

log = logging.getLogger(__name__)

DEMO_FPS = 30.0


def depth_report(depth, gt, poses, intrinsics) -> dict:
    """Metric accuracy against gt plus multi-view inconsistency of (N, H, W) depth."""
    metrics = depth_metrics(depth, gt)
    metrics["inconsistency"] = multiview_inconsistency(depth, poses, intrinsics)
    return metrics


def default_output() -> Path:
    """demo_out/<date-time>: a fresh folder per run, so `make demo` never clobbers a result."""
    return Path("demo_out") / datetime.now().strftime("%Y%m%d-%H%M%S")


def pose_estimator_available() -> bool:
    try:
        from ..poses import estimate_poses  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class DemoOptions:
    """frames, width, height: the rendered sequence; seed: scene and prior; poses: POSE_CHOICES;
    pose_options: estimator settings (PipelineConfig.pose_options) when poses are estimated;
    prior: "simulated" (ground truth distorted like a network, see recon.synthetic.prior)
    or "fastdepth"; compare_prior: also fuse the raw prior to score it (not written)."""

    output: Path | None = None
    overwrite: bool = False
    frames: int = 90
    width: int = 640
    height: int = 480
    seed: int = 0
    poses: str = "auto"
    pose_options: dict[str, Any] = field(default_factory=dict)
    prior: str = "simulated"
    compare_prior: bool = True
    adjust: bool = True
    medea: MedeaConfig = field(default_factory=pipeline_medea)
    rerun: str = "save"
    device: str = "cpu"
    progress: bool = True


@dataclass
class DemoReport:
    result: PipelineResult
    sequence: SyntheticSequence
    poses_used: str
    evaluation: dict
    seconds_render: float
    command: str


def write_demo_inputs(out: OutputFolder, seq: SyntheticSequence, prior: np.ndarray | None) -> dict[str, Path]:
    """The rendered video, the prior maps and the ground-truth trajectory under OUT/input/."""
    from ..io.pose_formats.trajectories import write_poses
    from ..io.video import write_video

    video = out.path_for("input/synthetic.mp4")
    with out.atomic("input/synthetic.mp4") as tmp:
        write_video(seq.rgb, tmp, DEMO_FPS)
    paths = {"video": video}
    with out.atomic("input/poses_gt.txt") as tmp:
        write_poses(tmp, seq.poses, "tum", timestamps=np.arange(len(seq.poses)) / DEMO_FPS)
    paths["poses"] = out.path_for("input/poses_gt.txt")
    if prior is not None:
        for i, depth in enumerate(prior):
            out.write_bytes(f"input/prior/{frame_name(i)}.npy", npy_bytes(depth.astype(np.float32)))
        paths["prior"] = out.path / "input" / "prior"
    return paths


def mesh_scores(mesh, seq: SyntheticSequence, stride: int = 2) -> dict:
    """Mesh metrics at 5 cm against the ground-truth mesh, both cut to what the cameras saw
    (every `stride`-th frame's ground-truth depth is enough to decide visibility)."""
    depth, poses = seq.depth[::stride], seq.poses[::stride]

    def seen(points):
        return visible_mask(points, depth, poses, seq.intrinsics)

    return mesh_metrics(mesh, seq.o3d_mesh(), num_points=100_000, point_filter=seen).to_dict()


def aligned_mesh(mesh, poses: np.ndarray, gt_poses: np.ndarray):
    """A copy of `mesh` moved by the similarity that takes the cameras onto gt's (orientations
    and centres: :func:`recon.eval.trajectory.pose_alignment`), and that similarity."""
    import copy

    from ..eval.trajectory import move_points, pose_alignment

    fit = pose_alignment(poses, gt_poses, "sim3")
    moved = copy.deepcopy(mesh)
    moved.vertices = type(moved.vertices)(move_points(moved.vertices, fit))
    return moved, fit


def evaluate(
    result: PipelineResult, seq: SyntheticSequence, compare_prior: bool = True, estimated: bool = False
) -> dict:
    """Depth error of the prior, MEDeA and the refinement, and their mesh scores (module docstring)."""
    idx = result.frames.indices
    gt_depth, gt_poses = seq.depth[idx], seq.poses[idx]
    adjusted = result.depth if result.adjusted_depth is None else result.adjusted_depth
    evaluation = {
        "depth_prior": depth_report(result.prior_depth, gt_depth, gt_poses, seq.intrinsics),
        "depth_adjusted": depth_report(adjusted, gt_depth, gt_poses, seq.intrinsics),
    }
    if result.refined is not None:
        evaluation["depth_refined"] = depth_report(result.depth, gt_depth, gt_poses, seq.intrinsics)
    mesh = result.fusion.mesh
    if estimated:
        mesh, evaluation["alignment"] = aligned_mesh(mesh, result.poses, gt_poses)
    evaluation["mesh_refined" if result.refined is not None else "mesh_adjusted"] = mesh_scores(mesh, seq)
    # The depths the pipeline did not fuse, fused the same way for comparison (not written).
    others = []
    if result.refined is not None:
        others.append(("mesh_adjusted", adjusted))
    if compare_prior and result.medea is not None:
        others.append(("mesh_prior", result.prior_depth))
    for key, depth in others:
        other = fuse(depth, result.frames.rgb, result.poses, result.intrinsics, FusionOptions(progress=False)).mesh
        if estimated:
            other, _ = aligned_mesh(other, result.poses, gt_poses)
        evaluation[key] = mesh_scores(other, seq)
    return evaluation


def run_demo(options: DemoOptions, say: Callable[[str], None] | None = None) -> DemoReport:
    """Render, write the inputs, run the pipeline, evaluate; returns the report (also on disk).
    say: called with each step's name (the CLI prints them); None says nothing."""
    say = say or (lambda _: None)
    if options.poses not in POSE_CHOICES:
        raise ReconInputError(f"demo poses must be one of {', '.join(POSE_CHOICES)}, got {options.poses!r}")
    if options.prior not in DEMO_PRIORS:
        raise ReconInputError(f"demo prior must be one of {', '.join(DEMO_PRIORS)}, got {options.prior!r}")
    if options.frames < 2:
        raise ReconInputError(f"demo needs at least 2 frames, got {options.frames}")
    output = Path(options.output) if options.output is not None else default_output()
    out = OutputFolder(output, options.overwrite)  # refuses a non-empty folder before any work

    poses = options.poses
    if poses == "auto":
        poses = "estimate" if pose_estimator_available() else "gt"
        if poses == "gt":
            log.warning("pose estimation is not installed in this build; using the ground-truth poses "
                        "(--poses estimate to require it)")
    start = time.perf_counter()
    say(f"rendering the synthetic room: {options.frames} frames at {options.width}x{options.height}")
    seq = render_sequence(options.frames, options.width, options.height, seed=options.seed)
    prior = simulate_prior(seq.depth, seed=options.seed) if options.prior == "simulated" else None
    inputs = write_demo_inputs(out, seq, prior)
    seconds_render = time.perf_counter() - start

    config = PipelineConfig(
        input=inputs["video"], output=out.path, overwrite=True, width=None, intrinsics=seq.intrinsics,
        poses=str(inputs["poses"]) if poses == "gt" else "estimate", pose_options=dict(options.pose_options),
        prior="folder" if prior is not None else "fastdepth", prior_path=inputs.get("prior"),
        adjust=options.adjust, medea=options.medea, rerun=options.rerun, device=options.device,
        progress=options.progress, stream="off",  # the scoring below reads the one-shot run's prior and MEDeA depth
    )
    command = command_line(config, build_parser())
    say(f"running: {command}")
    result = run_pipeline(config, on_stage=lambda stage: say(f"  {stage}") if options.progress else None)

    say("scoring against the ground truth")
    evaluation = evaluate(result, seq, options.compare_prior, estimated=poses == "estimate")
    report = {**result.report, "demo": {"frames": options.frames, "size": [options.width, options.height],
                                         "seed": options.seed, "poses": poses, "prior": options.prior,
                                         "seconds_render": seconds_render, "command": command},
              "evaluation": evaluation}
    # The pipeline wrote report.json through its own OutputFolder; this run owns it.
    atomic_write_bytes(out.path / REPORT_JSON, json_bytes(report), overwrite=True)
    result = replace(result, report=report)
    return DemoReport(result, seq, poses, evaluation, seconds_render, command)


def format_demo(report: DemoReport) -> str:
    """Depth error table (prior, MEDeA, refined; change: last against the prior) and mesh
    scores, as the demo prints them."""
    ev = report.evaluation
    columns = [("prior", ev["depth_prior"]), ("MEDeA", ev["depth_adjusted"])]
    if "depth_refined" in ev:
        columns.append(("refined", ev["depth_refined"]))
    rows = [("abs rel", "abs_rel", "{:.4f}"), ("abs diff [m]", "abs_diff", "{:.4f}"), ("sq rel", "sq_rel", "{:.4f}"),
            ("RMSE [m]", "rmse", "{:.4f}"), ("delta < 1.25", "delta1", "{:.4f}"),
            ("inconsistency", "inconsistency", "{:.4f}")]
    lines = [f"{'depth metric':<16}" + "".join(f"{name:>10}" for name, _ in columns) + f"{'change':>10}"]
    for label, key, fmt in rows:
        values = [depth[key] for _, depth in columns]
        change = (values[-1] - values[0]) / values[0] if values[0] else float("nan")
        lines.append(f"{label:<16}" + "".join(f"{fmt.format(v):>10}" for v in values) + f"{change:>+10.0%}")
    lines.append("")
    lines.append(f"{'mesh vs ground truth (5 cm)':<28}{'accuracy':>10}{'complete':>10}{'precision':>10}"
                 f"{'recall':>10}{'F-score':>10}")
    for label, key in (("refined depth (written)", "mesh_refined"), ("MEDeA depth", "mesh_adjusted"),
                       ("raw prior", "mesh_prior")):
        if key in ev:
            m = ev[key]
            lines.append(f"{label:<28}{m['accuracy']:>10.4f}{m['completeness']:>10.4f}{m['precision']:>10.3f}"
                         f"{m['recall']:>10.3f}{m['fscore']:>10.3f}")
    lines.append(f"poses: {report.poses_used}; rendering {report.seconds_render:.1f} s")
    return "\n".join(lines)


__all__ = ["DemoOptions", "DemoReport", "default_output", "depth_report", "evaluate", "format_demo", "mesh_scores",
           "run_demo", "write_demo_inputs"]
