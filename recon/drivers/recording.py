"""The run's Rerun recording, opened the same way by both drivers: saved (to OUT/recording.rrd
or --rerun-path, under a temporary name until the run ends well), served or spawned."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

from ..core.config import PipelineConfig
from ..io.output_folder import RECORDING, OutputFolder, atomic_path


def open_recording(config: PipelineConfig, out: OutputFolder, stack: ExitStack):
    """The run's Rerun logger as ``config.rerun`` says, closed when `stack` closes: (RerunLogger
    or None for "off", the final .rrd path or None). A saved recording is written under a
    temporary name and renamed when the run ends well, like every other output file."""
    if config.rerun == "off":
        return None, None
    from viewer import RerunLogger

    if config.rerun == "save":
        final = out.path_for(RECORDING) if config.rerun_path is None else Path(config.rerun_path)
        tmp = stack.enter_context(out.atomic(RECORDING) if config.rerun_path is None
                                  else atomic_path(config.rerun_path, overwrite=config.overwrite))
        logger = stack.enter_context(RerunLogger("save", tmp, max_width=config.rerun_max_width))
        return logger, final
    logger = RerunLogger(config.rerun, max_width=config.rerun_max_width)
    stack.callback(logger.close)
    return logger, None


__all__ = ["open_recording"]
