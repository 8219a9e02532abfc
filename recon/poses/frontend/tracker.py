"""The front end's local window (DROID-SLAM's ``droid_frontend``): each new frame is aligned
to the current keyframe by dense flow; frames that move far enough become keyframes, are
linked to their recent neighbours and the window is bundle-adjusted; a frame that cannot
be aligned is tried against the previous frame (promoted to a keyframe) and older
keyframes, and too many failures in a row stop tracking with the frame and the reason.

:class:`Tracker` drives a :class:`~recon.poses.frontend.track_state.TrackState`; the keyframe
policy is ``motion_filter``'s, the edges and BA ``backend``'s.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
import torch

from recon.geometry import lie
from recon.poses.ba import graph as gr
from recon.poses.ba import motion_only
from recon.poses.config import ba_pixels
from recon.poses.frontend import backend, motion_filter
from recon.poses.frontend.track_state import TrackState
from recon.poses.matching import features
from recon.poses.matching import flow as fl
from recon.poses.result import FrameNumbers, TrackingLostError, by_position

log = logging.getLogger(__name__)


class Alignment(NamedTuple):
    """A frame aligned to keyframe ``kf``: its pose T (4, 4) world-to-camera, the flows
    keyframe -> frame ``fwd`` and back ``bwd`` (h, w, 2) with their confidences ``cf``, ``cb``
    (h, w) at the flow resolution, whether DIS was seeded, and the forward flow pooled to
    the BA grid (``TrackState.edge_targets``: ``target`` (h', w', 2), ``weight`` (h', w'))."""

    kf: int
    T: torch.Tensor
    fwd: np.ndarray
    bwd: np.ndarray
    cf: np.ndarray
    cb: np.ndarray
    seeded: bool
    target: torch.Tensor
    weight: torch.Tensor


class Tracker:
    """Frame-by-frame tracking over one TrackState (``state``); number: how what it says
    names frames (``result.FrameNumbers``)."""

    def __init__(self, state: TrackState, number: FrameNumbers = by_position):
        self.state = state
        self.number = number

    def start(self, index: int, frame: np.ndarray) -> None:
        """The first frame: the first keyframe, at the origin."""
        s = self.state
        disp, pw = s.prior_disp(index, frame)
        gray = fl.prepare_gray(frame, s.geo.flow_shape)
        s.graph.add_keyframe(index, gray, torch.eye(4, dtype=torch.float64), disp, disp.clone(), pw, s.whitening(gray))
        if s.cfg.feature_init:
            s.kf_detail[0] = self._detail(frame)
        s.frame_T[index] = torch.eye(4, dtype=torch.float64)
        s.status[index] = "keyframe"

    def track(self, index: int, frame: np.ndarray) -> None:
        """Align one frame and, when it moved far enough, make it a keyframe."""
        s = self.state
        gray = fl.prepare_gray(frame, s.geo.flow_shape)
        predicted = self._predict(index)
        found = self._start_on(s.ref_kf, gray, predicted)
        if found is None and self._promote_previous(index):
            # The reference keyframe is too far (fast rotation, blur): the previous frame,
            # which still tracked, becomes a keyframe and this frame is aligned to it.
            found = self._start_on(s.ref_kf, gray, predicted)
        if found is None and s.cfg.feature_init:
            found = self._from_features(s.ref_kf, gray, frame)
        status = "tracked"
        if found is None:
            found = self._relocalise(index, gray, frame)
            if found is None:
                self._lost(index)
                return
            s.ref_kf = found.kf
            status = "relocalised"
        s.lost_run = []
        flows, motion, parallax = self._record(index, found, status)
        if motion_filter.is_keyframe(motion, parallax, s.cfg):
            revisit = self._revisit(gray, s.frame_T[index])
            if revisit is None:
                self._add_keyframe(index, frame, gray, s.frame_T[index], found.kf, flows)
                s.previous = None
                return
            found, measured = revisit
            s.ref_kf = found.kf
            s.revisits += 1
            flows, _, _ = self._record(index, found, status, measured)
        s.previous = (index, frame, gray, s.frame_T[index], s.refs[index][0], flows)
        if not found.seeded:
            s.park_edge(index, found.kf, found.target, found.weight)

    def _measure(self, found: Alignment) -> tuple[torch.Tensor, float, float]:
        """(pose relative to its keyframe (4, 4), motion, parallax) of an alignment: what the
        keyframe policy judges."""
        s = self.state
        rel = found.T @ lie.inv(s.graph.poses([found.kf])[0])
        return (rel, *motion_filter.motion_and_parallax(found.fwd, found.cf, rel, s.intrinsics, s.geo))

    def _record(self, index: int, found: Alignment, status: str, measured: tuple | None = None
                ) -> tuple[tuple, float, float]:
        """Keep a frame's alignment to its keyframe; returns its flows and the motion and
        parallax they measure from that keyframe (``measured``: what ``_measure`` already
        said of it)."""
        s = self.state
        rel, motion, parallax = measured or self._measure(found)
        s.frame_T[index] = found.T
        s.refs[index] = (found.kf, found.seeded)
        s.rel[index] = rel
        s.status[index] = status
        s.inlier[index] = s.last_inlier
        return (found.fwd, found.bwd, found.cf, found.cb), motion, parallax

    def _revisit(self, gray: np.ndarray, T: torch.Tensor):
        """An older keyframe that already sees what a frame due to become a keyframe sees
        (``FrontendConfig.revisit_flow``), judged at the frame's tracked pose T (4, 4): the
        frame's ``Alignment`` to it and ``_measure``'s figures for it, when
        the map predicts little parallax and the measured flow confirms that the frame is no
        keyframe from there; else None."""
        s = self.state
        cfg = s.cfg
        candidates = [k for k in range(len(s.graph)) if k != s.ref_kf]
        if cfg.revisit_flow <= 0 or not candidates:
            return None
        parallax, motion, frac = gr.parallax_into(s.graph.poses(candidates), s.graph.disps(candidates), s.intr, T)
        limit = ba_pixels(cfg.revisit_flow, s.geo.ba_shape[1])
        near = (parallax <= limit) & (motion <= 2 * limit)
        near &= frac >= cfg.revisit_overlap
        for n in [int(n) for n in torch.argsort(parallax) if near[n]][:2]:
            k = candidates[n]
            found = self._against(k, gray, T)
            if found is None:
                continue
            measured = self._measure(found)
            if not motion_filter.is_keyframe(*measured[1:], cfg):
                return found, measured
        return None

    def _predict(self, index: int) -> torch.Tensor:
        """Where the frame starts: the previous frame's pose as tracked (else the reference
        keyframe's), not a constant-velocity prediction.
        why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen"""
        s = self.state
        return s.frame_T.get(index - 1, s.graph.poses([s.ref_kf])[0])

    def _start_on(self, kf: int, gray: np.ndarray, predicted: torch.Tensor):
        """Alignment to keyframe kf from the predicted pose: unseeded flow first, then (when
        the prediction moves the keyframe's pixels by more than ``seed_min_flow``) flow
        seeded with what the prediction implies, which reaches motions DIS cannot find from
        zero. Unseeded first keeps what works at full frame rate exactly as it was.
        why: docs/decisions.md#pose-settings-how-the-defaults-were-chosen"""
        s = self.state
        found = self._against(kf, gray, predicted)
        if found is None and s.cfg.seed_min_flow < float("inf"):
            seed = self._seed(kf, predicted)
            if fl.mean_magnitude(seed[0]) >= s.cfg.seed_min_flow:
                found = self._against(kf, gray, predicted, seed)
        return found

    def _seed(self, kf: int, T: torch.Tensor) -> tuple[np.ndarray, np.ndarray] | None:
        """Flows keyframe kf <-> a frame at pose T (flow resolution) predicted by the keyframe's
        depth (which stands in for the frame's on the way back)."""
        s = self.state
        return gr.seed_flows(s.graph.poses([kf])[0], T, s.graph.disps([kf])[0], s.intr, s.geo.flow_shape, s.k1)

    def _from_features(self, kf: int, gray: np.ndarray, frame: np.ndarray):
        """Alignment to keyframe kf started from the pose ORB matches give by PnP against the
        keyframe's depth (``features``): for motion too large or blurred for the flow."""
        s = self.state
        rel, inliers = features.relative_pose(self._keyframe_keypoints(kf), (1.0 / s.graph.disps([kf])[0]).numpy(),
                                              features.detect(self._detail(frame), s.cfg.features),
                                              s.detail_intrinsics, s.detail_shape, s.cfg.features)
        if rel is None:
            s.last_failure += f"; {inliers} ORB inliers against keyframe {s.graph.frames[kf]}"
            return None
        T = torch.from_numpy(rel) @ s.graph.poses([kf])[0]
        found = self._against(kf, gray, T, self._seed(kf, T))
        if found is not None:
            s.feature_starts += 1
        return found

    def _detail(self, frame: np.ndarray) -> np.ndarray:
        return fl.prepare_gray(frame, self.state.detail_shape)

    def _keyframe_keypoints(self, kf: int) -> features.Keypoints:
        s = self.state
        if kf not in s.kf_keypoints:
            s.kf_keypoints[kf] = features.detect(s.kf_detail[kf], s.cfg.features)
        return s.kf_keypoints[kf]

    def _align(self, T_init: torch.Tensor, kf: int, target: torch.Tensor, weight: torch.Tensor):
        """Pose (4, 4) of one frame against keyframe kf, and its inlier fraction."""
        s = self.state
        T, _, inl = motion_only.align_frames(
            T_init[None], s.graph.poses([kf]), s.graph.disps([kf]), s.intr, torch.zeros(1, dtype=torch.int64),
            target[None].double(), weight[None].double(), huber=1.0, k1=s.k1, whiten=s.graph.whitening([kf]),
        )
        return T[0], float(inl[0])

    def _against(self, kf: int, gray: np.ndarray, T0: torch.Tensor, seed=None) -> Alignment | None:
        """Flow from keyframe kf to a frame (seed: predicted flows both ways, or None) and
        the frame's pose aligned to it from T0, or None when the flow or the alignment is not
        to be trusted (``last_failure`` says why)."""
        s = self.state
        cfg = s.cfg
        fwd, bwd, cf, cb = fl.flow_pair(s.graph.gray[kf], gray, cfg.flow, *(seed or (None, None)))
        correlation = fl.match_correlation(s.graph.gray[kf], gray, fwd, cf)
        if correlation < cfg.min_match_correlation:
            s.last_failure = f"image correlation along the flow {correlation:.2f} < {cfg.min_match_correlation}"
            return None
        local = fl.local_correlation(s.graph.gray[kf], gray, fwd, cf)
        if local < cfg.min_local_correlation:
            s.last_failure = f"local image correlation along the flow {local:.2f} < {cfg.min_local_correlation}"
            return None
        target, weight = s.edge_targets(fwd, cf)
        if float(weight.mean()) < cfg.min_edge_weight:
            s.last_failure = f"mean flow confidence {float(weight.mean()):.2f} < {cfg.min_edge_weight}"
            return None
        T, inl = self._align(T0, kf, target, weight)
        if inl < cfg.lost_inlier:
            s.last_failure = f"inlier fraction {inl:.2f} < {cfg.lost_inlier}"
            return None
        s.last_inlier = inl
        return Alignment(kf, T, fwd, bwd, cf, cb, seed is not None, target, weight)

    def _promote_previous(self, index: int) -> bool:
        """Make the previous frame a keyframe when it tracked (and is not one already)."""
        s = self.state
        if s.previous is None or s.previous[0] != index - 1:
            return False
        prev, frame, gray, T, kf, flows = s.previous
        s.previous = None
        log.info("frame %d: keyframe at frame %d too far, the previous frame becomes a keyframe", self.number(index),
                 self.number(s.graph.frames[kf]))
        self._add_keyframe(prev, frame, gray, T, kf, flows)
        return True

    def _relocalise(self, index: int, gray: np.ndarray, frame: np.ndarray):
        """Try older keyframes (most recent first) when the reference keyframe fails: by flow
        from their pose, then from the pose their ORB matches give."""
        s = self.state
        K = len(s.graph)
        tried = [k for k in range(K - 1, -1, -1) if k != s.ref_kf][: s.cfg.reloc_candidates]
        for k in tried:
            found = self._against(k, gray, s.graph.poses([k])[0])
            if found is None and s.cfg.feature_init:
                found = self._from_features(k, gray, frame)
            if found is not None:
                s.reloc_events.append({"frame": index, "keyframe": int(s.graph.frames[k])})
                log.info("frame %d: relocalised against keyframe at frame %d", self.number(index),
                         self.number(s.graph.frames[k]))
                return found
        return None

    def _lost(self, index: int) -> None:
        s = self.state
        s.lost_run.append(index)
        s.status[index] = "lost"
        if len(s.lost_run) > s.cfg.max_lost:
            first = s.lost_run[0]
            raise TrackingLostError(
                f"tracking lost at frame {self.number(first)}: {len(s.lost_run)} consecutive frames could not be "
                f"aligned to any of the last keyframes ({s.last_failure}); the video may cut, blur or move too fast",
                frame=first, lost=True,
            )

    def _add_keyframe(self, index, frame, gray, T, ref, flows) -> None:
        s = self.state
        g = s.graph
        disp, pw = s.prior_disp(index, frame)
        k = g.add_keyframe(index, gray, T, disp, disp.clone(), pw, s.whitening(gray))
        if s.cfg.feature_init:
            s.kf_detail[k] = self._detail(frame)
        s.refs.pop(index, None)
        s.status[index] = "keyframe"
        backend.add_pair(s, ref, k, *flows, "temporal")
        for j in range(k - 1, max(k - 1 - s.cfg.temporal_radius, -1), -1):
            if j != ref:
                backend.link(s, j, k, "temporal")
        backend.link_proximity(s, k)
        backend.window_ba(s, k)
        s.ref_kf = k
        s.frame_T[index] = g.poses([k])[0]
        self._forget_detail()

    def _forget_detail(self) -> None:
        """Drop the detail images and ORB keypoints of keyframes no feature start can use
        again: only the reference keyframe and the relocalisation candidates (the last
        ``reloc_candidates`` others) are tried, and the reference is always one of the
        last ``reloc_candidates + 1``. Keeps their memory per keyframe from growing."""
        s = self.state
        oldest = len(s.graph) - 1 - s.cfg.reloc_candidates
        for k in [k for k in s.kf_detail if k < oldest and k != s.ref_kf]:
            del s.kf_detail[k]
            s.kf_keypoints.pop(k, None)
