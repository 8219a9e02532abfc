"""The built-in sample: render the synthetic room, simulate a monocular prior, run MEDeA
with the ground-truth poses, and measure depth error and consistency before and after.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from medea_core import MedeaConfig, MedeaResult

from .eval.depth import depth_metrics, multiview_inconsistency
from .medea import adjust_sequence
from .synthetic import render_sequence, simulate_prior


@dataclass
class DemoReport:
    frames: int
    size: tuple[int, int]
    before: dict
    after: dict
    seconds_render: float
    seconds_medea: float
    result: MedeaResult


def depth_report(depth, gt, poses, intrinsics) -> dict:
    """Metric accuracy against gt plus multi-view inconsistency of (N, H, W) depth."""
    metrics = depth_metrics(depth, gt)
    metrics["inconsistency"] = multiview_inconsistency(depth, poses, intrinsics)
    return metrics


def run_synthetic_demo(
    num_frames: int = 120,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    config: MedeaConfig | None = None,
    progress: bool = True,
) -> DemoReport:
    start = time.perf_counter()
    seq = render_sequence(num_frames=num_frames, width=width, height=height, seed=seed)
    prior = simulate_prior(seq.depth, seed=seed)
    seconds_render = time.perf_counter() - start
    start = time.perf_counter()
    result = adjust_sequence(seq.rgb, prior, seq.poses, seq.intrinsics, config=config, progress=progress)
    seconds_medea = time.perf_counter() - start
    adjusted = result.depth.numpy()
    return DemoReport(
        frames=num_frames,
        size=(height, width),
        before=depth_report(prior, seq.depth, seq.poses, seq.intrinsics),
        after=depth_report(adjusted, seq.depth, seq.poses, seq.intrinsics),
        seconds_render=seconds_render,
        seconds_medea=seconds_medea,
        result=result,
    )


def format_report(report: DemoReport) -> str:
    rows = [("abs rel", "abs_rel", "{:.4f}"), ("abs diff [m]", "abs_diff", "{:.4f}"), ("sq rel", "sq_rel", "{:.4f}"),
            ("RMSE [m]", "rmse", "{:.4f}"), ("delta < 1.25", "delta1", "{:.4f}"), ("inconsistency", "inconsistency", "{:.4f}")]
    lines = [f"{'metric':<16}{'prior':>10}{'MEDeA':>10}{'change':>10}"]
    for label, key, fmt in rows:
        before, after = report.before[key], report.after[key]
        change = (after - before) / before if before else float("nan")
        lines.append(f"{label:<16}{fmt.format(before):>10}{fmt.format(after):>10}{change:>+10.0%}")
    history = report.result.history
    epochs = ", ".join(f"{name} {h.epochs} epochs" for name, h in history.items())
    lines.append(
        f"{report.frames} frames at {report.size[1]}x{report.size[0]}: rendered in {report.seconds_render:.1f} s, "
        f"MEDeA {report.seconds_medea:.1f} s ({report.seconds_medea / report.frames:.3f} s/frame; {epochs})"
    )
    return "\n".join(lines)
