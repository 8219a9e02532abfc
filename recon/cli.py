"""The `recon` command line.

Bad input raises ReconInputError anywhere below; `main` prints its single line and exits
with code 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys

import torch

from medea_core import MedeaConfig

from .errors import ReconInputError


def add_medea_arguments(parser: argparse.ArgumentParser) -> None:
    """Options mirroring MedeaConfig. Unset options keep the preset's value."""
    d = MedeaConfig()
    g = parser.add_argument_group("MEDeA depth adjustment")
    g.add_argument("--preset", choices=["paper", "fast"], default="paper",
                   help="paper: the paper's settings (default); fast: pixel stride 2 and Stage II lr 0.01, "
                        "about 4x faster at equal accuracy on our benchmarks")
    g.add_argument("--image-scale", type=float, help=f"working resolution relative to the input (paper {d.image_scale})")
    g.add_argument("--batch-pairs", type=int, help=f"frame pairs per optimiser step (paper {d.batch_pairs})")
    g.add_argument("--pixel-stride", type=int, help="score every k-th pixel per step (paper 1)")
    g.add_argument("--stage1-epochs", type=int, help=f"max epochs of Stage I, keyframes (paper {d.stage1.epochs})")
    g.add_argument("--stage2-epochs", type=int, help=f"max epochs of Stage II, all frames (paper {d.stage2.epochs})")
    g.add_argument("--lr", type=float, help=f"Adam learning rate of both stages (paper {d.stage1.lr})")
    g.add_argument("--no-stage1", action="store_true", help="skip Stage I (then Stage II optimises every frame)")
    g.add_argument("--no-stage2", action="store_true", help="skip Stage II")
    g.add_argument("--no-propagation", action="store_true", help="start Stage II from scale 1 instead of the keyframes' scale")
    g.add_argument("--no-photometric", action="store_true", help="drop the photometric loss")
    g.add_argument("--no-depth-loss", action="store_true", help="drop the depth consistency loss")
    g.add_argument("--no-feature-loss", action="store_true", help="drop the feature-metric loss")
    g.add_argument("--feature-loss", choices=["S", "M"], help="S: normalised L1 (MEDeA-S, paper default), M: dot product (MEDeA-M)")
    g.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")


def medea_config_from_args(args: argparse.Namespace) -> MedeaConfig:
    config = MedeaConfig.fast() if args.preset == "fast" else MedeaConfig()
    for name in ("image_scale", "batch_pairs", "pixel_stride", "feature_loss"):
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


def resolve_device(name: str) -> str:
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ReconInputError(f"--device {name}: CUDA is not available on this machine (use --device cpu)")
    return name


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import format_report, run_synthetic_demo

    config = medea_config_from_args(args)
    print(f"recon demo: rendering a synthetic room ({args.frames} frames, {args.width}x{args.height}), "
          f"simulating a monocular prior, adjusting it with MEDeA on {config.device}")
    report = run_synthetic_demo(args.frames, args.width, args.height, args.scene_seed, config, progress=not args.quiet)
    print(format_report(report))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="recon",
        description="Video to multi-view-consistent metric depth (MEDeA) and a mesh.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the built-in synthetic sample and report depth error before/after MEDeA")
    demo.add_argument("--frames", type=int, default=120, help="number of rendered frames (default %(default)s)")
    demo.add_argument("--width", type=int, default=640)
    demo.add_argument("--height", type=int, default=480)
    demo.add_argument("--scene-seed", type=int, default=0, help="seed of the synthetic scene and prior")
    demo.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default %(default)s)")
    demo.add_argument("--quiet", action="store_true", help="no progress bars")
    add_medea_arguments(demo)
    demo.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ReconInputError as error:
        print(f"recon: error: {error}", file=sys.stderr)
        return ReconInputError.exit_code
    except KeyboardInterrupt:
        print("recon: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
