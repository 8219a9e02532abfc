"""The DROID-SLAM-style front end with classical parts: :class:`StreamingFrontend`, which
drives its roles over one state a frame at a time, and :func:`estimate_poses_frontend`, the
same fed from a whole video.

The roles are named after DROID-SLAM's files: ``track_state``, ``motion_filter``,
``tracker``, ``backend`` and ``filler``; the settings are ``frontend_config``'s. Frames come
at working resolution; flow runs at 1/4, BA at 1/8. Internally poses are world-to-camera
(``T_cw``); the result is camera-to-world, in the depth prior's metres.
More: docs/poses.md#the-front-ends-parts
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace

import numpy as np
import torch
from tqdm import tqdm

from recon.errors import ReconInputError
from recon.poses.ba import bundle as ba
from recon.poses.checks import motion_checks, normal_flow, prior_agreement, quality, scale_watch
from recon.poses.config import FrontendConfig, calibrates_lens, make_geometry
from recon.poses.frontend import backend, filler
from recon.poses.frontend.park import FramePark, MemoryPark, ShiftedPark
from recon.poses.frontend.pieces import StreamingPieces
from recon.poses.frontend.track_state import TrackState
from recon.poses.frontend.tracker import Tracker
from recon.poses.intrinsics import plumb_line, rotation_focal, vanishing
from recon.poses.intrinsics.calib import estimate_focal
from recon.poses.intrinsics.focal_choice import agreed_on, choose_focal
from recon.poses.matching import flow as fl
from recon.poses.result import (
    FrameNumbers,
    PoseResult,
    PriorSource,
    TrackingLostError,
    by_position,
    check_frame,
    frame_spans,
    invert_poses,
    iterate_frames,
    numbered,
    parse_intrinsics,
)

log = logging.getLogger(__name__)

__all__ = ["FrontendConfig", "StreamingFrontend", "estimate_focal", "estimate_poses_frontend"]


class StreamingFrontend:
    """The front end fed one frame at a time, for videos too long to hold in memory.

    ``add(index, frame)`` tracks the next frame and says how it went; ``finish(frame_lookup)``
    does what needs the whole video (global BA, the non-keyframes aligned to their final
    keyframes, the metric rescale) and returns the :class:`PoseResult`.

    intrinsics: (fx, fy, cx, cy) in pixels of the frames (or a 3x3 matrix), or None to search
    the focal length (principal point at the centre): the first ``8 * calib_keyframes``
    frames are then kept until the search has them, and tracked after it. prior: a callable
    ``prior(index, frame)`` -> (h, w) metric depth (0 invalid), called for the frames that
    need it (keyframes), or an (N, h, w) array (see :class:`PriorSource`). number: how its
    errors and log lines name frame `index` (``result.FrameNumbers``: the video's frame
    numbers; default: the index). park: where tracking parks what ``finish`` needs again
    of each frame (``park.FramePark``, by index; None: ``finish`` makes it again).

    Memory (``TrackState``): frames are not kept (the previous one excepted, which may
    become a keyframe); what grows is the keyframe graph, per keyframe its grey image,
    depths and flow edges, and per other frame two 4x4 poses, a status, an inlier fraction
    and the keyframe it was aligned to. ``finish`` reads the frames back through
    ``frame_lookup``.
    """

    def __init__(self, intrinsics, prior, config: FrontendConfig | None = None, number: FrameNumbers = by_position,
                 park: FramePark | None = None):
        self.prior = prior if isinstance(prior, PriorSource) else PriorSource(prior)
        self.park = park
        self.number = number
        self.intrinsics = parse_intrinsics(intrinsics)
        config = config or FrontendConfig()
        self.cfg = replace(config, calibrate_lens=calibrates_lens(config.calibrate_lens, self.intrinsics))
        self.diagnostics: dict = {"method": "frontend"}
        # Set by the focal search (recon.poses.intrinsics.focal_choice) when intrinsics are unknown.
        self._focal_choice = None
        self.state: TrackState | None = None
        self.tracker: Tracker | None = None
        self.count = 0  # frames added
        self._pending: list[np.ndarray] = []  # frames waiting for the focal search
        self._shape: tuple[int, int] | None = None
        self._seconds = 0.0
        self._finished = False

    def add(self, index: int, frame: np.ndarray) -> tuple[str, np.ndarray | None]:
        """Track frame `index` (frames come in order: 0, 1, 2, ...), (H, W, 3) uint8 RGB.

        Returns its status ("keyframe", "tracked", "relocalised", "lost", or "buffered"
        while the focal search waits for frames) and its camera-to-world pose (4, 4) as
        tracked now: before the global BA and the metric rescale (identity for frame 0),
        None while it has none (buffered, lost). A buffered frame's pose is ``current(i)``
        once the frame that completes the buffer has been added.
        Raises TrackingLostError when more than ``max_lost`` frames in a row are lost.
        """
        if self._finished:
            raise RuntimeError("StreamingFrontend.add after finish")
        if index != self.count:
            raise ReconInputError(f"frame {index} given where frame {self.count} was expected (frames come in order)")
        # A copy: the tracker keeps the previous frame, and a caller may reuse its buffer.
        frame = np.array(check_frame(frame, index, self._shape))
        self._shape = frame.shape[:2]
        self.count += 1
        with self._running():
            if self.intrinsics is None:
                self._pending.append(frame)
                if len(self._pending) < 8 * self.cfg.calib_keyframes:
                    return "buffered", None
                self._calibrate()
            else:
                self._track(index, frame)
        return self.current(index)

    def current(self, index: int) -> tuple[str, np.ndarray | None]:
        """Status and camera-to-world pose (4, 4) of frame `index` as tracked now (see ``add``)."""
        if not 0 <= index < self.count:
            raise IndexError(f"frame {index} has not been added ({self.count} frames so far)")
        s = self.state
        if s is None or index not in s.status:
            return "buffered", None
        T = s.frame_T.get(index)
        return s.status[index], None if T is None else invert_poses(T.numpy())

    def finish_image(self, frame: np.ndarray) -> np.ndarray:
        """What ``finish`` needs of a frame (H, W, 3) uint8: its grey image at the flow
        resolution, uint8 (1/48 of the frame's bytes at 640x480). A caller that parks frames
        on disk until ``finish`` can keep this instead of the frame."""
        return fl.prepare_gray(frame, make_geometry(frame.shape[:2], self.cfg.ba_stride).flow_shape)

    @property
    def focal_choice(self):
        """How the focal length was chosen (``focal_choice.FocalChoice``), None when given."""
        return self._focal_choice

    @property
    def lens_k1(self) -> float:
        """The lens' radial term as tracking has it now (the BA refines it when it calibrates)."""
        return self.state.k1 if self.state is not None else self.cfg.lens_k1

    def evidence(self) -> np.ndarray:
        """(count,) the share of each frame's flow confidence its tracked pose explains (the
        quality gate's ``frame_inlier`` as tracking has it now; NaN where there is none)."""
        inlier = self.state.inlier if self.state is not None else {}
        return np.array([inlier.get(i, np.nan) for i in range(self.count)], dtype=np.float64)

    def lost_tail(self) -> int | None:
        """The first frame of a loss that runs into the last frame added and is long enough
        for ``finish`` to refuse it (more than half of ``max_lost``), else None."""
        s, last = self.state, self.count - 1
        if s is not None and s.lost_run and len(s.lost_run) > self.cfg.max_lost // 2 and s.lost_run[-1] == last:
            return s.lost_run[0]
        return None

    def flush(self) -> None:
        """Search the focal length on the frames buffered for it and track them now (a video
        shorter than the search's buffer; ``finish`` does it too). Raises TrackingLostError as
        ``add`` does."""
        if self.state is None and self._pending:
            with self._running():
                self._calibrate()

    def finish(self, frame_lookup: Callable[[int], np.ndarray], progress: bool = False,
               stop: int | None = None, failing: tuple[float, int] | None = None) -> PoseResult:
        """Poses of every frame added, metric: the lost-at-the-end check, global BA, the
        non-keyframes aligned to their final keyframes (frames read back through
        ``frame_lookup(i)`` -> the frame given to ``add(i, ...)`` or its ``finish_image``), the
        metric rescale. seconds: the time spent in ``add`` and ``finish``. The diagnostics are
        those of :func:`estimate_poses_frontend`. stop: poses of frames [0, stop) only, the
        later ones forgotten (where tracking lost the camera and a new piece took over,
        ``recon.poses.frontend.pieces``). failing: (share, lookback) for a video that ends where
        the camera was lost: the frames of the last `lookback` whose tracking was already
        failing there (``quality.failing_since`` on their evidence after the global BA) are
        forgotten as well, and the BA solved again without them. Raises TrackingLostError."""
        if self._finished:
            raise RuntimeError("StreamingFrontend.finish called twice")
        if stop is not None and stop < self.count:
            if self.state is None:
                raise RuntimeError("StreamingFrontend.finish(stop=...) before tracking started")
            self.state.forget_from(stop)
            self.count = stop
        if self.count == 0:
            raise TrackingLostError("no frames to track", frame=0)
        self._finished = True
        with self._running():
            if self.state is None:  # a video shorter than the focal search's buffer
                self._calibrate()
            result = self._finish(frame_lookup, progress, failing)
        result.seconds = self._seconds
        return result

    # ------------------------------------------------------------------ steps

    @contextmanager
    def _running(self) -> Iterator[None]:
        """The front end's torch threads (restored after, as other work shares the process)
        and the time spent, for ``PoseResult.seconds``."""
        threads = torch.get_num_threads()
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._seconds += time.perf_counter() - t0
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)

    def _track(self, index: int, frame: np.ndarray) -> None:
        if self.state is None:
            geo = make_geometry(frame.shape[:2], self.cfg.ba_stride)
            self.state = TrackState(self.intrinsics, geo, self.prior, self.cfg, self.park)
            self.tracker = Tracker(self.state, self.number)
            self.tracker.start(index, frame)
        else:
            self.tracker.track(index, frame)

    def _calibrate(self) -> None:
        """Focal search on the buffered first frames, then track them."""
        frames, self._pending = self._pending, []
        height, width = frames[0].shape[:2]
        lens, regions = None, None
        if self.cfg.plumb_line and self.cfg.calibrate_lens and self.cfg.lens_k1 == 0.0:
            # The straight edges' regions, found once for the lens and the vanishing points.
            edges = plumb_line.PlumbLineConfig()
            regions = plumb_line.sample_regions(frames, edges, edges.max_frames, edges.max_width)
            lens = plumb_line.estimate_lens(frames, edges, regions)
            self.diagnostics["plumb_line"] = lens.to_dict()
            lens = lens if lens.trusted else None
        vp = None
        if self.cfg.vanishing_points:
            vp = vanishing.estimate_focal_vp(frames, lens, regions=regions)
            self.diagnostics["vanishing_points"] = vp.to_dict()
        search = None
        if not agreed_on(vp, self.cfg):
            # The flow search's BA over the first keyframes is the calibration's largest cost;
            # where the vanishing points are agreed on, their value is taken whatever it says.
            search = estimate_focal(frames, self.prior, self.cfg, lens)
            self.diagnostics["focal_search"] = {"focal": search.focal, "bracketed": search.bracketed,
                                                "evaluations": search.evaluations}
        rotation = None
        if self.cfg.rotation_focal:
            rotation = rotation_focal.estimate_focal_rotation(frames)
            self.diagnostics["rotation_focal"] = rotation.to_dict()
        choice = self._focal_choice = choose_focal(search, vp, self.cfg, rotation)
        focal = choice.focal
        self.intrinsics = (focal, focal, (width - 1) / 2.0, (height - 1) / 2.0)
        self.diagnostics["focal"] = choice.to_dict()
        self.diagnostics["focal_source"] = choice.source
        if lens is not None:
            # Tracking starts from the lens the focal length was found with; the BA refines it.
            self.cfg = replace(self.cfg, lens_k1=lens.k1(focal))
            self.diagnostics["plumb_line"]["k1"] = self.cfg.lens_k1
        # A warning, not a detail: the mesh's size and shape follow the focal length, and the
        # estimates have known errors. why: docs/decisions.md#the-focal-length-from-nothing
        log.warning(choice.warning(width))
        for i, frame in enumerate(frames):
            self._track(i, frame)

    def _prior_agreement(self, prior_disp: torch.Tensor, prior_w: torch.Tensor) -> dict:
        """Whether the prior's depth follows the keyframes' depth as their flow measures it
        (``recon.poses.checks.prior_agreement``): report.json's poses.metric_scale, which a run stops
        at (``recon.drivers.segments.check_metric_scale``)."""
        s = self.state
        _, edges = s.graph.edge_list()
        depth, rel = prior_agreement.keyframe_triangulations(s.graph.poses(), edges.ii, edges.jj, edges.target,
                                                             edges.weight, s.intr, float(s.k1))
        cfg = prior_agreement.AgreementConfig()
        measured = (rel < cfg.max_error) & (prior_w > 0)
        correlation = prior_agreement.log_depth_correlation(depth.numpy(), (1.0 / prior_disp).numpy(), measured.numpy())
        return prior_agreement.judge_agreement(s.graph.frames, *correlation, cfg).to_dict()

    def _check_end(self) -> None:
        """A loss that runs into the end of the video (more than half of ``max_lost``) is a failure."""
        first = self.lost_tail()
        if first is not None:
            raise TrackingLostError.at_the_end(first, self.number)

    def _finish(self, frame_lookup: Callable[[int], np.ndarray], progress: bool,
                failing: tuple[float, int] | None = None) -> PoseResult:
        s = self.state
        self._check_end()
        backend.global_ba(s)
        given = self.count
        if failing:
            self._forget_failing(frame_lookup, *failing)
        n = self.count
        filler.align_non_keyframes(s, frame_lookup, n, progress)
        g = s.graph
        for k, i in enumerate(g.frames):
            s.frame_T[i] = g.poses([k])[0]
        prior, prior_w = g.priors()
        # Said by the caller, which knows the video's frame numbers (recon.core.stages.gate_estimate).
        watch = scale_watch.watch_scale(g.disps().numpy(), prior.numpy(), (prior_w > 0).numpy(), g.frames)
        if watch.breaks and self.cfg.join_scale_breaks:
            backend.rescale_stretches(s, [(b.before, f) for b, f in zip(watch.breaks, watch.corrections)])
            watch.applied = True
        scale = backend.metric_rescale(s)
        T_cw = torch.stack([s.frame_T[i] for i in range(n)]).numpy()
        keyframe_depth = (1.0 / g.disps()).float().numpy()
        self.diagnostics["prior_agreement"] = self._prior_agreement(prior, prior_w)
        motion = motion_checks.check_motion(
            g.poses().numpy(), keyframe_depth, g.frames, T_cw, float(self.intrinsics[0]), s.geo.shape[1],
            lens_k1=s.k1 if self.cfg.calibrate_lens else None, k1_bound=ba.MAX_K1)
        if self.cfg.check_short_flow:
            motion = self._short_flow(motion)
        watch = watch.without_turns(motion.rotation_only)
        focal_estimated = self._focal_choice is not None
        why = motion.renumbered([self.number(i) for i in range(n)]).untrusted(focal_estimated=focal_estimated)
        if focal_estimated and not self._focal_choice.found:
            why.insert(0, self._focal_choice.not_found())
        result = PoseResult(
            poses=invert_poses(T_cw),
            intrinsics=tuple(float(v) for v in self.intrinsics),
            keyframes=np.array(g.frames, dtype=np.int64),
            seconds=0.0,
            diagnostics={**self.diagnostics, **self._diagnostics(scale), "scale_watch": watch.to_dict(),
                         "motion_checks": motion.to_dict()},
            keyframe_depth=keyframe_depth,
        )
        if why and self.cfg.stop_untrusted:
            # Frames far apart are SfM's usual input, but the run does not fall back to it unless
            # it is asked for a second opinion (recon.poses.second_opinion), which compares the
            # two. why: docs/decisions.md#the-checks-on-an-estimated-trajectory
            jumping = motion.moves_too_fast and focal_estimated
            err = TrackingLostError(
                f"the trajectory of frames {frame_spans([(0, n - 1)], self.number)}"
                + (f" (frames {frame_spans([(n, given - 1)], self.number)} left out: tracking was failing there)"
                   if n < given else "")
                + f" cannot be trusted: {'; '.join(why)}"
                + ("; give the camera's intrinsics (--intrinsics or --fov), try --pose-method sfm, or "
                   "--on-break keep to take the trajectory anyway" if jumping else ""),
                frame=0, sfm_may_help=not jumping)
            err.untrusted_result = result
            raise err
        return result

    def _forget_failing(self, frame_lookup: Callable[[int], np.ndarray], share: float, lookback: int) -> None:
        """Forget the last frames whose tracking was failing before the loss that ends the
        video (``finish``'s failing) and solve the global BA again without them."""
        s, n = self.state, self.count
        lookback = min(lookback, n - 2)  # two frames are kept at least
        if lookback <= 0:
            return
        # The last frames' evidence against the solved map; the state is left as it is until
        # the filler aligns every frame.
        first = max(n - lookback - quality.GOOD_RUN, 0)
        evidence = self.evidence()
        for i, (_, _, _, inlier) in filler.realigned(s, frame_lookup, n, first=first).items():
            if np.isfinite(inlier):  # as the filler keeps it
                evidence[i] = inlier
        since = quality.failing_since(evidence, share, lookback)
        if since < n:
            log.info("frames %s: tracking was failing before the camera was lost; forgotten",
                     frame_spans([(since, n - 1)], self.number))
            s.forget_from(since)
            self.count = since
            backend.global_ba(s)

    def _short_flow(self, motion: motion_checks.MotionChecks) -> motion_checks.MotionChecks:
        """The motion checks with the stretches whose steps the dense flow made short
        (``normal_flow``). A verdict, not a break. why: docs/decisions.md#the-short-flow-check"""
        g, s, cfg = self.state.graph, self.state, self.cfg.normal_flow
        num, den, judged = normal_flow.keyframe_slopes(g.poses(), g.disps(), g.gray, s.intr, s.k1, cfg)
        stretches, largest = normal_flow.short_stretches(num, den, judged, cfg)
        return replace(motion, short_flow=[[g.frames[a], g.frames[b + 1]] for a, b in stretches],
                       short_flow_slope=largest)

    def _diagnostics(self, scale: float) -> dict:
        s, n = self.state, self.count
        last = s.ba_reports[-1] if s.ba_reports else ba.BAReport()
        status = [s.status.get(i, "tracked") for i in range(n)]
        return dict(
            num_keyframes=len(s.graph),
            edges=s.graph.kinds(),
            metric_scale_factor=scale,
            frame_status=status,
            frame_inlier=[s.inlier.get(i, float("nan")) for i in range(n)],
            feature_starts=s.feature_starts,
            lost_frames=[i for i, st in enumerate(status) if st in ("recovered", "interpolated")],
            relocalisations=s.reloc_events,
            revisits=s.revisits,
            ba_rmse_px=last.rmse,
            ba_inlier_fraction=last.inlier_fraction,
            ba_grid=s.geo.ba_shape[::-1],  # reported (w, h), as the run reports always had it
            lens_k1=s.k1,
        )


def streaming_frontend(intrinsics, prior, config: FrontendConfig, number: FrameNumbers = by_position,
                       park: FramePark | None = None) -> StreamingFrontend | StreamingPieces:
    """The streaming front end for a video: with ``config.restart_after_loss`` one that starts
    again where it loses the camera (``recon.poses.frontend.pieces.StreamingPieces``: pieces of at
    least twice a loss's length, each with the first piece's camera and lens), else one
    that stops there. prior, number and park: as :class:`StreamingFrontend` takes them, by
    position in the video."""
    if not config.restart_after_loss:
        return StreamingFrontend(intrinsics, prior, config, number, park)
    source = prior if isinstance(prior, PriorSource) else PriorSource(prior)

    def piece(first: int, intr, k1) -> StreamingFrontend:
        piece_config = config if k1 is None else replace(config, lens_k1=float(k1))
        # An array stays an array (a view from the piece's first frame): the front end reads
        # every frame's prior for the metric scale only when it is not asked for one by one.
        piece_prior = source.prior[first:] if not source.is_callable else \
            (lambda i, frame: source.get(first + i, frame))
        return StreamingFrontend(intr, piece_prior, piece_config, lambda i: number(first + i),
                                 None if park is None else ShiftedPark(park, first))

    loss = config.max_lost + 1
    return StreamingPieces(piece, intrinsics, min_frames=2 * loss, keep=loss + 1,
                           failing=(config.failing_inlier, loss) if config.failing_inlier > 0 else None, number=number)


# --------------------------------------------------------------------------- whole videos


def estimate_poses_frontend(frames, prior_depth, intrinsics=None, progress: bool = True,
                            config: FrontendConfig | None = None, frame_numbers=None) -> PoseResult:
    """Track a video with the dense front end (:class:`StreamingFrontend` fed every frame).

    frames: (N, H, W, 3) uint8 RGB (or a sequence of such frames); prior_depth: (N, h, w)
    metric depth (0 invalid) or a callable ``prior(index, frame)``; intrinsics: (fx, fy,
    cx, cy) in pixels of the frames, or None to search the focal length (principal point
    at the centre); frame_numbers: the video's frame number of each frame, how errors and
    log lines name them (``result.numbered``; default: positions). Returns camera-to-world
    poses of every frame, metric.

    diagnostics: method, num_keyframes, edges per kind, focal search (evaluations,
    bracketed), metric scale factor applied, per-frame status ("keyframe", "tracked",
    "recovered" (lost while tracking, aligned at the end), "interpolated" (no reliable
    flow: geodesic between keyframes)), relocalisation events, BA rmse / inlier fraction.
    Raises TrackingLostError when more than ``max_lost`` consecutive frames cannot be aligned.
    """
    t0 = time.perf_counter()
    frames_list = [f for _, f in iterate_frames(frames)]  # views of an array; the filler reads them back
    if not frames_list:
        raise TrackingLostError("no frames to track", frame=0)
    prior = PriorSource(prior_depth)
    if not prior.is_callable and len(prior) != len(frames_list):
        raise ReconInputError(f"prior depth has {len(prior)} frames but the video has {len(frames_list)}")
    # Every frame is in memory here: what tracking parks for the filler (115 KB a frame at
    # 640x480) adds an eighth.
    stream = streaming_frontend(intrinsics, prior, config or FrontendConfig(), numbered(frame_numbers), MemoryPark())
    try:
        for i, frame in enumerate(tqdm(frames_list, desc="tracking", unit="frame", disable=not progress,
                                       leave=False)):
            stream.add(i, frame)
        result = stream.finish(frames_list.__getitem__, progress)
    except TrackingLostError as err:
        err.focal_choice = stream.focal_choice
        raise
    result.seconds = time.perf_counter() - t0
    return result
