"""The `recon` command line's arguments: the parser (`build_parser`: the sub-commands run,
batch, demo, view, eval and export) and its option groups mirroring the typed configs
(recon.pipeline.PipelineConfig, MedeaConfig, FusionOptions, mvs_core.MvsConfig, the pose
options). Named choices come from recon.choices; turning parsed arguments into those
configs is recon.commands.cli_config's, running them recon.commands.cli's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from medea_core import MedeaConfig

from ..choices import (
    DEMO_PRIORS,
    DEVICE_SPELLINGS,
    ON_BREAK_CHOICES,
    POSE_CHOICES,
    POSE_METHODS,
    PRIOR_ALIGN_CHOICES,
    PRIOR_CHOICES,
    REFINE_CHOICES,
    STREAM_CHOICES,
)
from .cli_config import config_from_flags


def add_medea_arguments(parser: argparse.ArgumentParser, preset: str = "fast") -> None:
    """Options mirroring MedeaConfig. Unset options keep the preset's value."""
    d, fast = MedeaConfig(), MedeaConfig.fast()
    g = parser.add_argument_group("MEDeA depth adjustment")
    from ..core.config_file import PRESETS, preset_names

    g.add_argument("--preset", choices=preset_names(), default=preset,
                   help=f"MEDeA's settings from a shipped config file ({PRESETS.name}/NAME.yaml beside "
                        f"recon/core/config_file.py; the flags below change them): paper, the paper's; fast, pixel "
                        f"stride {fast.pixel_stride}, Stage II lr {fast.stage2.lr:g} and Stage I at most "
                        f"{fast.stage1.epochs} epochs, about 2x faster at equal accuracy on our benchmarks "
                        "(default %(default)s)")
    g.add_argument("--no-medea", action="store_true", help="skip MEDeA: fuse the raw depth prior")
    g.add_argument("--image-scale", type=float,
                   help=f"working resolution relative to the input (paper {d.image_scale})")
    g.add_argument("--batch-pairs", type=int, help=f"frame pairs per optimiser step (paper {d.batch_pairs})")
    g.add_argument("--pixel-stride", type=int, help="score every k-th pixel per step (paper 1)")
    g.add_argument("--feature-stride", type=int, help="the same on the feature grid (paper 1)")
    g.add_argument("--feature-channels", type=int,
                   help="keep only the N most varying feature channels (paper: all); warping cost grows with N")
    g.add_argument("--stage1-epochs", type=int, help=f"max epochs of Stage I, keyframes (paper {d.stage1.epochs}, "
                                                       f"fast preset {fast.stage1.epochs})")
    g.add_argument("--stage2-epochs", type=int, help=f"max epochs of Stage II, all frames (paper {d.stage2.epochs})")
    g.add_argument("--lr", type=float, help=f"Adam learning rate of both stages (paper {d.stage1.lr})")
    g.add_argument("--no-stage1", action="store_true", help="skip Stage I (then Stage II optimises every frame)")
    g.add_argument("--no-stage2", action="store_true", help="skip Stage II")
    g.add_argument("--no-propagation", action="store_true",
                   help="start Stage II from scale 1 instead of the keyframes' scale")
    g.add_argument("--no-photometric", action="store_true", help="drop the photometric loss")
    g.add_argument("--no-depth-loss", action="store_true", help="drop the depth consistency loss")
    g.add_argument("--no-feature-loss", action="store_true", help="drop the feature-metric loss")
    g.add_argument("--feature-loss", choices=["S", "M"],
                   help="S: normalised L1 (MEDeA-S, paper default), M: dot product (MEDeA-M)")
    g.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")


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
    from ..fusion import FusionOptions, tsdf
    from ..pipeline import PipelineConfig

    d, fd = PipelineConfig(Path(), Path()), FusionOptions()
    g = parser.add_argument_group("frames")
    g.add_argument("--stride", type=int, help="use every k-th frame (default: 1, raised to stay within --frame-budget)")
    g.add_argument("--max-frames", type=int, help="use at most this many frames")
    g.add_argument("--start", type=float, dest="start_time", help="first second of the video to use")
    g.add_argument("--end", type=float, dest="end_time", help="stop at this second of the video")
    g.add_argument("--frame-budget", type=int, default=d.frame_budget,
                   help="the most frames a one-shot run holds in memory, counted at 640x480 (larger frames count "
                        "for more; 150 holds a one-shot run to about 3 GB); longer inputs are streamed (see "
                        "--stream) (default %(default)s)")
    g.add_argument("--stream", choices=STREAM_CHOICES, default=d.stream,
                   help="stream the frames through the stages in bounded memory, MEDeA on overlapping windows, the "
                        "mesh growing as it goes: auto = when the input has more frames than --frame-budget, and "
                        "for a video whose poses are estimated (depth for the frames the camera moved to reach; "
                        "run again at once, where SfM can be tried, if the front end loses the camera); off gives "
                        "every frame depth and raises the stride to fit the budget (default %(default)s)")
    g.add_argument("--depth-frames", default=d.depth_frames, metavar="{motion,all,K}",
                   help="streamed runs: the tracked frames that get depth and are fused: motion = one each time the "
                        f"camera moved {d.depth_motion:g} x the median depth or turned {d.depth_rotation:g} degrees, "
                        "all, or every K-th (default %(default)s)")
    g.add_argument("--depth-motion", type=float, default=d.depth_motion,
                   help="streamed runs, --depth-frames motion: the camera's movement that takes a frame, as a fraction "
                        "of the median depth (default %(default)s)")
    g.add_argument("--depth-rotation", type=float, default=d.depth_rotation,
                   help="streamed runs, --depth-frames motion: the turn in degrees that takes a frame "
                        "(default %(default)s)")
    g.add_argument("--window", type=int, default=d.window,
                   help="streamed runs: frames per MEDeA window, counted at 640x480 like --frame-budget (default "
                        "%(default)s)")
    g.add_argument("--window-overlap", type=int, default=d.window_overlap,
                   help="streamed runs: frames shared by consecutive windows (default %(default)s)")
    g.add_argument("--mesh-every", type=int, default=d.mesh_every,
                   help="streamed runs: re-extract the mesh for live Rerun every this many fused frames; 0 = only at "
                        "the end (default %(default)s)")
    g.add_argument("--width", type=int, default=d.width,
                   help="working width in pixels, aspect kept; 0 keeps the input's size (default %(default)s)")
    g.add_argument("--fps", type=float, help="frame rate of an image folder (default 30), for --start/--end")

    g = parser.add_argument_group("camera")
    g.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="pinhole intrinsics in pixels of the input as decoded (pixel centres at integers)")
    g.add_argument("--fov", type=float, help="horizontal field of view in degrees (when intrinsics are unknown)")
    g.add_argument("--distortion", metavar="K1,K2,P1,P2[,K3]",
                   help="the lens' distortion, OpenCV's model, for the camera of --intrinsics or --fov (default: "
                        "a dataset's published coefficients with its calibration, else none); the frames are "
                        "resampled into the pinhole camera before any other stage")
    g.add_argument("--rolling-shutter", type=float, default=d.rolling_shutter, metavar="MS",
                   help="the camera's rolling-shutter readout time in milliseconds (phones and webcams: about 10-30; "
                        "0: a global shutter, default). Each frame is resampled to one instant with the camera's "
                        "turn rate from the poses (estimated poses: estimated again on the resampled frames, "
                        "so such a video is not streamed by --stream auto; a streamed run applies it to given "
                        "poses only)")

    g = parser.add_argument_group("poses")
    g.add_argument("--poses", default="auto", metavar="{%s}|PATH" % ",".join(POSE_CHOICES),
                   help="auto (dataset ground truth if any, else estimate), gt, estimate, or a pose file/folder "
                        "(TUM, COLMAP, nerfstudio transforms.json, per-frame 4x4 matrices, Open3D .log); "
                        "default %(default)s")
    g.add_argument("--pose-method", choices=POSE_METHODS, default=d.pose_method,
                   help="pose estimator (default %(default)s)")
    g.add_argument("--on-break", choices=ON_BREAK_CHOICES, default=d.on_break,
                   help="where an estimated trajectory's scale breaks or the camera is lost (report.json "
                        "poses.scale_watch): segments (tracking starts again where the camera was lost; each "
                        "stretch reconstructed on its own in OUT/segment_NN/), stop (one line naming the "
                        "frames, exit 2) or keep (one trajectory, warned); keep also returns a trajectory the "
                        "front end's motion checks distrust (poses.motion_checks). A metric scale the depth prior "
                        "cannot vouch for because its depth does not follow the scene's (a close-up, an outdoor "
                        "view: poses.metric_scale) is written and marked, except under stop, which refuses it. "
                        "Default %(default)s")
    g.add_argument("--no-join", dest="join_segments", action="store_false",
                   help="do not try to join the stretches on either side of a scale break (by ORB matches and "
                        "PnP across it) before --on-break applies")
    add_pose_option_argument(g)

    g = parser.add_argument_group("depth prior")
    g.add_argument("--prior", choices=PRIOR_CHOICES, default=d.prior,
                   help="fastdepth (network, default), sensor (an RGB-D dataset's depth), folder (depth maps in "
                        "--prior-path), hf (a local Hugging Face depth model in --prior-path; needs transformers: "
                        "pip install -e .[hf])")
    g.add_argument("--prior-path", type=Path, metavar="PATH",
                   help="folder: one depth map per frame (.npy/.png/.exr/.tiff, metres; 16-bit PNG in millimetres; "
                        "0, NaN and inf: no depth), matched by frame name. hf: the model folder (config.json, "
                        "weights, preprocessor_config.json, as save_pretrained writes them); nothing is downloaded")
    g.add_argument("--prior-align", choices=PRIOR_ALIGN_CHOICES, default=d.prior_align,
                   help="hf: a model that predicts affine-invariant disparity (DPT/MiDaS, relative Depth Anything; "
                        "read from its config.json) is fitted per frame (scale and shift) to the metric depth of "
                        "fastdepth (FastDepth on the same frames, --weights) or sensor (an RGB-D dataset's depth); "
                        "metric models (ZoeDepth, GLPN, Depth Pro, metric Depth Anything) are used as they are "
                        "(default %(default)s)")
    g.add_argument("--weights", type=Path, help="FastDepth weights (model.json, .npz or a folder); default: "
                                                "$RECON_WEIGHTS, then the model packaged with recon")
    g.add_argument("--no-features", action="store_true", help="do not give MEDeA the prior's encoder features")

    g = parser.add_argument_group("multi-view stereo refinement (after MEDeA)")
    g.add_argument("--refine", choices=REFINE_CHOICES, default=d.refine,
                   help="mvs: per-pixel depth from the frames around MEDeA's depth, with a confidence; only the "
                        "pixels it reconstructs are fused. none: MEDeA's depth, the paper's pipeline "
                        "(default %(default)s)")
    g.add_argument("--refine-option", action=_RefineOptionAction, default=[], metavar="KEY=VALUE",
                   help="change a refinement setting (mvs_core.MvsConfig), e.g. num_sources=4, hypotheses=16 "
                        "(repeatable); `--refine-option list` prints every setting with its default")
    polish = g.add_mutually_exclusive_group()
    polish.add_argument("--polish", action="store_true",
                        help="polish given poses (dataset, pose file) against the frames before MEDeA when refining "
                             "(recon.poses.given.polish; one-shot runs); off by default: given poses are used as given")
    polish.add_argument("--no-polish", action="store_true",
                        help="use given poses as they are (the default; kept for scripts that say so)")
    g.add_argument("--polish-option", action=_PolishOptionAction, default=[], metavar="KEY=VALUE",
                   help="change a setting of the polish (recon.poses.given.polish.PolishConfig), "
                        "e.g. calibrate_lens=true (repeatable); `--polish-option list` prints every setting with its "
                        "default")
    gate = g.add_mutually_exclusive_group()
    gate.add_argument("--medea-gate", action="store_true",
                      help="skip MEDeA, and refine from the prior's depth, when the given poses contradict the "
                           "frames (every run with given poses checks them and warns; off by default: on TUM's "
                           "motion capture it made the mesh better and the depth worse)")
    gate.add_argument("--no-medea-gate", action="store_true", help="run MEDeA whatever the check says (the default)")

    g = parser.add_argument_group("TSDF fusion")
    g.add_argument("--voxel-size", type=float,
                   help=f"metres (default: median depth / {1 / tsdf.VOXEL_PER_DEPTH:g}, clamped to "
                        f"{tsdf.MIN_VOXEL * 1000:g} mm - {tsdf.MAX_VOXEL * 100:g} cm)")
    g.add_argument("--trunc", type=float, help=f"truncation in metres (default {fd.trunc_voxels:g} voxels)")
    g.add_argument("--max-depth", type=float,
                   help=f"ignore depth beyond this many metres (default: {tsdf.MAX_DEPTH_MARGIN:g} x the "
                        f"{tsdf.MAX_DEPTH_PERCENTILE:g}th percentile)")
    g.add_argument("--weight-threshold", type=float, default=fd.weight_threshold,
                   help="frames that must see a voxel for it to be meshed (default %(default)s)")
    g.add_argument("--min-fragment", type=int, default=fd.min_fragment_triangles,
                   help="drop mesh pieces with fewer triangles (default %(default)s; 0 keeps all)")
    g.add_argument("--block-count", type=int, default=fd.block_count,
                   help="memory budget in voxel blocks (10 KiB each); the voxel grows to fit (default %(default)s)")
    g.add_argument("--min-confidence", type=float, default=fd.min_confidence,
                   help="with the refinement, fuse only pixels of at least this confidence (reconstructed pixels: "
                        "the share of source views that agree, >= 1/3; filled pixels: 0.1 x the share of "
                        "reconstructed pixels around them; 0 fuses all). Default: 0.1 (reconstructed pixels only) "
                        "with given poses, 0.01 (also filled pixels near evidence) with estimated poses")
    g.add_argument("--max-triangles", type=int, default=fd.max_triangles,
                   help="the mesh's triangle budget: a larger mesh is thinned (vertex clustering, colours "
                        "kept) to 80-100 %% of this many triangles (default %(default)s; 0 keeps the full mesh)")
    g.add_argument("--point-cloud", action="store_true", help="also write point_cloud.ply")

    g = parser.add_argument_group("output")
    g.add_argument("--no-npy", action="store_true", help="write depth maps as 16-bit PNG only (no float .npy)")
    g.add_argument("--no-glb", action="store_true", help="do not write mesh.glb")


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
    heading = ("pose options (--pose-option KEY=VALUE): name, type, default, config; their meaning is in the "
               "docstrings of recon.poses.frontend.streaming.FrontendConfig and recon.poses.sfm.mapper.SfMConfig")

    def table(self, parser: argparse.ArgumentParser) -> str:
        from ..poses.options import pose_option_table

        return pose_option_table()


class _SetAction(_ListableAction):
    heading = "settings (--set NAME=VALUE, and the names of a --config file's sections): name, type, default"

    def table(self, parser: argparse.ArgumentParser) -> str:
        from ..core.config_file import settings_listing
        # A bare `recon run IN -o OUT`'s settings, parsed by the run command's own parser.
        return settings_listing(config_from_flags(parser.parse_args(["IN", "-o", "OUT"])))


class _FieldOptionAction(_ListableAction):
    """The KEY=VALUE options of one config's fields: subclasses name the config (``config()``)."""

    @staticmethod
    def config():
        raise NotImplementedError

    def table(self, parser: argparse.ArgumentParser) -> str:
        from ..options import option_table

        return option_table(self.config())


class _RefineOptionAction(_FieldOptionAction):
    heading = ("refinement options (--refine-option KEY=VALUE): name, type, default; their meaning is in the "
               "docstring of mvs_core.MvsConfig")

    @staticmethod
    def config():
        from mvs_core import MvsConfig

        return MvsConfig


class _PolishOptionAction(_FieldOptionAction):
    heading = ("pose polish options (--polish-option KEY=VALUE, with --polish): name, type, default; their meaning "
               "is in the docstring of recon.poses.given.polish.PolishConfig")

    @staticmethod
    def config():
        from ..poses.given.polish import PolishConfig

        return PolishConfig


def add_pose_option_argument(parser) -> None:
    parser.add_argument("--pose-option", action=_PoseOptionAction, default=[], metavar="KEY=VALUE",
                        help="change a pose estimator setting, e.g. keyframe_flow=12, window=6, calibrate_lens=false "
                             "(repeatable); `--pose-option list` prints every setting with its default")


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
    run.add_argument("--config", type=Path, metavar="FILE",
                     help="settings from a YAML or JSON file: PipelineConfig's fields by name, a section per stage "
                          "(medea, mvs, fusion, polish_config), as report.json's options, or a report.json itself to "
                          "run a result again; flags given with other values than their defaults override it")
    run.add_argument("--set", action=_SetAction, metavar="NAME=VALUE", default=[], dest="settings",
                     help="one setting by its config name, typed like its field, over the flags and --config "
                          "(repeatable): --set medea.stage1.epochs=200 --set fusion.voxel_size=0.02 --set "
                          "frame_budget=100; `--set list` prints every name with its type and default")
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
