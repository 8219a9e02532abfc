"""Rerun inspection of the pipeline (see ``viewer.rerun_log``)."""

from .rerun_log import RerunLogger, default_mode

__all__ = ["RerunLogger", "default_mode"]
