"""The `recon` command line's arguments: the parser (`build_parser`: the sub-commands run,
batch, demo, view, eval and export). The flags of `recon run` that set a setting are made
from recon.commands.cli_config.RUN_FLAGS, their help from the settings' field docstrings;
every other setting is reached with --set or --config. Named choices come from
recon.choices; turning parsed arguments into configs is recon.commands.cli_config's,
running them recon.commands.cli's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..choices import DEMO_PRIORS, DEVICE_SPELLINGS, POSE_CHOICES
from .cli_config import RUN_FLAGS, Flag, bare_config, setting_field


def flag_help(flag: Flag) -> str:
    """The help of `flag`: its setting's field summary (recon.options.field_summary), with
    the default for a flag that takes a value, and what an inverting flag (--no-X) does."""
    from ..core.config_file import setting_default
    from ..options import field_summary

    owner, name = setting_field(flag.setting)
    text = field_summary(owner, name).replace("%", "%%")
    action = flag.parse.get("action")
    if action == "store_false" or (action == "store_true" and flag.convert is not None):
        return f"{text} This flag turns it off ({flag.setting}=false)."
    if action is None and setting_default(flag.setting) is not None:
        return f"{text} Default: %(default)s."
    return text


def _add_flag(group, flag: Flag) -> None:
    from ..core.config_file import setting_default

    extra = {} if "action" in flag.parse else {"default": setting_default(flag.setting)}
    group.add_argument(flag.option, help=flag_help(flag), **extra, **flag.parse)


def add_medea_arguments(parser: argparse.ArgumentParser, preset: str = "fast") -> None:
    """--preset (MEDeA's settings from a shipped config file) and --no-medea."""
    from ..core.config_file import PRESETS, preset_names

    g = parser.add_argument_group("MEDeA depth adjustment", "docs/depth.md; every MEDeA setting: --set medea.NAME")
    g.add_argument("--preset", choices=preset_names(), default=preset,
                   help=f"MEDeA's settings from a shipped config file, {PRESETS.name}/NAME.yaml: fast, about 2x "
                        "faster than the paper's at equal accuracy, or paper (default %(default)s).")
    _add_flag(g, Flag("--no-medea", "adjust", {"action": "store_true"}, convert=lambda no: not no))


# --------------------------------------------------------------------------- shared options


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="auto", help=f"{DEVICE_SPELLINGS} (default %(default)s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def add_rerun_argument(parser: argparse.ArgumentParser, default: str | None, what: str) -> None:
    default_text = default or "spawn when a display is available, else off"
    parser.add_argument(
        "--rerun", nargs="+", metavar="MODE", default=None,
        help=f"Rerun inspection of {what}: spawn (desktop viewer), save [PATH.rrd] (default OUT/recording.rrd), "
             f"serve (web viewer on localhost; waits until Ctrl-C), off (default: {default_text})",
    )


# --------------------------------------------------------------------------- recon run


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `recon run` (and `recon batch`) that make its PipelineConfig: --config,
    --set, and a group per stage of the flags of RUN_FLAGS, with --pose-option among the poses'."""
    parser.add_argument("--config", type=Path, metavar="FILE",
                        help="Settings from a YAML or JSON file, a section per stage as in report.json's options "
                             "(or a report.json, to run a result again); flags given with other values than their "
                             "defaults override it. docs/running.md#settings-in-a-file---config---preset---set")
    parser.add_argument("--set", action=_SetAction, metavar="NAME=VALUE", default=[], dest="settings",
                        help="One setting by its dotted name, over the flags and --config (repeatable), e.g. "
                             "--set medea.stage1.epochs=200; `--set list` prints every name with its type and "
                             "default.")
    for title, docs, flags in RUN_FLAGS:
        g = parser.add_argument_group(title, docs)
        for flag in flags:
            _add_flag(g, flag)
        if title == "poses":
            add_pose_option_argument(g)


class _ListableAction(argparse.Action):
    """Collects the values of a repeatable KEY=VALUE option; `list` prints the settings it takes
    (``heading``, then ``table()``) and exits while parsing, as --help does, so that it needs
    no input or output folder."""

    heading = ""

    def table(self, parser: argparse.ArgumentParser) -> str:
        """parser: the (sub)command's parser this option belongs to."""
        raise NotImplementedError

    def __call__(self, parser, namespace, values, option_string=None):
        if values == "list":
            print(self.heading)
            print(self.table(parser))
            parser.exit()
        # Not append: the default list would be shared between parses.
        setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), values])


class _PoseOptionAction(_ListableAction):
    heading = ("pose options (--pose-option KEY=VALUE): name, type, default, config, and below each what it "
               "does (recon.poses.config.FrontendConfig, recon.poses.sfm.mapper.SfMConfig)")

    def table(self, parser: argparse.ArgumentParser) -> str:
        from ..poses.options import pose_option_table

        return pose_option_table()


class _SetAction(_ListableAction):
    heading = "settings (--set NAME=VALUE, and the names of a --config file's sections): name, type, default"

    def table(self, parser: argparse.ArgumentParser) -> str:
        from ..core.config_file import settings_listing
        # A bare `recon run IN -o OUT`'s settings (also for `recon batch`, whose parser has no IN).
        return settings_listing(bare_config(build_parser(), "IN", "OUT"))


def add_pose_option_argument(parser) -> None:
    parser.add_argument("--pose-option", action=_PoseOptionAction, default=[], metavar="KEY=VALUE",
                        help="Change a pose estimator setting, e.g. keyframe_flow=12 (repeatable); `--pose-option "
                             "list` prints them. docs/poses.md#settings---pose-option")


# --------------------------------------------------------------------------- parser

RUN_EXAMPLES = """examples:
  recon run my_video.mp4 -o out/                       phone video, FastDepth prior, estimated poses
  recon run my_video.mp4 -o out/ --fov 70 --stride 2   known field of view, every 2nd frame
  recon run frames/ -o out/ --poses poses.txt          image folder with a TUM trajectory
  recon run rgbd_dataset_freiburg1_desk/ -o out/ --prior sensor --poses gt
  recon run my_video.mp4 -o out/ --prior hf --prior-path models/depth-anything-small
                                                       a local Hugging Face depth model (aligned to FastDepth)
  recon run my_video.mp4 -o out/ --rerun save          also write out/recording.rrd
  recon view out/                                      inspect the result in Rerun

Every setting, with a flag or without one (MEDeA's ablations, the streaming and TSDF internals,
the refinement's and the polish's settings), is reached with --set NAME=VALUE or --config FILE;
`recon run --set list` names them all. docs/running.md#settings-in-a-file---config---preset---set
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="recon",
        description="Video to multi-view-consistent metric depth (MEDeA) and a mesh. "
                    "Start with `recon demo`, then `recon run YOUR_VIDEO -o OUT`.",
    )
    sub = parser.add_subparsers(dest="command", required=True)  # the metavar lists every sub-command

    run = sub.add_parser(
        "run", help="video / image folder / RGB-D dataset -> depth maps, camera trajectory and mesh",
        description="Run the whole pipeline: decode frames, depth prior, camera poses, MEDeA depth adjustment, "
                    "TSDF fusion, export (mesh.ply, mesh.glb, trajectory.txt, intrinsics.json, depth/, report.json) "
                    "and optional Rerun logging.",
        epilog=RUN_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("input", help="video file (mp4, mov, avi, mkv, ...), image folder, or RGB-D dataset folder "
                                   "(TUM, 7-Scenes, ScanNet export, ARKitScenes, Open3D/Redwood)")
    run.add_argument("-o", "--output", required=True, help="output folder (must be empty unless --overwrite)")
    run.add_argument("--overwrite", action="store_true", help="write into a non-empty output folder")
    add_rerun_argument(run, None, "the run")
    run.add_argument("--export", metavar="FORMATS",
                     help="when the run is done, export the output folder for other tools: colmap, nerfstudio or "
                          "colmap,nerfstudio, into OUT/colmap/ and OUT/nerfstudio/ (as `recon export OUT --to ...`)")
    add_device_arguments(run)
    add_run_arguments(run)
    add_medea_arguments(run)

    batch = sub.add_parser(
        "batch", help="many videos / folders -> one output folder each, run in parallel on Ray",
        description="Run the pipeline on every input as a Ray task (a local Ray instance, or a cluster joined with "
                    "--address): OUT/<input name without suffix>/ per input, one line per input as it finishes "
                    "(the node that ran it, the count, the time left), a summary table and OUT/batch.json "
                    "(rewritten as each input finishes). Inputs whose output is complete (report.json) are skipped, "
                    "so running the same command again resumes; a failed input does not stop the others (exit code "
                    "2 when any failed); an input whose node leaves the cluster is run again on another. The run "
                    "options are those of `recon run`, the same for every input. On a cluster, the inputs and the "
                    "output folder must be paths every node sees (a shared file system): each node is checked "
                    "before any input runs. Needs Ray: pip install -e .[batch].",
    )
    batch.add_argument("inputs", nargs="+", metavar="INPUT",
                       help="video files, image folders or RGB-D dataset folders (as for `recon run`)")
    batch.add_argument("-o", "--output", required=True,
                       help="folder of the results: OUT/<input name>/ per input (a name taken by an earlier input "
                            "gets -2, -3, ...), OUT/batch.json; on a cluster a path every node sees and can write "
                            "(a shared file system, or object storage mounted at the same path on every node)")
    batch.add_argument("--address", help="join this Ray cluster (auto: the one `ray start` made here; HOST:6379; "
                                         "ray://HOST:10001); default: start a local Ray instance")
    batch.add_argument("--num-cpus", type=int, help="CPUs of the local Ray instance (default: all of this machine's)")
    batch.add_argument("--cpus-per-task", type=int, default=2,
                       help="CPUs Ray reserves for each input, and torch's threads in it (default %(default)s)")
    batch.add_argument("--gpus-per-task", type=float,
                       help="GPUs Ray reserves for each input, may be a fraction (default: 1 with --device cuda, "
                            "else 0)")
    batch.add_argument("--memory-per-task", type=float, metavar="GB", default=3.0,
                       help="memory Ray reserves for each input, so that no more inputs share a node than fit in "
                            "its memory (default %(default)s: a one-shot run of 100 frames at 640x480; longer inputs "
                            "stream within --frame-budget; 0: none reserved)")
    batch.add_argument("--node-retries", type=int, default=2, metavar="N",
                       help="times an input whose node left the cluster is run again on another node (default "
                            "%(default)s; an input whose worker died on a live node is reported failed)")
    batch.add_argument("--save-recording", action="store_true",
                       help="write OUT/<name>/recording.rrd for each input (Rerun is otherwise off)")
    add_device_arguments(batch)
    add_run_arguments(batch)
    add_medea_arguments(batch)

    demo = sub.add_parser(
        "demo", help="render a synthetic room as a video, run `recon run` on it, score it against ground truth",
        description="The built-in sample: renders a textured synthetic room to OUT/input/synthetic.mp4 with a "
                    "simulated monocular prior and the true trajectory, runs the pipeline on it, and prints the "
                    "depth error before/after MEDeA and the mesh F-score against the ground-truth mesh.",
    )
    demo.add_argument("-o", "--output", type=Path, help="output folder (default demo_out/<date-time>)")
    demo.add_argument("--overwrite", action="store_true", help="write into a non-empty output folder")
    demo.add_argument("--frames", type=int, default=90, help="number of rendered frames (default %(default)s)")
    demo.add_argument("--width", type=int, default=640, help="rendered width (default %(default)s)")
    demo.add_argument("--height", type=int, default=480, help="rendered height (default %(default)s)")
    demo.add_argument("--scene-seed", type=int, default=0, help="seed of the synthetic scene and prior")
    demo.add_argument("--seed", type=int, help="MEDeA's random seed (default: the preset's)")
    demo.add_argument("--poses", choices=POSE_CHOICES, default="auto",
                      help="estimate (pose front end), gt (rendered trajectory), auto: estimate when the estimator "
                           "is installed, else gt with a note (default %(default)s)")
    add_pose_option_argument(demo)
    demo.add_argument("--prior", choices=DEMO_PRIORS, default="simulated",
                      help="simulated: ground truth distorted like a monocular network (default); fastdepth: the "
                           "real network")
    demo.add_argument("--no-compare", action="store_true", help="skip fusing the raw prior for the F-score comparison")
    add_rerun_argument(demo, "save", "the demo")
    add_device_arguments(demo)
    add_medea_arguments(demo)

    view = sub.add_parser(
        "view", help="open a result in Rerun",
        description="Open OUT/recording.rrd (or an .rrd file) in the Rerun viewer; for an output folder without a "
                    "recording, log its mesh, cameras and depth maps.",
    )
    view.add_argument("path", help="output folder of `recon run` or an .rrd file")
    view.add_argument("--overwrite", action="store_true", help="replace an existing file given to --rerun save")
    add_rerun_argument(view, "spawn with a display, else serve", "the result")
    view.add_argument("--quiet", action="store_true", help="no progress bars")
    view.add_argument("--bind", default="127.0.0.1",
                      help="address the web viewer (serve) listens on (default %(default)s, this machine only; "
                           "0.0.0.0 for every interface)")

    ev = sub.add_parser(
        "eval", help="score an output folder against a dataset's ground truth",
        description="Depth (metric and median-scaled, DeepVideoMVS protocol), trajectory (ATE SE(3)/Sim(3), RPE, "
                    "scale error) and mesh (accuracy, completeness, chamfer, precision, recall, F-score) of an "
                    "output folder of `recon run`, against the dataset it was made from. Prints tables and writes "
                    "OUT/eval.json.",
    )
    ev.add_argument("output", help="output folder of `recon run`")
    ev.add_argument("--gt", required=True,
                    help="dataset folder with ground truth (TUM, 7-Scenes, ScanNet, ARKitScenes, Redwood)")
    ev.add_argument("--min-depth", type=float, default=1e-3,
                    help="evaluated ground-truth depth range, metres (default %(default)s)")
    ev.add_argument("--max-depth", type=float, default=10.0, help="(default %(default)s)")
    ev.add_argument("--threshold", type=float, default=0.05,
                    help="mesh precision/recall distance, metres (default %(default)s)")
    ev.add_argument("--reference-mesh", type=Path, help="compare with this mesh instead of a TSDF of the sensor depth")
    ev.add_argument("--mesh-align", choices=["auto", "none", "se3", "sim3", "sim3+icp"], default="auto",
                    help="bring the mesh into the ground truth's frame first; auto: Sim(3) from the trajectory "
                         "when the poses were estimated, none for ground-truth poses; sim3+icp: that Sim(3), then "
                         "ICP with a scale onto the reference surface (Tanks and Temples' protocol)")
    ev.add_argument("--overwrite", action="store_true", help="replace an existing OUT/eval.json")
    ev.add_argument("--quiet", action="store_true", help="no progress bars")
    add_export_parser(sub)
    return parser


def add_export_parser(sub) -> None:
    """`recon export OUT --to colmap|nerfstudio`: the options of recon.export.tools.ExportOptions
    (checked there; importing it here would load Open3D for every command's --help)."""
    ex = sub.add_parser(
        "export", help="an output folder -> a COLMAP model or a nerfstudio dataset, for other tools",
        description="Export an output folder of `recon run` for other tools: a COLMAP text model (images/, "
                    "sparse/0/cameras.txt, images.txt, points3D.txt) and a nerfstudio dataset (transforms.json, "
                    "images/, depth/ 16-bit millimetre PNGs, points.ply). The frames are decoded again from the "
                    "run's input (report.json input.path, or --input) at the size of the depth maps, resampled as "
                    "the run resampled them; the points are the mesh's vertices. A run written as segments is "
                    "exported segment by segment. docs/export.md has the conventions.",
    )
    ex.add_argument("output", help="output folder of `recon run`")
    ex.add_argument("--to", action="append", required=True, metavar="FORMAT",
                    help="colmap or nerfstudio; repeat, or separate with commas, for both")
    ex.add_argument("-o", "--dest", type=Path, metavar="DEST",
                    help="folder that receives <format>/ (default: the output folder: OUT/colmap/, OUT/nerfstudio/)")
    ex.add_argument("--overwrite", action="store_true", help="replace an existing export")
    ex.add_argument("--max-points", type=int, metavar="N",
                    help="most 3D points: a fixed random subset of the mesh's vertices when it has more "
                         "(default 100000)")
    ex.add_argument("--image-format", metavar="{jpg,png}", help="jpg (quality 95, default) or png (lossless)")
    ex.add_argument("--input", type=Path, metavar="PATH",
                    help="where the run's input (video, image folder, dataset) is now, when it has moved")
    ex.add_argument("--quiet", action="store_true", help="no progress bars")
