"""Rerun inspection of the pipeline (see ``viewer.rerun_log``, ``viewer.arrays`` for the
arrays it accepts, and ``viewer.blueprint`` for the layout every recording opens with): a
leaf library that never imports recon; reading an output folder for `recon view` is
:mod:`recon.commands.view`'s."""

from .blueprint import default_blueprint
from .rerun_log import RerunLogger, default_mode

__all__ = ["RerunLogger", "default_blueprint", "default_mode"]
