"""The streamed pipeline's first pass (:mod:`recon.drivers.streamed`): decode, prior, track.

Frames are decoded in order, PRIOR_BATCH at a time, and tracked one at a time
(:class:`recon.poses.frontend.streaming.StreamingFrontend`, or the given poses), each parked
in a :class:`~recon.io.frame_store.FrameStore`; the depth frames
(:class:`recon.drivers.stream_plan.MotionSelector`; given poses: at their scale, searched on
the first frames) with their prior and features, the only frames with a prior besides the
front end's keyframes. The estimate is closed and gated as in a one-shot run; the depth
pass gets a :class:`TrackedVideo`.
More: docs/running.md#how-a-streamed-run-works
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import numpy as np

from ..core.clock import StageClock
from ..core.config import PipelineConfig
from ..core.sequence import Sequence
from ..core.stages import (
    PosePlan,
    PoseStage,
    default_intrinsics,
    gate_estimate,
    ground_truth_kept,
    judge_given_poses,
    medea_settings,
    prior_function,
)
from ..errors import ReconInputError
from ..io.frame_store import FrameStore
from ..io.pose_formats.matching import frame_names, match_pose_file
from ..io.source import FrameSource
from ..priors.base import PriorOutput, concat_outputs
from ..threads import prefetched
from .segments import estimator_options
from .stream_plan import MotionSelector, depth_gap, parse_depth_frames, select_later

log = logging.getLogger(__name__)

# Frames decoded at once; with given poses, the depth frames among them get their prior at once.
PRIOR_BATCH = 8
# Given poses: the first frames, held back until the prior's scale against the poses is known.
SCALE_PROBE_FRAMES = 32
# Depth values kept per depth frame (a pixel lattice) to size the TSDF volume, and in all.
_SAMPLE_STEP = 16
_SAMPLE_MAX = 400_000

@dataclass
class TrackedVideo:
    """What the tracking pass leaves: per frame (position in the selection) its source
    index, timestamp, name, camera-to-world pose (NaN when it has none) and whether it got
    depth; the camera; the lens term; the pose report; a sample of prior depth values."""

    indices: np.ndarray
    timestamps: np.ndarray
    names: list[str]
    poses: np.ndarray
    depth_frame: np.ndarray
    intrinsics: tuple[float, float, float, float]
    intrinsics_from: str
    size: tuple[int, int]
    lens_k1: float = 0.0
    pose_source: str = ""
    pose_info: dict = field(default_factory=dict)
    depth_sample: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    prior_info: dict = field(default_factory=dict)
    feature_shape: list | None = None
    # Given poses: why MEDeA is skipped (--medea-gate and the frames contradict them), else None.
    medea_skipped: str | None = None
    # Given poses, depth frames by motion: the prior's factor the motion rule measured in
    # (GlobalScale.to_dict and the frames searched), else None.
    prior_scale: dict | None = None
    # Depth frames by motion: how many were taken for depth_frames_min alone.
    depth_by_gap: int = 0



def track_video(config: PipelineConfig, source: FrameSource, plan: PosePlan, given, store: FrameStore, logger,
                clock: StageClock) -> TrackedVideo:
    """Decode, prior, track (module docstring); every frame parked in ``store``."""
    from tqdm.auto import tqdm

    loop = _TrackLoop(config, source, plan, given, store, logger, clock)
    total = source.count if source.count > 0 else None
    with tqdm(total=total, desc="tracking", unit="frame", disable=not config.progress) as bar:
        for batch in _batches(source, clock):
            loop.add(batch)
            bar.update(len(batch))
    return loop.close()


def _median_depth(depth: np.ndarray) -> float:
    valid = depth[depth > 0]
    return float(np.median(valid)) if valid.size else 0.0


class _TrackLoop:
    """The tracking pass's state: per-frame records (small), the poser, the depth-frame rule."""

    def __init__(self, config: PipelineConfig, source: FrameSource, plan: PosePlan, given, store: FrameStore,
                 logger, clock: StageClock):
        self.config, self.source, self.store, self.logger, self.clock = config, source, store, logger, clock
        self.intrinsics, self.intrinsics_from = given
        self.prior = prior_function(source, config.prior, path=config.prior_path, weights=config.weights,
                                    features=config.features and config.adjust, align=config.prior_align,
                                    device=config.device, progress=False)
        # Estimated poses: each frame's prior, made when first asked for (by the front end for a
        # keyframe, or for a depth frame), kept for the recent frames (_frame_prior).
        self.priors: dict[int, PriorOutput] = {}
        self.poser = _Poser(config, source, plan, self.intrinsics, store, self._front_end_prior)
        if plan.polishes(config):
            log.warning("streamed runs do not polish given poses against the frames (that needs every frame at "
                        "once); MEDeA and the refinement use the poses as given")
        # Given poses are checked against the first frames, as they come (recon.poses.given.pose_check).
        self.to_check: list[tuple[np.ndarray, np.ndarray]] | None = None if plan.estimated else []
        self.pose_check: dict | None = None
        self.medea_skipped: str | None = None
        self.select = MotionSelector(config.depth_motion, config.depth_rotation,
                                     parse_depth_frames(config.depth_frames),
                                     max_gap=depth_gap(source.count, config.depth_frames_min))
        # Frames the front end had no pose for yet (its focal search buffers the first ones):
        # their positions; the store keeps their colour, and the motion rule chooses among
        # them once close() has their poses.
        self.unposed: list[int] = []
        self.names_of = _frame_namer(source)
        self.indices, self.stamps, self.names, self.live, self.chosen, self.sample = [], [], [], [], [], []
        self.prior_info, self.feature_shape = {}, None
        # Given poses, depth frames by motion: the motion rule measures the camera's path in
        # the prior's median depth, so the first frames wait for the prior's scale (_settle_scale).
        self.prior_scale: dict | None = None
        self.probe: list[Sequence] | None = None
        searched = config.adjust and medea_settings(config, estimated=False).scale_search
        if not plan.estimated and self.select.step is None and searched:
            self.probe = []

    def add(self, batch: Sequence) -> None:
        """Prior, poses and depth-frame choice of a batch of frames; each frame parked (the
        first SCALE_PROBE_FRAMES of a given-pose run once the prior's scale is known)."""
        if self.probe is not None:
            self.probe.append(batch)
            if sum(len(b) for b in self.probe) >= SCALE_PROBE_FRAMES:
                self._settle_scale()
            return
        self._add(batch)

    def _settle_scale(self) -> None:
        """The prior's factor against the given poses on the frames held back (MEDeA's search,
        recon.core.medea.search_prior_scale); then those frames are added as any others, their
        prior reused, and the motion rule measures in the prior's depth times the factor."""
        from ..core.medea import search_prior_scale

        held, self.probe = self.probe, None
        if not held:
            return
        seq = Sequence.concatenate(held)
        positions = np.arange(len(self.indices), len(self.indices) + len(seq))
        seq = seq.with_(names=self.names_of(seq.indices, positions), intrinsics=self.intrinsics)
        with self.clock.stage("poses"):
            poses = self.poser.batch(positions, seq)
        posed = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
        out = self._prior(seq.take(posed), positions[posed]) if len(posed) else None
        if len(posed) >= 2:
            camera = self._live_intrinsics()
            with self.clock.stage("medea"):
                scale = search_prior_scale(seq.rgb[posed], out.depth, poses[posed], camera,
                                           medea_settings(self.config, False))
            self.prior_scale = {**scale.to_dict(), "frames": int(len(posed))}
        start = 0
        for batch in held:
            rows = np.flatnonzero((posed >= start) & (posed < start + len(batch)))
            ready = None if out is None else (replace(out, depth=out.depth[rows], features=None if out.features is None
                                                      else out.features[rows]), posed[rows] - start)
            self._add(batch, ready)
            start += len(batch)

    def _add(self, batch: Sequence, ready=None) -> None:
        """add() of one batch; ready: with given poses, the prior already computed for some of
        its frames as (PriorOutput, their rows in the batch)."""
        positions = np.arange(len(self.indices), len(self.indices) + len(batch))
        batch = batch.with_(names=self.names_of(batch.indices, positions), intrinsics=self.intrinsics)
        self.indices += [int(i) for i in batch.indices]
        self.stamps += [float(t) for t in batch.timestamps]
        self.names += list(batch.names)
        if self.poser.estimating:
            # The depth frames are chosen on the front end's live poses; the prior is made
            # for the frames taken (and the keyframes the front end asks for). A frame
            # without a pose yet (the focal search still buffering) waits for close()
            # (self.unposed); the store keeps its colour until then.
            with self.clock.stage("poses"):
                poses = self.poser.batch(positions, batch)
            posed = np.isfinite(poses).all(axis=(1, 2))
            take = np.ones(len(batch), bool)
            for k in range(len(batch)):
                if posed[k]:
                    take[k] = self.select(poses[k], lambda k=k: _median_depth(
                        self._frame_prior(positions[k], batch.rgb[k]).depth[0]))
                else:
                    self.unposed.append(int(positions[k]))
            rows = np.flatnonzero(take & posed)
            out = concat_outputs([self._frame_prior(positions[k], batch.rgb[k]) for k in rows]) if len(rows) else None
            for old in [p for p in self.priors if p < positions[0] - 2 * PRIOR_BATCH]:
                del self.priors[old]  # the front end asks for a frame's prior up to one frame later
        else:
            # Given poses: only the depth frames need a prior.
            with self.clock.stage("poses"):
                poses = self.poser.batch(positions, batch)
            take = np.array([self.select(pose) for pose in poses], bool)
            with self.clock.stage("poses"):
                self._check(batch, poses)
            rows = np.flatnonzero(take)
            out = self._given_prior(batch, positions, rows, ready) if len(rows) else None
            if out is not None:
                self.select.depth = self.prior_factor * _median_depth(out.depth[-1]) or self.select.depth
        with self.clock.stage("store"):
            # A frame's colour is read again only if it gets depth; the front end's finish
            # needs the others' grey image at its flow size, 1/48 of the bytes.
            for k, position in enumerate(positions):
                if take[k]:
                    self.store.put(position, rgb=batch.rgb[k])
                elif self.poser.estimating:
                    self.store.put(position, grey=self.poser.frontend.finish_image(batch.rgb[k]))
            for row, k in enumerate(rows):
                self._keep_prior(positions[k], out.depth[row], None if out.features is None else out.features[row])
        self.live += list(poses)
        self.chosen += list(take)
        self._log(batch, poses)

    @property
    def prior_factor(self) -> float:
        """The factor the motion rule puts on the prior's depth: the probe's, where applied."""
        found = self.prior_scale
        return found["factor"] if found is not None and found["applied"] else 1.0

    def _given_prior(self, batch: Sequence, positions: np.ndarray, rows: np.ndarray, ready):
        """The prior of the batch's frames ``rows``, taken from ``ready`` (see _add) where it has them."""
        if ready is None or not np.isin(rows, ready[1]).all():
            return self._prior(batch.take(rows), positions[rows])
        held, held_rows = ready
        at = np.searchsorted(held_rows, rows)
        return replace(held, depth=held.depth[at], features=None if held.features is None else held.features[at])

    def _keep_prior(self, position: int, depth: np.ndarray, features: np.ndarray | None) -> None:
        """Park a depth frame's prior (and features) in the store, and sample its depth."""
        self.store.put(position, prior=depth, features=features)
        self.sample.append(depth[::_SAMPLE_STEP, ::_SAMPLE_STEP].ravel())

    def _frame_prior(self, position: int, rgb: np.ndarray | None = None):
        """The prior (PriorOutput of one frame) of the frame at ``position``, made once while
        recent, of its colour ``rgb`` (H, W, 3), or of the one in the store (None)."""
        position = int(position)
        if position not in self.priors:
            rgb = self.store.get(position, "rgb") if rgb is None else rgb
            one = Sequence(np.array([self.indices[position]], np.int64), np.array([self.stamps[position]]), rgb[None],
                           [self.names[position]], self.intrinsics)
            self.priors[position] = self._prior(one, np.array([position]))
        return self.priors[position]

    def _front_end_prior(self, position: int, frame: np.ndarray) -> np.ndarray:
        """The prior depth (H, W) the front end asks for (a keyframe's, of the frame it gives)."""
        return self._frame_prior(position, frame).depth[0]

    def _check(self, batch: Sequence | None, poses: np.ndarray | None) -> None:
        """Collect the first frames with given poses; judge them once there are enough (or,
        with batch None, at the end of a shorter video)."""
        from ..poses.given.pose_check import PoseCheckConfig

        if self.to_check is None:
            return
        wanted = PoseCheckConfig().max_pairs + 1
        if batch is not None:
            self.to_check += [(batch.rgb[k], pose) for k, pose in enumerate(poses)][:wanted - len(self.to_check)]
        if len(self.to_check) >= wanted or (batch is None and len(self.to_check) >= 2):
            rgb, given = (np.stack(x) for x in zip(*self.to_check))
            self.pose_check, self.medea_skipped = judge_given_poses(
                rgb, given, self.intrinsics, self.config.medea_gate and self.config.adjust)
            self.to_check = None

    def _prior(self, batch: Sequence, positions: np.ndarray):
        with self.clock.stage("prior"):
            out = self.prior(batch, positions)
        self.prior_info = out.info
        self.feature_shape = None if out.features is None else list(out.features.shape[1:])
        return out

    def _log(self, batch: Sequence, poses: np.ndarray) -> None:
        """Each frame's RGB, with its camera as known now (an estimate's are logged again once
        final: recon.drivers.stream_depth.depth_windows)."""
        if self.logger is None:
            return
        with self.clock.stage("logging"):
            camera = self._live_intrinsics()
            for k, pose in enumerate(poses):
                self.logger.log_frame(int(batch.indices[k]), batch.rgb[k],
                                      pose=pose if np.isfinite(pose).all() else None, intrinsics=camera,
                                      timestamp=float(batch.timestamps[k]))

    def _live_intrinsics(self) -> tuple | None:
        """The camera while tracking: given; else the front end's once its focal search is done
        (None before); else the pose file's; else the field of view close() will assume."""
        if self.intrinsics is not None:
            return self.intrinsics
        if self.poser.estimating:
            return self.poser.frontend.intrinsics
        if self.poser.file_intrinsics is not None:
            return self.poser.file_intrinsics
        return default_intrinsics(*self.source.shape)

    def close(self) -> TrackedVideo:
        """Close the poses (global BA, gate) and return what the depth pass needs."""
        if self.probe is not None:  # a video shorter than the probe
            self._settle_scale()
        if len(self.indices) < 2:
            raise ReconInputError(f"{self.source.path}: needs at least 2 frames, got {len(self.indices)} "
                                  f"({self.source.selection.describe()})")
        indices, stamps = np.asarray(self.indices, np.int64), np.asarray(self.stamps, np.float64)
        with self.clock.stage("poses"):
            self._check(None, None)
            closed, camera_from = self.poser.close(self.store, indices, np.asarray(self.live))
        keep = np.isfinite(closed.poses).all(axis=(1, 2))
        chosen, by_gap = self._choose_unposed(closed.poses)
        if closed.dropped_note:
            log.warning(closed.dropped_note)
        camera = closed.intrinsics
        if camera is None:
            camera, camera_from = default_intrinsics(*self.source.shape), "assumed (NYU field of view)"
            log.warning("camera intrinsics unknown; assuming NYU Depth v2's field of view "
                        "(pass --intrinsics or --fov for a better mesh)")
        values = np.concatenate(self.sample) if self.sample else np.zeros(0, np.float32)
        values = values[values > 0]
        if len(values) > _SAMPLE_MAX:
            values = values[np.linspace(0, len(values) - 1, _SAMPLE_MAX).astype(np.int64)]
        return TrackedVideo(
            indices=indices, timestamps=stamps, names=self.names, poses=closed.poses,
            depth_frame=chosen & keep, intrinsics=tuple(float(v) for v in camera),
            intrinsics_from=self.intrinsics_from if self.intrinsics is not None else camera_from,
            size=tuple(self.source.shape), lens_k1=closed.lens_k1, pose_source=closed.source,
            pose_info=closed.info if self.pose_check is None else {**closed.info, "check": self.pose_check},
            depth_sample=values, prior_info=self.prior_info, feature_shape=self.feature_shape,
            medea_skipped=self.medea_skipped, prior_scale=self.prior_scale, depth_by_gap=by_gap,
        )

    def _choose_unposed(self, poses: np.ndarray) -> tuple[np.ndarray, int]:
        """Every frame's depth-frame choice, the frames tracked before they had a pose chosen
        now on their final ``poses`` (N, 4, 4) by the same rule, and the count the floor took."""
        chosen = np.asarray(self.chosen, bool).copy()
        if not self.unposed:
            return chosen, self.select.by_gap
        later = np.asarray(self.unposed, np.int64)
        taken, by_gap = select_later(poses[later], lambda k: _median_depth(self._frame_prior(later[k]).depth[0]),
                                     self.select.motion, self.select.rotation, self.select.step, self.select.max_gap)
        for position in later[taken]:  # their prior is made now
            out = self._frame_prior(position)
            self._keep_prior(position, out.depth[0], None if out.features is None else out.features[0])
        chosen[later] = taken
        return chosen, self.select.by_gap + by_gap


def _frame_namer(source: FrameSource) -> Callable[[np.ndarray, np.ndarray], list[str]]:
    """names(indices, positions) of a batch: a dataset's names cover all its selected frames
    at once (recon.io.pose_formats.matching.frame_names), other sources name frames by index."""
    from ..io.frames import DatasetSource

    if isinstance(source, DatasetSource):
        every = frame_names(source, None)
        return lambda indices, positions: [every[int(p)] for p in positions]
    return lambda indices, positions: frame_names(source, indices)


def _batches(source: FrameSource, clock: StageClock) -> Iterator[Sequence]:
    """The selected frames, PRIOR_BATCH at a time, as Sequences (the time spent waiting for
    them on the clock's decode). The next batch is decoded on a thread of its own while the
    caller works on this one."""
    frames = prefetched(source, ahead=PRIOR_BATCH)
    while True:
        with clock.stage("decode"):
            chunk = [f for _, f in zip(range(PRIOR_BATCH), frames)]
        if not chunk:
            return
        yield Sequence(np.asarray([f.index for f in chunk], np.int64), np.asarray([f.timestamp for f in chunk]),
                       np.stack([f.rgb for f in chunk]), [""] * len(chunk))


class _Poser:
    """Poses frame by frame during tracking: the streaming front end, the dataset's ground
    truth or a pose file, then closed once every frame is in."""

    def __init__(self, config: PipelineConfig, source: FrameSource, plan: PosePlan, intrinsics, store: FrameStore,
                 prior: Callable[[int, np.ndarray], np.ndarray]):
        self.plan, self.source, self.config, self.store = plan, source, config, store
        self.estimating = plan.estimated
        self.intrinsics = intrinsics
        self.file_intrinsics = None
        self.frontend = None
        # Position -> the video's frame number, for what tracking says (recon.poses.result.FrameNumbers).
        self.frame_number: dict[int, int] = {}
        if self.estimating:
            from ..poses.frontend.streaming import streaming_frontend

            if config.pose_method == "sfm":
                raise ReconInputError("--pose-method sfm needs every frame at once: run it with --stream off")
            # With --on-break segments (restart_after_loss) it starts again where it loses the
            # camera, as the one-shot run does, instead of stopping the streamed run.
            options = estimator_options(config, frontend_only=True)
            self.frontend_config = _frontend_config(options, config.device)
            # Tracking parks what the filler needs again of each frame in the store, on disk.
            self.frontend = streaming_frontend(intrinsics, prior, self.frontend_config,
                                               self.frame_number.__getitem__, store)

    def batch(self, positions, seq: Sequence) -> np.ndarray:
        """(B, 4, 4) camera-to-world poses of a batch as known now (NaN where none)."""
        if self.plan.kind == "gt":
            return np.asarray(self.source.poses[positions], np.float64)
        if self.plan.kind == "file":
            poses, self.file_intrinsics = match_pose_file(self.plan.data, self.source, seq.indices, seq.timestamps)
            return np.asarray(poses, np.float64)
        out = []
        for k, position in enumerate(positions):
            self.frame_number[int(position)] = int(seq.indices[k])
            _, pose = self.frontend.add(int(position), seq.rgb[k])
            out.append(np.full((4, 4), np.nan) if pose is None else pose)
        return np.asarray(out, np.float64)

    def close(self, store: FrameStore, indices, live: np.ndarray) -> tuple[PoseStage, str]:
        """The pose stage of every tracked frame (as the one-shot driver's, with NaN poses
        for the frames left out instead of ``keep``) and where its intrinsics came from."""
        if self.plan.kind == "gt":
            _, note = ground_truth_kept(self.source)
            return PoseStage(live, self.intrinsics, "dataset ground truth", dropped_note=note), "unknown"
        if self.plan.kind == "file":
            intr = self.intrinsics or self.file_intrinsics
            return PoseStage(live, intr, f"file {self.plan.data.path}"), "poses (file)"
        return self._close_estimate(store, indices), "poses (estimated)"

    def _close_estimate(self, store: FrameStore, indices) -> PoseStage:
        def frame(position: int) -> np.ndarray:
            return store.get(position, "rgb" if store.has(position, "rgb") else "grey")

        result = self.frontend.finish(frame, self.config.progress)
        self._second_opinion(result)
        kept, info, note = gate_estimate(result, indices)
        poses = np.asarray(result.poses, np.float64).copy()
        poses[~kept] = np.nan
        return PoseStage(poses, tuple(result.intrinsics), "estimated (streamed front end)", info,
                         lens_k1=float(result.diagnostics.get("lens_k1", 0.0)), dropped_note=note)

    def _second_opinion(self, result) -> None:
        """SfM's opinion of the depth frames (those whose colour the store keeps) where the
        front end doubts its trajectory, as ``recon.poses.estimate_poses`` asks it in a
        one-shot run (with ``--pose-method auto``, not under ``--on-break keep``):
        ``diagnostics["second_opinion"]``."""
        from ..poses.second_opinion import doubts, on_views, stretches

        asked = doubts(result.diagnostics, self.frame_number.__getitem__)
        if not asked or self.config.pose_method != "auto" or not self.frontend_config.stop_untrusted:
            return
        log.warning("the front end doubts part of its trajectory (%s); asking SfM (pycolmap) for a second opinion "
                    "on its depth frames", asked)
        views = [p for p in range(len(result.poses)) if self.store.has(p, "rgb")]
        try:
            opinion = on_views(result.poses, np.array(views, np.int64), lambda p: self.store.get(p, "rgb"),
                               self.intrinsics, asked, stretches(result.diagnostics, len(result.poses)))
        except ReconInputError as err:  # no pycolmap
            log.warning("no second opinion: %s", err)
            return
        result.diagnostics["second_opinion"] = opinion.to_dict()


def _frontend_config(options: dict, device: str = "cpu"):
    from ..poses.frontend.streaming import FrontendConfig
    from ..poses.options import configure_frontend

    unknown = sorted(set(options) - set(FrontendConfig.__dataclass_fields__))
    if unknown:
        raise ReconInputError(f"streamed runs use the front end, which has no option {', '.join(unknown)}")
    return configure_frontend(options, device)


__all__ = ["PRIOR_BATCH", "TrackedVideo", "track_video"]
