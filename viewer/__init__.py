"""Rerun inspection of the pipeline (see ``viewer.rerun_log``): a leaf library that never
imports recon; reading an output folder for `recon view` is :mod:`recon.view`'s."""

from .rerun_log import RerunLogger, default_mode

__all__ = ["RerunLogger", "default_mode"]
