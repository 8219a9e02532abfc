"""The pipeline's stages, each a function of the sequence and its own options.

Every stage takes the :class:`~recon.core.sequence.Sequence` built so far and the few
settings it needs (never the whole ``PipelineConfig``), and returns what it made; the
drivers (:mod:`recon.drivers.oneshot`, :mod:`recon.drivers.streamed`) wire them in order
and time them. The methods live elsewhere (readers in :mod:`recon.io`, priors in
:mod:`recon.priors`, poses in :mod:`recon.poses`, MEDeA in :mod:`recon.core.medea`,
refinement in :mod:`recon.core.refine`); a stage here only says which method runs, on what,
and what goes to the report.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import ReconInputError
from ..geometry.camera import intrinsics_from_fov, resize_intrinsics
from ..geometry.rolling_shutter import MIN_SHIFT_PX, angular_velocity
from ..io.frames import DatasetSource, open_source
from ..io.pose_formats.matching import frame_names, match_pose_file
from ..io.source import FrameSource
from .sequence import Sequence

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- decode


# The frame budget counts frames of this many pixels (640x480); a larger frame counts for
# more, a smaller one for one: what a one-shot run holds grows with the frames' pixels
# (its depth maps, confidences and refinement buffers), not below a frame's fixed share
# (its MEDeA grid and features).
BUDGET_FRAME_PIXELS = 640 * 480


def budget_capacity(frame_budget: int, shape: tuple[int, int]) -> int:
    """How many frames of ``shape`` (H, W) at working size a one-shot run of
    ``frame_budget`` (frames at 640x480) holds."""
    weight = max(1.0, shape[0] * shape[1] / BUDGET_FRAME_PIXELS)
    return max(2, int(frame_budget / weight))


def window_frames(config, size: tuple[int, int]) -> int:
    """Frames per MEDeA window for frames of ``size`` (H, W): a window holds its frames at
    working size as a one-shot run does, so ``config.window`` counts frames at 640x480 as
    the frame budget does (budget_capacity), and never fewer than the overlap and two."""
    return max(budget_capacity(int(config.window), size), int(config.window_overlap) + 2)


def select_frames(path: Path, *, stride: int | None = None, max_frames: int | None = None,
                  start_time: float | None = None, end_time: float | None = None, width: int | None = None,
                  fps: float | None = None, frame_budget: int | None = 150) -> FrameSource:
    """Open the input with the selection (recon.io.source.Selection; width: working width,
    fps: frame rate of an image folder), raising the stride when no stride is given and the
    input has more frames than ``frame_budget`` holds (budget_capacity; None: never; the
    streamed pipeline takes every frame)."""
    def open_with(step):
        return open_source(path, stride=step, max_frames=max_frames, start_time=start_time, end_time=end_time,
                           width=width, min_frames=2, fps=fps)

    source = open_with(1 if stride is None else stride)
    if frame_budget is None or stride is not None or max_frames is not None:
        return source
    capacity = budget_capacity(frame_budget, source.shape)
    if source.count > capacity:
        step = math.ceil(source.count / capacity)
        log.warning("%d frames at %dx%d exceed the frame budget (%d such frames); using one frame in %d (set "
                    "--stride or --max-frames to choose)", source.count, source.shape[1], source.shape[0], capacity,
                    step)
        source = open_with(step)
    return source


def decode(source: FrameSource, progress: bool = True) -> Sequence:
    """All selected frames at working size (decoded one at a time, stored small), named."""
    from tqdm.auto import tqdm

    indices, times, images = [], [], []
    total = source.count if source.count > 0 else None
    for frame in tqdm(source, total=total, desc="decode", unit="frame", disable=not progress, leave=False):
        indices.append(frame.index)
        times.append(frame.timestamp)
        images.append(frame.rgb)
    if len(images) < 2:
        raise ReconInputError(
            f"{source.path}: needs at least 2 frames, got {len(images)} ({source.selection.describe()})")
    indices = np.asarray(indices, np.int64)
    return Sequence(indices, np.asarray(times, np.float64), np.stack(images), frame_names(source, indices))


# --------------------------------------------------------------------------- intrinsics


def given_intrinsics(source: FrameSource, intrinsics=None, fov: float | None = None) -> tuple[tuple | None, str]:
    """Intrinsics at working size known before poses: (values or None, where they came from).
    intrinsics: (fx, fy, cx, cy) in pixels of the input as decoded; fov: horizontal degrees."""
    if intrinsics is not None:
        height, width = source.native_shape
        cx, cy = float(intrinsics[2]), float(intrinsics[3])
        if not (0 <= cx <= width and 0 <= cy <= height):
            # Most often a calibration of another resolution, or the numbers in another order.
            raise ReconInputError(f"--intrinsics: the principal point ({cx:g}, {cy:g}) lies outside the "
                                  f"{width}x{height} frames of the input; give fx,fy,cx,cy in pixels of the input "
                                  "as decoded")
        return resize_intrinsics(intrinsics, source.native_shape, source.shape), "given"
    if fov is not None:
        return intrinsics_from_fov(fov, *source.shape), f"fov {fov:g} deg"
    if source.intrinsics is not None:
        return tuple(source.intrinsics), "dataset calibration"
    return None, "unknown"


def undistort_known_lens(source: FrameSource, intrinsics, intrinsics_from: str, distortion=None) -> dict | None:
    """Resample the source's frames into the pinhole camera when its lens is known: the
    coefficients given (`distortion`, OpenCV's k1, k2, p1, p2[, k3]; they need intrinsics
    known before the poses), else a dataset's published ones when its calibration is the
    camera used. A lens belongs to the calibration it came with: intrinsics given on the
    command line take no dataset coefficients. Returns what the source reports of it
    (``FrameSource.to_pinhole``), or None for a pinhole camera."""
    from ..geometry.camera import is_pinhole

    known_from = "given"
    if distortion is None and intrinsics_from == "dataset calibration":
        distortion, known_from = source.distortion, "dataset calibration"
    if is_pinhole(distortion):
        return None
    if intrinsics is None:
        raise ReconInputError("--distortion needs the camera it belongs to: give --intrinsics or --fov too (or a "
                              "dataset folder with its calibration)")
    return source.to_pinhole(intrinsics, distortion, known_from)


def default_intrinsics(height: int, width: int) -> tuple[float, float, float, float]:
    """The fallback camera: NYU Depth v2's field of view (what FastDepth was trained on)."""
    from ..priors.fastdepth import assumed_intrinsics

    fx, fy, _, _ = assumed_intrinsics(height, width)
    return (float(fx), float(fy), (width - 1) / 2.0, (height - 1) / 2.0)


# --------------------------------------------------------------------------- prior


def _has_sensor_depth(source: FrameSource) -> bool:
    return isinstance(source, DatasetSource) and source.has_depth


def prior_function(source: FrameSource, name: str, *, path: Path | None = None, weights: Path | None = None,
                   features: bool = True, align: str = "fastdepth", device: str = "cpu", progress: bool = True):
    """``prior(seq, positions) -> PriorOutput`` for frames of ``source`` (a Sequence of them
    and their positions in the selection), the network loaded once: the streamed pipeline
    calls it batch by batch. Building it loads the network, so a model that cannot be used
    fails here, before any frame is decoded.

    name: "fastdepth", "sensor" (the dataset's depth), "folder" (maps in ``path``) or "hf"
    (the local Hugging Face model in ``path``). align: for an "hf" model that predicts
    affine-invariant disparity, the metric depth it is fitted to per frame: "fastdepth"
    or "sensor".
    """
    from ..priors import make_prior

    common = dict(device=device, progress=progress)
    if name == "fastdepth":
        model = make_prior("fastdepth", weights=weights, features=features, **common)
    elif name == "sensor" and not _has_sensor_depth(source):
        raise ReconInputError(f"{source.path}: --prior sensor needs an RGB-D dataset folder with depth")
    elif name == "hf":
        model = _hf_prior(source, path, align, weights, common)

    def sensor_prior(positions):
        depth = np.stack([source.depth(int(k)) for k in positions])
        return make_prior("sensor", depth=depth, source=str(source.path), **common)

    nonfinite: dict[str, int] = {}  # folder prior: depth file -> NaN/inf pixels, over the whole run

    def prior(seq: Sequence, positions):
        if name in ("fastdepth", "hf"):
            batch_model = model
            if name == "hf" and model.kind == "affine_disparity" and align == "sensor":
                model.align_to = sensor_prior(positions)
        elif name == "sensor":
            batch_model = sensor_prior(positions)
        else:
            batch_model = make_prior("folder", path=path, frame_names=seq.names, **common)
        try:
            output = batch_model(seq.rgb, seq.intrinsics)
        except ValueError as error:  # a frame whose reference depth is too sparse to fit
            if name != "hf" or "align" not in str(error):
                raise
            raise ReconInputError(f"depth prior hf: aligning to {align} depth failed ({error})") from None
        if output.kind != "metric":
            raise ReconInputError(f"depth prior {name} gave {output.kind} depth; the pipeline needs metric depth")
        if name == "folder":
            output = _count_nonfinite(output, nonfinite, path)
        return output

    return prior


def _count_nonfinite(output, counts: dict[str, int], folder: Path):
    """The folder prior's output with its NaN/inf counts summed over the run so far (the
    streamed pipeline calls the prior batch by batch; report.json shows the last info), and
    one warning when the first are found."""
    found = output.info.get("nonfinite_files", {})
    if found and not counts:
        first = next(iter(found))
        log.warning("%s: NaN or inf pixels in the depth maps (first: %s, %d pixels) are read as invalid (no depth); "
                    "report.json counts them (prior.info.nonfinite_pixels, nonfinite_files)", folder, first,
                    found[first])
    counts.update(found)
    return replace(output, info={**output.info, "nonfinite_pixels": sum(counts.values()),
                                 "nonfinite_files": dict(counts)})


def _hf_prior(source: FrameSource, path: Path | None, align: str, weights: Path | None, common: dict):
    """The Hugging Face model (recon.priors.hf) loaded; when its config says it predicts
    affine-invariant disparity, with the metric reference it is aligned to (FastDepth loaded
    here; sensor depth is set per batch)."""
    from ..priors import make_prior

    if path is None:
        raise ReconInputError("--prior hf needs a local Hugging Face model folder (--prior-path MODEL_DIR)")
    model = make_prior("hf", model=path, **common)
    if model.kind == "affine_disparity":
        if align == "fastdepth":
            model.align_to = make_prior("fastdepth", weights=weights, features=False, **common)
        elif not _has_sensor_depth(source):
            raise ReconInputError(f"{source.path}: --prior-align sensor needs an RGB-D dataset folder with depth")
    return model


# --------------------------------------------------------------------------- poses


@dataclass(frozen=True)
class PosePlan:
    """Where the poses will come from, settled before any heavy work.

    kind: "gt" (the dataset's ground truth), "estimate" or "file"; data: the read pose
    file (recon.io.pose_formats.trajectories.PoseData) when kind is "file".
    """

    kind: str
    data: object = None

    @property
    def estimated(self) -> bool:
        return self.kind == "estimate"

    def polishes(self, config) -> bool:
        """Whether a one-shot run with PipelineConfig ``config`` polishes these poses (given
        ones, when refining, with ``polish`` on)."""
        return not self.estimated and config.refine != "none" and config.polish


@dataclass
class PoseStage:
    """Poses of the sequence's frames and what the report says of them."""

    poses: np.ndarray
    intrinsics: tuple | None
    source: str
    info: dict = field(default_factory=dict)
    keep: np.ndarray | None = None  # frames kept (ground truth may lack poses for some)
    lens_k1: float = 0.0  # radial term the poses were estimated with (recon.geometry.lens)
    dropped_note: str = ""  # why frames were left out, said once when keep is set


def plan_poses(choice: str, source: FrameSource) -> PosePlan:
    """The pose source for ``choice`` ("auto", "gt", "estimate" or a pose file / folder),
    checked: raises ReconInputError when it cannot work."""
    from ..io.pose_formats.trajectories import read_poses

    has_gt = isinstance(source, DatasetSource) and source.poses is not None
    if choice == "auto":
        choice = "gt" if has_gt else "estimate"
    if choice == "gt" and not has_gt:
        raise ReconInputError(f"{source.path}: --poses gt needs a dataset folder with ground-truth poses")
    if choice == "estimate":
        _pose_estimator()
        return PosePlan("estimate")
    if choice == "gt":
        return PosePlan("gt")
    return PosePlan("file", read_poses(Path(choice)))


def _pose_estimator():
    try:
        from ..poses import estimate_poses
    except ImportError:
        raise ReconInputError(
            "pose estimation not available; pass --poses FILE or a dataset with ground-truth poses"
        ) from None
    return estimate_poses


def camera_poses(plan: PosePlan, source: FrameSource, seq: Sequence, *, method: str = "auto",
                 options: dict | None = None, device: str = "cpu", progress: bool = True) -> PoseStage:
    """Poses of the sequence's frames from the planned source; method and options: the
    estimator's (recon.poses.estimate_poses) when the plan is to estimate."""
    if plan.kind == "gt":
        valid, note = ground_truth_kept(source)
        keep = None if valid.all() else np.flatnonzero(valid)
        return PoseStage(source.poses, None, "dataset ground truth", keep=keep, dropped_note=note)
    if plan.kind == "estimate":
        return estimated_poses(seq, method=method, options=options or {}, device=device, progress=progress)
    poses, file_intrinsics = match_pose_file(plan.data, source, seq.indices, seq.timestamps)
    return PoseStage(poses, file_intrinsics, f"file {plan.data.path}")


def ground_truth_kept(source: FrameSource) -> tuple[np.ndarray, str]:
    """(N,) bool: the selected frames with a ground-truth pose, and the note naming how many
    are left out ("" when none); ReconInputError when fewer than two have one."""
    valid = np.isfinite(source.poses).all(axis=(1, 2))
    if valid.sum() < 2:
        raise ReconInputError(f"{source.path}: fewer than 2 selected frames have a ground-truth pose")
    missing = len(valid) - int(valid.sum())
    return valid, f"{missing} frames have no ground-truth pose and are left out" if missing else ""


def gate_estimate(result, frame_indices) -> tuple[np.ndarray, dict, str]:
    """An estimate (a recon.poses PoseResult of the frames `frame_indices`, their video frame
    numbers) through the quality gate (recon.poses.checks.quality): (N,) bool frames kept, what
    report.json says of it, and the note naming the frames left out ("" when none)."""
    from ..poses.checks.motion_checks import MotionChecks
    from ..poses.checks.prior_agreement import PriorAgreement
    from ..poses.checks.quality import gate_trajectory, runs
    from ..poses.checks.scale_watch import ScaleWatch
    from ..poses.result import frame_spans
    from ..poses.second_opinion import SecondOpinion

    names = [int(i) for i in frame_indices]
    gate = gate_trajectory(result, frame_numbers=names)
    # Said once each, below, by video frame.
    diagnostics = {k: v for k, v in result.diagnostics.items()
                   if k not in ("scale_watch", "motion_checks", "prior_agreement", "frame_status", "scale_spread",
                                "second_opinion")}
    if "pieces" in diagnostics:  # tracked in pieces after a loss (recon.poses.frontend.pieces): named by video frame
        diagnostics["pieces"] = [{**p, "frames": [names[i] for i in p["frames"]]} for p in diagnostics["pieces"]]
    info = {"keyframes": len(result.keyframes), "seconds": result.seconds,
            "diagnostics": {k: v for k, v in diagnostics.items() if np.ndim(v) == 0 or len(v) < 50},
            "quality": gate.summary(names), "frame_status": list(result.diagnostics.get("frame_status", []))}
    # Frames of a piece without a pose are said once, with the piece's reason; the note below
    # names the other frames the gate leaves out.
    said = set()
    for piece in result.diagnostics.get("pieces", []):
        if not piece["tracked"]:
            a, b = piece["frames"]
            log.warning("video frames %s get no pose and are left out of depth and fusion: %s",
                        frame_spans([(a, b)], names.__getitem__), piece["why"])
            said.update(range(a, b + 1))
    if "scale_watch" in result.diagnostics:
        watch = ScaleWatch.from_dict(result.diagnostics["scale_watch"])
        # Verdicts by position in the selection, frames and breaks named by video frame.
        named = watch.renumbered(names)
        info["scale_watch"] = {**named.to_dict(), "frame_verdicts": watch.frame_verdicts(len(names))}
        if named.breaks:
            log.warning("%s (report.json: poses.scale_watch)", named.describe())
    if "motion_checks" in result.diagnostics:
        checks = MotionChecks.from_dict(result.diagnostics["motion_checks"])
        named_checks = checks.renumbered(names)
        info["motion_checks"] = {**named_checks.to_dict(), "frame_verdicts": checks.frame_verdicts(len(names))}
        for mark in (named_checks.turning_said(), named_checks.short_said()):
            if mark:
                log.warning("%s (report.json: poses.motion_checks)", mark)
    if "second_opinion" in result.diagnostics:  # the front end and SfM compared (recon.poses.second_opinion)
        opinion = SecondOpinion.from_dict(result.diagnostics["second_opinion"])
        # Each stretch compared, named by video frame.
        info["second_opinion"] = {**opinion.to_dict(), "by_stretch": [
            {**s, "frames": [names[f] for f in s["frames"]]} for s in opinion.by_stretch]}
        (log.info if opinion.trusted else log.warning)("%s (report.json: poses.second_opinion)", opinion.said())
    if "scale_spread" in result.diagnostics:  # SfM's (recon.drivers.segments.check_scale_spread)
        info["scale_spread"] = result.diagnostics["scale_spread"]
    if "prior_agreement" in result.diagnostics:
        agreement = PriorAgreement.from_dict(result.diagnostics["prior_agreement"]).renumbered(names)
        # Acted on with the scale breaks (recon.drivers.segments.check_metric_scale).
        info["metric_scale"] = agreement.to_dict()
    note = ""
    others = sorted(set(gate.dropped) - said)
    if others:
        spans = frame_spans(runs(others)[:5], names.__getitem__)
        note = (f"{len(others)} of {len(gate.keep)} frames have no pose the images back "
                f"(video frames {spans}) and are left out of depth and fusion (report.json: poses.quality)")
    return gate.keep, info, note


def estimated_poses(seq: Sequence, *, method: str, options: dict, device: str, progress: bool) -> PoseStage:
    """Poses estimated from the frames, through the quality gate (recon.poses.checks.quality):
    frames whose pose the images do not back are left out, named in report.json."""
    result = _pose_estimator()(seq.rgb, seq.prior_depth, intrinsics=seq.intrinsics, method=method, device=device,
                               progress=progress, frame_numbers=seq.indices, **options)
    kept, info, note = gate_estimate(result, seq.indices)
    keep = None if kept.all() else np.flatnonzero(kept)
    return PoseStage(np.asarray(result.poses, np.float64), tuple(result.intrinsics), "estimated", info, keep=keep,
                     lens_k1=float(result.diagnostics.get("lens_k1", 0.0)), dropped_note=note)


def tracking_states(stage: PoseStage, seq: Sequence) -> list[tuple[int, str, np.ndarray]] | None:
    """[(video frame, tracking state, camera-to-world pose)] of every frame of an estimate,
    "dropped: <why>" for those the quality gate left out; None for given poses."""
    status = stage.info.get("frame_status")
    if not status:
        return None
    why = {d["frame"]: d["reason"] for d in stage.info.get("quality", {}).get("dropped_frames", [])}
    # The scale check's verdict rides along, so that the timeline shows which stretch a
    # frame's pose belongs to when the trajectory's scale breaks (recon.poses.checks.scale_watch).
    scale = stage.info.get("scale_watch", {}).get("frame_verdicts") or ["ok"] * len(status)
    motion = stage.info.get("motion_checks", {}).get("frame_verdicts") or ["ok"] * len(status)
    # Kept under --on-break keep though the prior cannot vouch for its metres (prior_agreement).
    metres = "" if stage.info.get("metric_scale", {}).get("trusted", True) else "; metric scale untrusted"
    return [(int(i), (f"dropped: {why[int(i)]}" if int(i) in why else state)
             + ("" if scale[k] == "ok" else f"; scale {scale[k]}") + ("" if motion[k] == "ok" else f"; {motion[k]}")
             + metres, stage.poses[k])
            for k, (i, state) in enumerate(zip(seq.indices, status))]


def unrolled_frames(seq: Sequence, readout_ms: float) -> tuple[Sequence, dict]:
    """The frames resampled to one instant each (recon.geometry.rolling_shutter), with the turn rate
    of their poses: (sequence, what report.json says of it)."""
    omega = angular_velocity(seq.poses, seq.timestamps)
    unrolled, shifts = seq.unroll(omega, readout_ms / 1000.0)
    return unrolled, shutter_summary(omega, shifts, readout_ms)


def shutter_summary(omega: np.ndarray, shifts: np.ndarray, readout_ms: float) -> dict:
    """What report.json says of a rolling-shutter resampling: omega (N, 3) rad/s and the
    largest shift (N,) pixels of the frames it resampled (or left, under MIN_SHIFT_PX)."""
    speed = np.degrees(np.linalg.norm(omega, axis=1))
    return {"readout_ms": float(readout_ms), "frames_resampled": int((shifts >= MIN_SHIFT_PX).sum()),
            "median_shift_px": float(np.median(shifts)), "max_shift_px": float(shifts.max()),
            "median_turn_deg_per_s": float(np.median(speed))}


# What the pipeline and the streamed run say after naming why MEDeA's gate skipped it.
MEDEA_SKIPPED_BECAUSE = ("its consistency terms would bend the depth to fit them, so the refinement starts from the "
                         "prior's depth (without --medea-gate MEDeA runs anyway)")


def judge_given_poses(rgb: np.ndarray, poses: np.ndarray, intrinsics, gate: bool) -> tuple[dict, str | None]:
    """The epipolar check of given poses against their frames (recon.poses.given.pose_check; rgb
    (N, H, W, 3) and poses (N, 4, 4) of neighbouring frames in order, intrinsics of a pinhole
    camera): (what report.json says of it, why MEDeA is skipped or None). Poses the frames
    contradict are said in one warning; MEDeA is skipped for them only with `gate`
    (--medea-gate). why: docs/decisions.md#the-gate-on-given-poses"""
    from ..poses.given.pose_check import check_given_poses

    check = check_given_poses(rgb, poses, intrinsics)
    if check.disagreement is None:
        return check.to_dict(), None
    if gate:
        log.warning("MEDeA skipped, the frames contradict the given poses: %s; %s", check.disagreement,
                    MEDEA_SKIPPED_BECAUSE)
        return check.to_dict(), f"the frames contradict the given poses: {check.disagreement}"
    log.warning("the frames contradict the given poses: %s. MEDeA's consistency terms bend the depth to fit such "
                "poses (on TUM fr1/rpy's motion capture its depth scored better and its mesh worse than the "
                "prior's): --medea-gate skips MEDeA for them, --polish fits the poses to the frames",
                check.disagreement)
    return check.to_dict(), None


def polished_poses(stage: PoseStage, seq: Sequence, config, progress: bool = True, device: str = "cpu") -> PoseStage:
    """The given poses polished against the frames (recon.poses.given.polish, ``config`` its
    PolishConfig; its bundle adjustment on ``device``), the lens with them."""
    from ..poses.given.polish import polish_poses

    result = polish_poses(seq.rgb, seq.prior_depth, stage.poses, seq.intrinsics, config, progress, device)
    info = {**stage.info, "polish": result.info}
    source = f"{stage.source}, polished against the frames" if result.info.get("polished") else stage.source
    return replace(stage, poses=result.poses, source=source, info=info, lens_k1=result.lens_k1)


# --------------------------------------------------------------------------- depth


def medea_settings(config, estimated: bool):
    """The MedeaConfig a run uses: ``config.medea``, with the search for the prior's scale
    (``scale_search``) on when the poses are given and ``config.scale_prior`` asks for it.
    config: the PipelineConfig; estimated: whether the poses were estimated."""
    if config.scale_prior and not estimated and not config.medea.scale_search:
        return replace(config.medea, scale_search=True)
    return config.medea


def adjust_with_medea(seq: Sequence, config, use_features: bool = True, progress: bool = True):
    """MEDeA (``config`` its MedeaConfig) on the sequence: (adjusted depth (N, H, W) float32,
    MedeaResult). use_features: give MEDeA the prior's encoder features when it has them."""
    from .medea import adjust_sequence

    features = seq.features if use_features else None
    result = adjust_sequence(seq.rgb, seq.prior_depth, seq.poses, seq.intrinsics, features, config, progress)
    return result.depth.numpy().astype(np.float32, copy=False), result


def refine_depth(seq: Sequence, depth: np.ndarray, config, device: str = "cpu", progress: bool = True, known=None):
    """Multi-view stereo refinement (``config`` its mvs_core.MvsConfig) of ``depth`` (N, H, W),
    the adjusted depth of the sequence's frames: mvs_core.RefineResult. known: the swept
    depth of the first K frames from an earlier call (they are then sources only)."""
    from .refine import refine_sequence

    return refine_sequence(seq.rgb, depth, seq.poses, seq.intrinsics, replace(config, device=device), progress,
                           known)
