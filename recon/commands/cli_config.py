"""Parsed `recon` arguments -> the typed configs they mirror: recon.pipeline.PipelineConfig
(over a --config file and --set), MedeaConfig (over a shipped preset), FusionOptions,
mvs_core.MvsConfig, PolishConfig and the pose options; the device, the Rerun mode, and the
`recon run` command line that makes a config (``command_line``). The arguments themselves
are recon.commands.cli_args' (its parser is passed in where a bare run's settings are
needed, so that this module does not import it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from medea_core import MedeaConfig

from ..choices import RERUN_MODES
from ..errors import ReconInputError


def medea_config_from_args(args: argparse.Namespace) -> MedeaConfig:
    config = preset_medea(args.preset)
    for name in ("image_scale", "batch_pairs", "pixel_stride", "feature_stride", "feature_channels", "feature_loss"):
        if getattr(args, name) is not None:
            setattr(config, name, getattr(args, name))
    if args.stage1_epochs is not None:
        config.stage1.epochs = args.stage1_epochs
    if args.stage2_epochs is not None:
        config.stage2.epochs = args.stage2_epochs
    if args.lr is not None:
        config.stage1.lr = config.stage2.lr = args.lr
    config.run_stage1 = not args.no_stage1
    config.run_stage2 = not args.no_stage2
    config.propagate_scale = not args.no_propagation
    config.use_photometric = not args.no_photometric
    config.use_depth = not args.no_depth_loss
    config.use_features = not args.no_feature_loss
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


def fusion_options_from_args(args: argparse.Namespace):
    from ..fusion import FusionOptions

    return FusionOptions(
        voxel_size=args.voxel_size, trunc=args.trunc, max_depth=args.max_depth, weight_threshold=args.weight_threshold,
        min_fragment_triangles=args.min_fragment, block_count=args.block_count, point_cloud=args.point_cloud,
        min_confidence=args.min_confidence, max_triangles=args.max_triangles,
    )


def polish_config_from_args(args: argparse.Namespace):
    from dataclasses import replace

    from ..options import parse_field_option
    from ..poses.given.polish import PolishConfig

    values = dict(parse_field_option(text, PolishConfig, "polish option") for text in args.polish_option)
    return replace(PolishConfig(), **values)


def mvs_config_from_args(args: argparse.Namespace):
    from dataclasses import replace

    from mvs_core import MvsConfig

    from ..options import parse_field_option

    values = dict(parse_field_option(text, MvsConfig, "refine option") for text in args.refine_option)
    config = replace(MvsConfig(), **values)
    try:
        config.validate()
    except ValueError as error:
        raise ReconInputError(f"--refine-option: {error}") from None
    return config


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
    """The PipelineConfig the parsed flags of `recon run` make."""
    from ..pipeline import PipelineConfig

    medea = medea_config_from_args(args)
    mode, path = rerun_mode(args, default_rerun_mode())
    return PipelineConfig(
        input=Path(args.input), output=Path(args.output), overwrite=args.overwrite, stride=args.stride,
        max_frames=args.max_frames, start_time=args.start_time, end_time=args.end_time, frame_budget=args.frame_budget,
        stream=args.stream, depth_frames=args.depth_frames, depth_motion=args.depth_motion,
        depth_rotation=args.depth_rotation, window=args.window, window_overlap=args.window_overlap,
        mesh_every=args.mesh_every,
        width=args.width or None, fps=args.fps,
        intrinsics=_numbers(args.intrinsics, 4, "--intrinsics") if args.intrinsics else None, fov=args.fov,
        distortion=_numbers(args.distortion, (4, 5), "--distortion") if args.distortion else None,
        rolling_shutter=args.rolling_shutter,
        poses=args.poses, pose_method=args.pose_method, pose_options=pose_options_from_args(args),
        on_break=args.on_break, join_segments=args.join_segments,
        prior=args.prior, prior_path=args.prior_path, prior_align=args.prior_align,
        weights=args.weights, features=not args.no_features, adjust=not args.no_medea, medea=medea,
        refine=args.refine, mvs=mvs_config_from_args(args),
        polish=args.polish, polish_config=polish_config_from_args(args),
        medea_gate=args.medea_gate,
        fusion=fusion_options_from_args(args), rerun=mode, rerun_path=path, device=medea.device,
        progress=not args.quiet, depth_npy=not args.no_npy, glb=not args.no_glb,
    )


def default_rerun_mode() -> str:
    from viewer import default_mode

    return default_mode()
