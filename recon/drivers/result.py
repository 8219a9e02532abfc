"""What a run returns, whichever driver ran it: :class:`RunResult` holds what both fill (and
what `recon run` prints, recon.pipeline.format_summary); the one-shot driver's
``PipelineResult`` adds the frames and depth it holds in memory, the streamed driver's
``StreamResult`` the counts of tracked and depth frames (its depth is on disk)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(kw_only=True)
class RunResult:
    """output: the output folder (everything below is also on disk there); poses (N, 4, 4)
    camera-to-world; intrinsics (fx, fy, cx, cy) at working size; fusion: the FusionResult
    (its ``mesh``); seconds: {stage: wall seconds}; files: {label: path}; report: what
    report.json holds; rerun_url: the live viewer's address, if one was served; segments:
    each stretch's own result where the trajectory's scale broke (--on-break segments).
    Both drivers' results also give ``depth`` (N, H, W) metres."""

    output: Path
    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    fusion: object
    seconds: dict[str, float]
    files: dict[str, Path]
    report: dict
    rerun_url: str | None = None
    segments: list = field(default_factory=list)

    @property
    def frame_count(self) -> int:
        """The frames the seconds are counted over (a streamed run: every tracked frame)."""
        raise NotImplementedError

    @property
    def seconds_per_frame(self) -> dict[str, float]:
        n = max(1, self.frame_count)
        return {stage: s / n for stage, s in self.seconds.items()}


__all__ = ["RunResult"]
