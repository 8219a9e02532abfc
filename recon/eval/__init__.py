"""Metrics: depth accuracy and multi-view consistency (`depth`), trajectories
(`trajectory`), meshes (`mesh`)."""

from .depth import METRIC_NAMES, depth_metrics, multiview_inconsistency

__all__ = ["METRIC_NAMES", "depth_metrics", "multiview_inconsistency"]
