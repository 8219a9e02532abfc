"""Rerun inspection of the pipeline (see ``viewer.rerun_log``, ``viewer.arrays`` for the
arrays it accepts, and ``viewer.blueprint`` for the layout every recording opens with): a
leaf library that never imports recon; reading an output folder for `recon view` is
:mod:`recon.commands.view`'s."""

from .modes import default_mode


def __getattr__(name: str):
    """RerunLogger and default_blueprint, imported when first asked for: they import the Rerun
    SDK, which a run without a viewer never needs (PEP 562)."""
    if name == "RerunLogger":
        from .rerun_log import RerunLogger

        return RerunLogger
    if name == "default_blueprint":
        from .blueprint import default_blueprint

        return default_blueprint
    raise AttributeError(f"module 'viewer' has no attribute {name!r}")


__all__ = ["RerunLogger", "default_blueprint", "default_mode"]
