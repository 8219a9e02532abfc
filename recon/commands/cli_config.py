"""Parsed `recon` arguments -> the typed configs they mirror: recon.pipeline.PipelineConfig
(over a --config file and --set), MedeaConfig (over a shipped preset) and the pose options;
the device, the Rerun mode, and the `recon run` command line that makes a config
(``command_line``). ``RUN_FLAGS`` names the setting each flag of `recon run` sets: the
parser (recon.commands.cli_args) is made from it, help texts from the settings' field
docstrings, and ``config_from_flags`` reads the parsed flags back through it.
"""

from __future__ import annotations

import argparse
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from medea_core import MedeaConfig

from ..choices import (
    ON_BREAK_CHOICES,
    POSE_CHOICES,
    POSE_METHODS,
    PRIOR_ALIGN_CHOICES,
    PRIOR_CHOICES,
    REFINE_CHOICES,
    RERUN_MODES,
    STREAM_CHOICES,
)
from ..errors import ReconInputError


def medea_config_from_args(args: argparse.Namespace) -> MedeaConfig:
    """MEDeA's settings: the preset of --preset, the seed of --seed (`recon demo`), the device."""
    config = preset_medea(args.preset)
    if getattr(args, "seed", None) is not None:
        config.seed = args.seed
    config.device = resolve_device(args.device)
    return config


def preset_medea(name: str) -> MedeaConfig:
    """The MEDeA settings of preset `name`: its shipped config file's ``medea`` section over
    the paper's MedeaConfig (recon.core.config_file.preset_path)."""
    from ..core.config_file import preset_path, read_config_file, updated

    return updated(MedeaConfig(), read_config_file(preset_path(name)).get("medea", {}), "medea")


def resolve_device(name: str) -> str:
    """The torch device for --device NAME (cpu, cuda, cuda:N or auto), checked here."""
    from ..core.config import device_index

    index = device_index(name)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ReconInputError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    if index is not None and index >= torch.cuda.device_count():
        raise ReconInputError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA device(s), "
                              f"numbered from 0")
    return name


def _numbers(text: str, count: int | tuple[int, ...], what: str) -> tuple[float, ...]:
    """`count` numbers (or one of the counts of a tuple) separated by commas."""
    counts = (count,) if isinstance(count, int) else count
    parts = [p for p in text.replace(",", " ").split() if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) not in counts:
        expected = " or ".join(str(c) for c in counts)
        raise ReconInputError(f"{what}: expected {expected} numbers separated by commas, got {text!r}")
    return values


def rerun_mode(args: argparse.Namespace, default: str) -> tuple[str, Path | None]:
    """(mode, path or None) from --rerun MODE [PATH]."""
    values = args.rerun or [default]
    mode, rest = values[0], values[1:]
    if mode not in RERUN_MODES:
        raise ReconInputError(f"--rerun: mode must be one of {', '.join(RERUN_MODES)}, got {mode!r}")
    if rest and mode != "save":
        raise ReconInputError(f"--rerun {mode} takes no path (only 'save' does)")
    if len(rest) > 1:
        raise ReconInputError(f"--rerun save takes one path, got {len(rest)}")
    return mode, Path(rest[0]) if rest else None


def pose_options_from_args(args: argparse.Namespace) -> dict:
    from ..poses.options import parse_pose_option

    return dict(parse_pose_option(text) for text in args.pose_option)


def pipeline_config_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser):
    """The run's PipelineConfig: the flags, over the settings of --config FILE if given
    (recon.core.config_file: a flag overrides the file where it differs from its default)."""
    from ..core.config_file import merged, read_config_file, with_settings

    config = config_from_flags(args)
    if getattr(args, "config", None) is not None:
        config = merged(read_config_file(args.config), config, bare_config(parser, args.input, args.output))
    return with_settings(config, getattr(args, "settings", None) or [])


def command_line(config, parser: argparse.ArgumentParser) -> str:
    """The `recon run` command line that makes `config`: its input and output, and a ``--set``
    for every setting in which it differs from a bare `recon run IN -o OUT`
    (recon.core.config_file.changed_settings), so that it cannot drift from the flags."""
    import shlex

    from ..core.config_file import changed_settings

    words = ["recon", "run", str(config.input), "-o", str(config.output)] + (["--overwrite"] * config.overwrite)
    for item in changed_settings(config, bare_config(parser, config.input, config.output)):
        if item.partition("=")[0] != "overwrite":
            words += ["--set", item]
    return shlex.join(words)


def bare_config(parser: argparse.ArgumentParser, input_path, output):
    """The config of a bare `recon run INPUT -o OUTPUT`: every flag at its default."""
    return config_from_flags(parser.parse_args(["run", str(input_path), "-o", str(output)]))


def config_from_flags(args: argparse.Namespace):
    """The PipelineConfig the parsed flags of `recon run` make (the settings of RUN_FLAGS)."""
    from ..core.config_file import with_values
    from ..pipeline import PipelineConfig

    medea = medea_config_from_args(args)
    mode, path = rerun_mode(args, default_rerun_mode())
    config = PipelineConfig(
        input=Path(args.input), output=Path(args.output), overwrite=args.overwrite,
        pose_options=pose_options_from_args(args), adjust=not args.no_medea, medea=medea,
        rerun=mode, rerun_path=path, device=medea.device, progress=not args.quiet,
    )
    return with_values(config, {flag.setting: flag.value(args) for _, _, flags in RUN_FLAGS for flag in flags})


def default_rerun_mode() -> str:
    from viewer import default_mode

    return default_mode()


# --------------------------------------------------------------------------- the flags of `recon run`


@dataclass(frozen=True)
class Flag:
    """A flag of `recon run` that sets one setting, whose field docstring is its help.

    option: the flag ("--stride"). setting: the dotted setting it sets ("fusion.voxel_size").
    parse: argparse's keywords (type, choices, metavar, action, dest); a flag that takes a
    value defaults to the setting's default. convert: the parsed value -> the setting's.
    """

    option: str
    setting: str
    parse: dict = field(default_factory=dict)
    convert: Callable | None = None

    @property
    def dest(self) -> str:
        return self.parse.get("dest") or self.option.lstrip("-").replace("-", "_")

    def value(self, args: argparse.Namespace):
        """The setting's value in the parsed arguments `args`."""
        value = getattr(args, self.dest)
        return value if self.convert is None else self.convert(value)


def _off(value: bool) -> bool:
    return not value


def _numbers_of(option: str, count):
    return lambda text: None if text is None else _numbers(text, count, option)


# (group title, where the docs explain it, its flags) in the order of `recon run --help`.
RUN_FLAGS: list[tuple[str, str, list[Flag]]] = [
    ("frames", "docs/running.md#long-videos-streaming", [
        Flag("--stride", "stride", {"type": int}),
        Flag("--max-frames", "max_frames", {"type": int}),
        Flag("--start", "start_time", {"type": float}),
        Flag("--end", "end_time", {"type": float}),
        Flag("--frame-budget", "frame_budget", {"type": int}),
        Flag("--stream", "stream", {"choices": STREAM_CHOICES}),
        Flag("--depth-frames", "depth_frames", {"metavar": "{motion,all,K}"}),
        Flag("--window", "window", {"type": int}),
        Flag("--width", "width", {"type": int}, convert=lambda width: width or None),
        Flag("--fps", "fps", {"type": float}),
    ]),
    ("camera", "docs/poses.md", [
        Flag("--intrinsics", "intrinsics", {"metavar": "FX,FY,CX,CY"}, convert=_numbers_of("--intrinsics", 4)),
        Flag("--fov", "fov", {"type": float}),
        Flag("--distortion", "distortion", {"metavar": "K1,K2,P1,P2[,K3]"},
             convert=_numbers_of("--distortion", (4, 5))),
        Flag("--rolling-shutter", "rolling_shutter", {"type": float, "metavar": "MS"}),
    ]),
    ("poses", "docs/poses.md", [
        Flag("--poses", "poses", {"metavar": "{%s}|PATH" % ",".join(POSE_CHOICES)}),
        Flag("--pose-method", "pose_method", {"choices": POSE_METHODS}),
        Flag("--on-break", "on_break", {"choices": ON_BREAK_CHOICES}),
        Flag("--no-join", "join_segments", {"action": "store_false", "dest": "join_segments"}),
    ]),
    ("depth prior", "docs/depth.md#the-depth-prior---prior", [
        Flag("--prior", "prior", {"choices": PRIOR_CHOICES}),
        Flag("--prior-path", "prior_path", {"type": Path, "metavar": "PATH"}),
        Flag("--prior-align", "prior_align", {"choices": PRIOR_ALIGN_CHOICES}),
        Flag("--weights", "weights", {"type": Path}),
        Flag("--no-features", "features", {"action": "store_true"}, convert=_off),
    ]),
    ("multi-view stereo refinement (after MEDeA)", "docs/depth.md#the-multi-view-stereo-refinement---refine", [
        Flag("--refine", "refine", {"choices": REFINE_CHOICES}),
        Flag("--polish", "polish", {"action": "store_true"}),
        Flag("--medea-gate", "medea_gate", {"action": "store_true"}),
    ]),
    ("TSDF fusion", "docs/fusion.md", [
        Flag("--voxel-size", "fusion.voxel_size", {"type": float}),
        Flag("--max-depth", "fusion.max_depth", {"type": float}),
        Flag("--min-confidence", "fusion.min_confidence", {"type": float}),
        Flag("--max-triangles", "fusion.max_triangles", {"type": int}),
        Flag("--point-cloud", "fusion.point_cloud", {"action": "store_true"}),
    ]),
    ("output", "docs/outputs.md", [
        Flag("--no-npy", "depth_npy", {"action": "store_true"}, convert=_off),
        Flag("--no-glb", "glb", {"action": "store_true"}, convert=_off),
    ]),
]


def setting_field(name: str) -> tuple[type, str]:
    """(the dataclass that has the setting, its field name) of a dotted setting of PipelineConfig."""
    from ..pipeline import PipelineConfig

    owner, *path = [PipelineConfig, *name.split(".")]
    for part in path[:-1]:
        owner = typing.get_type_hints(owner)[part]
    return owner, path[-1]

