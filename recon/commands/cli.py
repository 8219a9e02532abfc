"""The `recon` command line: `recon run`, `recon batch`, `recon demo`, `recon view`, `recon eval`
and `recon export`.

This module runs the commands; their options, which mirror the typed configs, are parsed by
recon.commands.cli_args and turned into those configs by recon.commands.cli_config. The
library never prints: `main` gives the ``recon`` logger one handler (``recon: warning: ...``
on stderr) and prints a ReconInputError raised anywhere below as the single line
``recon: error: ...``, exit code 2, no traceback.
More: docs/outputs.md#errors-and-exit-codes
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from ..errors import ReconInputError
from .cli_args import build_parser
from .cli_config import (
    default_rerun_mode,
    medea_config_from_args,
    pipeline_config_from_args,
    pose_options_from_args,
    rerun_mode,
)


def _wait_for_ctrl_c(url: str | None) -> None:
    import time

    print(f"rerun: serving {url or ''} (web viewer on localhost); press Ctrl-C to stop", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


# --------------------------------------------------------------------------- recon run


def _cmd_run(args: argparse.Namespace) -> int:
    from ..export.tools import ExportOptions, export_folder, parse_formats
    from ..memory import freeze_imported
    from ..pipeline import format_summary, run_pipeline

    freeze_imported()
    formats = parse_formats(args.export) if args.export is not None else ()  # bad names fail before the run
    config = pipeline_config_from_args(args, build_parser())
    result = run_pipeline(config, on_stage=None if args.quiet else lambda stage: print(stage, flush=True))
    print(format_summary(result))
    if formats:
        # Into OUT/<format>/ (each segment folder's, for a run written as segments).
        options = ExportOptions(overwrite=config.overwrite, input=config.input, progress=not args.quiet)
        for exported in export_folder(result.output, formats, options=options):
            print(f"exported {exported}")
    if config.rerun == "serve":
        _wait_for_ctrl_c(result.rerun_url)
    return 0


# --------------------------------------------------------------------------- recon batch


def _cmd_batch(args: argparse.Namespace) -> int:
    import dataclasses

    from .batch import FAILED, BatchOptions, default_gpus_per_task, format_progress, format_table, run_batch

    # The run options mean what they mean for `recon run`: the same conversion, on a stand-in
    # input and output that each input's copy replaces. The device is resolved in each task,
    # on the node Ray picks, not here.
    run_args = argparse.Namespace(**{**vars(args), "input": ".", "output": ".", "overwrite": False, "device": "cpu",
                                     "rerun": ["save" if args.save_recording else "off"]})
    template = dataclasses.replace(pipeline_config_from_args(run_args, build_parser()), device=args.device)
    gpus = default_gpus_per_task(args.device) if args.gpus_per_task is None else args.gpus_per_task
    options = BatchOptions(address=args.address, num_cpus=args.num_cpus, cpus_per_task=args.cpus_per_task,
                           gpus_per_task=gpus, memory_per_task=args.memory_per_task, node_retries=args.node_retries)

    def on_done(outcome, progress) -> None:
        for message in outcome.warnings:  # the task's warnings, as `recon run` would have shown them
            logging.getLogger("recon.commands.batch").warning("%s: %s", outcome.input, message)
        if not args.quiet:
            print(format_progress(outcome, progress), flush=True)

    rows = run_batch(args.inputs, args.output, template, options, on_done)
    print(format_table(rows))
    failed = sum(row.status == FAILED for row in rows)
    if failed:
        raise ReconInputError(f"{failed} of {len(rows)} inputs failed")
    return 0


# --------------------------------------------------------------------------- recon demo


def _cmd_demo(args: argparse.Namespace) -> int:
    from ..memory import freeze_imported
    from ..pipeline import format_summary
    from .demo import DemoOptions, default_output, format_demo, run_demo

    freeze_imported()
    medea = medea_config_from_args(args)
    pose_options = pose_options_from_args(args)
    mode, path = rerun_mode(args, "save")
    if path is not None:
        raise ReconInputError("recon demo --rerun save takes no path (the recording is OUT/recording.rrd)")
    output = args.output or default_output()
    print(f"recon demo: {args.frames} frames at {args.width}x{args.height}, prior {args.prior}, poses {args.poses}, "
          f"MEDeA preset {args.preset} on {medea.device}; output {output}")
    report = run_demo(DemoOptions(
        output=output, overwrite=args.overwrite, frames=args.frames, width=args.width, height=args.height,
        seed=args.scene_seed, poses=args.poses, pose_options=pose_options, prior=args.prior,
        compare_prior=not args.no_compare,
        adjust=not args.no_medea, medea=medea,
        rerun=mode, device=medea.device, progress=not args.quiet,
    ), say=print)
    print(format_summary(report.result))
    print()
    print(format_demo(report))
    if mode == "serve":
        _wait_for_ctrl_c(report.result.rerun_url)
    return 0


# --------------------------------------------------------------------------- recon export


def _cmd_export(args: argparse.Namespace) -> int:
    from ..export.tools import ExportOptions, export_folder

    given = {"max_points": args.max_points, "image_format": args.image_format}  # unset: ExportOptions' defaults
    options = ExportOptions(**{k: v for k, v in given.items() if v is not None}, overwrite=args.overwrite,
                            input=args.input, progress=not args.quiet)
    for exported in export_folder(args.output, args.to, args.dest, options):
        print(f"wrote {exported}")
    return 0


# --------------------------------------------------------------------------- recon eval


def _cmd_eval(args: argparse.Namespace) -> int:
    from ..eval.evaluate import EvalOptions, evaluate_output, format_evaluation
    from ..io.output_folder import EVAL_JSON, atomic_write_bytes, json_bytes

    options = EvalOptions(min_depth=args.min_depth, max_depth=args.max_depth, threshold=args.threshold,
                          reference_mesh=args.reference_mesh, mesh_align=args.mesh_align, progress=not args.quiet)
    target = Path(args.output) / EVAL_JSON
    if target.exists() and not args.overwrite:
        raise ReconInputError(f"{target}: already exists (use --overwrite to replace it)")
    result = evaluate_output(args.output, args.gt, options)
    print(format_evaluation(result))
    atomic_write_bytes(target, json_bytes(result), overwrite=args.overwrite)
    print(f"\nwrote {target}")
    return 0


# --------------------------------------------------------------------------- recon view


def _cmd_view(args: argparse.Namespace) -> int:
    import tempfile
    from contextlib import ExitStack

    from viewer import RerunLogger

    from ..io.output_folder import RECORDING, atomic_path
    from .view import log_output_folder, recording_of

    display_default = "spawn" if default_rerun_mode() == "spawn" else "serve"
    mode, path = rerun_mode(args, display_default)
    if mode == "off":
        raise ReconInputError("recon view needs a Rerun mode: spawn, serve or save PATH")
    target = Path(args.path)
    if not target.exists():
        raise ReconInputError(f"{target}: no such file or folder")
    recording = recording_of(target)
    if recording is not None and mode != "save":
        return _open_recording(recording, mode, args.bind)
    if mode == "save" and path is None:
        raise ReconInputError("recon view --rerun save needs a path: --rerun save OUT.rrd")
    if path is not None and path.exists() and not args.overwrite:
        raise ReconInputError(f"{path}: already exists (pass --overwrite to replace it)")
    if mode == "serve":
        # The SDK's own server listens on every interface; the viewer's command line binds where
        # it is told, so the folder is logged to a temporary recording that it then serves.
        with tempfile.TemporaryDirectory(prefix="recon-view-") as folder:
            temporary = Path(folder) / RECORDING
            with RerunLogger("save", temporary, max_width=None) as logger:
                summary = log_output_folder(target, logger, progress=not args.quiet)
            print(f"logged {summary}")
            return _open_recording(temporary, mode, args.bind)
    with ExitStack() as stack:
        written = None if path is None else stack.enter_context(atomic_path(path, overwrite=args.overwrite))
        with RerunLogger(mode, written, max_width=None) as logger:
            summary = log_output_folder(target, logger, progress=not args.quiet)
    print(f"logged {summary}" + (f" to {path}" if path else ""))
    return 0


def _open_recording(recording: Path, mode: str, bind: str) -> int:
    """The Rerun viewer on an .rrd: a desktop window (spawn, returns at once) or a web viewer
    listening on `bind` until Ctrl-C (serve)."""
    import subprocess

    command = [sys.executable, "-m", "rerun", str(recording)]
    if mode == "serve":
        command += ["--serve-web", "--bind", bind]
    print(f"opening {recording} in Rerun ({mode}{f' on {bind}' if mode == 'serve' else ''})")
    if mode == "spawn":
        subprocess.Popen(command, start_new_session=True)
        return 0
    try:
        return subprocess.call(command)
    except KeyboardInterrupt:
        return 0


# --------------------------------------------------------------------------- main

_COMMANDS = {"run": _cmd_run, "batch": _cmd_batch, "demo": _cmd_demo, "view": _cmd_view, "eval": _cmd_eval,
             "export": _cmd_export}


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a record comes (it may be replaced after the
    handler is made: tests capture it, embedding applications redirect it)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value):
        pass


def _log_warnings_to_stderr() -> None:
    """recon's warnings (a pose fallback, frames fusion skipped) as `recon: warning: ...`
    lines; without a handler Python prints them bare."""
    logger = logging.getLogger("recon")
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("recon: warning: %(message)s"))
        handler.setLevel(logging.WARNING)
        logger.addHandler(handler)


class _Terminated(BaseException):
    """SIGTERM (a scheduler or `kill` stopping the run), raised where the run is so that its
    clean-up runs as on Ctrl-C: the frame store's temporary files and the half-written output
    folder go; by default Python would die on the spot and leave them."""


# Set once SIGTERM arrives. The exception the handler raises can come out as another one: a
# C function that is interrupted (numpy.fromfile inside np.load) may replace it with its own
# TypeError. Whatever propagates after the signal, the run was terminated.
_TERMINATION = threading.Event()


def _raise_terminated(signum, frame):
    _TERMINATION.set()
    raise _Terminated


def main(argv: list[str] | None = None) -> int:
    # A crash in native code (Open3D, torch, FFmpeg) then leaves the Python stack on stderr
    # instead of a bare exit status.
    if not faulthandler.is_enabled():
        faulthandler.enable()
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if in_main_thread else None
    _TERMINATION.clear()
    try:
        return _main(argv)
    except BrokenPipeError:
        # Whoever read our output stopped early (`recon run --pose-option list | head`): not
        # an error. Point stdout at /dev/null so the interpreter's final flush stays quiet.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except BaseException:
        if not _TERMINATION.is_set():  # set by the handler before it raises _Terminated
            raise
        print("recon: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _log_warnings_to_stderr()
    try:
        return _COMMANDS[args.command](args)
    except ReconInputError as error:
        if _TERMINATION.is_set():
            raise  # a read cut short by SIGTERM, not bad input
        print(f"recon: error: {error}", file=sys.stderr)
        return ReconInputError.exit_code
    except KeyboardInterrupt:
        print("recon: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
