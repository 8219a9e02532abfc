"""The dense pose front end (recon.poses.frontend.streaming) on the synthetic room (conftest: pose_room):
accuracy, metric scale, lens calibration, focal search, tracking loss named by frame, and the
streaming front end (frame by frame) giving the batch result."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
import torch

from recon.errors import ReconInputError
from recon.eval.trajectory import align, ate_rmse, path_length, rpe, scale_error
from recon.geometry.lens import distort_images
from recon.poses import TrackingLostError, estimate_poses
from recon.poses.frontend.streaming import FrontendConfig
from recon.poses.intrinsics.calib import estimate_focal
from recon.poses.intrinsics.focal_choice import VANISHING_ACCURACY
from recon.poses.intrinsics.plumb_line import LensEstimate
from recon.poses.result import PriorSource


def test_frontend_synthetic_accuracy_and_metric_scale(pose_room):
    seq, prior = pose_room
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    assert res.poses.shape == (36, 4, 4) and np.isfinite(res.poses).all()
    assert res.diagnostics["method"] == "frontend" and len(res.keyframes) >= 4
    length = path_length(seq.poses)
    ate = ate_rmse(res.poses, seq.poses, "sim3")["rmse"]
    assert ate <= 0.01 * length, f"Sim(3) ATE {ate:.4f} m > 1% of the {length:.2f} m path"
    assert scale_error(res.poses, seq.poses) <= 0.10
    # Rotations are right too (ATE looks at camera centres only).
    assert rpe(res.poses, seq.poses, delta=10)["rot_rmse_deg"] < 0.5  # the true 10-frame rotation is ~4 deg
    assert res.keyframe_depth is not None and res.keyframe_depth.shape[0] == len(res.keyframes)


def test_frontend_calibrates_a_barrel_lens(pose_room):
    """The room filmed through a barrel lens (k1 = -0.1, 4 % at the corners): asked to, the
    front end finds k1 and keeps the path and scale; with the intrinsics given and nothing
    asked, the calibration is used as given (no lens on top of it: a pinhole camera, whose
    scale here is 19 % off)."""
    seq, prior = pose_room
    rgb = distort_images(seq.rgb, seq.intrinsics, -0.1)
    depth = distort_images(prior, seq.intrinsics, -0.1, nearest=True)
    length = path_length(seq.poses)
    res = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False,
                         config=replace(FrontendConfig(), calibrate_lens=True))
    assert abs(res.diagnostics["lens_k1"] + 0.1) < 0.02, res.diagnostics["lens_k1"]
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.01 * length
    assert scale_error(res.poses, seq.poses) <= 0.10
    given = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False)
    assert given.diagnostics["lens_k1"] == 0.0 and given.intrinsics == pytest.approx(seq.intrinsics)
    assert scale_error(given.poses, seq.poses) > 0.10


def test_frontend_estimates_focal_length_when_intrinsics_are_withheld(pose_room, caplog):
    """The focal length is searched when no intrinsics are given, and the user is warned once
    with the figure and how to give the camera instead."""
    seq, prior = pose_room
    with caplog.at_level(logging.WARNING, logger="recon"):
        res = estimate_poses(seq.rgb, prior, None, method="frontend", progress=False)
    f_true = seq.intrinsics[0]
    assert abs(res.intrinsics[0] / f_true - 1) <= 0.05, (res.intrinsics, f_true)
    assert res.diagnostics["focal_search"]["bracketed"]
    # The room's textured walls break its edges: no lens is claimed, the search is a pinhole one.
    assert res.diagnostics["plumb_line"]["trusted"] is False and "k1" not in res.diagnostics["plumb_line"]
    # ... and too few of its edges are straight to agree on vanishing points: the flow's value stands.
    assert res.diagnostics["focal_source"] == "flow" and res.diagnostics["focal"]["focal"] == res.intrinsics[0]
    said = [r.getMessage() for r in caplog.records if "focal length estimated" in r.getMessage()]
    assert len(said) == 1 and f"{res.intrinsics[0]:.1f} px" in said[0] and "--fov or --intrinsics" in said[0]
    length = path_length(seq.poses)
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.02 * length


def _with_vanishing_focal(pose_room, caplog, monkeypatch, share_of_true: float, agreeing: float = 0.6):
    """The room tracked without intrinsics while the vanishing points report a trusted focal
    length of `share_of_true` x the true one, `agreeing` of the frames agreeing on it: (that
    focal length, the result, the focal warnings)."""
    from recon.poses.intrinsics import vanishing

    seq, prior = pose_room
    f_vp = share_of_true * seq.intrinsics[0]
    found = vanishing.VanishingFocal(f_vp, agreeing, int(40 * agreeing), 36, 40, True)
    monkeypatch.setattr(vanishing, "estimate_focal_vp", lambda frames, lens=None, cfg=None, regions=None: found)
    with caplog.at_level(logging.WARNING, logger="recon"):
        res = estimate_poses(seq.rgb, prior, None, method="frontend", progress=False)
    return f_vp, res, [r.getMessage() for r in caplog.records if "focal length estimated" in r.getMessage()]


def test_vanishing_points_most_frames_agree_on_replace_the_search(pose_room, caplog, monkeypatch):
    """Where most frames agree on the vanishing points, tracking runs with their focal
    length, the flow search (whose value could not change the choice) is not made, and the
    warning says where the value came from; a value far from the truth is tracked with too,
    its range widened by the rotation's estimate where that one is trusted."""
    f_vp, res, said = _with_vanishing_focal(pose_room, caplog, monkeypatch, 0.97)
    assert res.intrinsics[0] == pytest.approx(f_vp) and res.diagnostics["focal_source"] == "vanishing points"
    assert "focal_search" not in res.diagnostics and "flow" not in res.diagnostics["focal"]["candidates"]
    assert len(said) == 1 and "vanishing points" in said[0] and f"{f_vp:.1f} px" in said[0]
    caplog.clear()
    f_vp, res, said = _with_vanishing_focal(pose_room, caplog, monkeypatch, 0.6)
    assert res.intrinsics[0] == pytest.approx(f_vp) and "focal_search" not in res.diagnostics
    choice = res.diagnostics["focal"]
    assert choice["low"] == pytest.approx(min(choice["candidates"].values()))
    assert choice["high"] == pytest.approx(max(choice["candidates"].values()))
    assert len(said) == 1 and (f"{f_vp:.0f}-" in said[0]) == choice["disagree"]


def test_vanishing_points_few_frames_agree_on_leave_the_search_standing(pose_room, caplog, monkeypatch):
    """A vanishing-point value a minority of the frames agree on does not replace the
    search's; it widens the range the warning gives."""
    f_vp, res, said = _with_vanishing_focal(pose_room, caplog, monkeypatch, 0.6, agreeing=0.3)
    assert res.diagnostics["focal_source"] == "flow"
    assert res.intrinsics[0] == pytest.approx(res.diagnostics["focal_search"]["focal"])
    low = f_vp / VANISHING_ACCURACY  # the vanishing points' value, give or take their accuracy
    assert len(said) == 1 and f"{low:.0f}-" in said[0] and res.diagnostics["focal"]["low"] == pytest.approx(low)


def test_focal_search_through_the_measured_lens(pose_room):
    """The room filmed through a barrel lens (k1 = -0.1) with the focal length withheld: as a
    pinhole search the focal length comes out long, as on the real recordings; searched
    through the lens that straight edges give (corner shift, no focal length needed) it is
    right, and that lens converts to the true k1 at the focal length found."""
    seq, prior = pose_room
    k1 = -0.1
    rgb = distort_images(seq.rgb, seq.intrinsics, k1)
    depth = distort_images(prior, seq.intrinsics, k1, nearest=True)
    f_true = seq.intrinsics[0]
    height, width = rgb.shape[1:3]
    half_diagonal = 0.5 * float(np.hypot(width - 1, height - 1))
    lens = LensEstimate(k1 * (half_diagonal / f_true) ** 2, half_diagonal, regions=100, trusted=True)
    cfg = FrontendConfig()
    pinhole = estimate_focal(list(rgb), PriorSource(depth), cfg).focal
    through_lens = estimate_focal(list(rgb), PriorSource(depth), cfg, lens).focal
    assert pinhole / f_true - 1 > 0.06, pinhole
    assert abs(through_lens / f_true - 1) < 0.035, through_lens
    assert abs(lens.k1(through_lens) - k1) < 0.01


def test_a_revisited_room_adds_no_keyframes(pose_room):
    """The room walked forwards, backwards and forwards again (three passes): the later
    passes go on from the keyframes of the first instead of adding their own, so the map
    stays the size of the room, and the poses stay as good as one pass's. With the reuse
    off (DROID-SLAM's behaviour) every pass adds keyframes."""
    seq, prior = pose_room
    order = np.concatenate([np.arange(36), np.arange(34, -1, -1), np.arange(1, 36)])
    one = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    again = estimate_poses(seq.rgb[order], prior[order], seq.intrinsics, method="frontend", progress=False)
    off = estimate_poses(seq.rgb[order], prior[order], seq.intrinsics, method="frontend", progress=False,
                         revisit_flow=0)
    assert again.diagnostics["revisits"] > 0 and off.diagnostics["revisits"] == 0
    assert len(again.keyframes) <= len(one.keyframes) + 3, (len(again.keyframes), len(one.keyframes))
    assert len(off.keyframes) >= 2 * len(one.keyframes), (len(off.keyframes), len(one.keyframes))
    length = path_length(seq.poses)
    ate = ate_rmse(again.poses, seq.poses[order], "sim3")["rmse"]
    assert ate <= 0.01 * length, f"Sim(3) ATE {ate:.4f} m > 1% of the {length:.2f} m path"
    # A frame walked past twice gets (nearly) the same pose both times.
    first, second = again.poses[10], again.poses[len(order) - 26]  # frame 10 on passes 1 and 3
    assert np.linalg.norm(first[:3, 3] - second[:3, 3]) <= 0.015 * length


def test_tracking_loss_names_the_frame(pose_room):
    seq, prior = pose_room
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=(14, 240, 320, 3), dtype=np.uint8)
    frames = np.concatenate([seq.rgb[:12], noise])
    depth = np.concatenate([prior[:12], prior[:14]])
    with pytest.raises(TrackingLostError, match="tracking lost at frame 12") as info:
        estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False)
    assert info.value.frame == 12


def test_restarts_change_nothing_where_the_camera_is_never_lost(pose_room):
    """A video tracked through without a loss gets the same estimate with restart_after_loss
    as without (the restarting front end is the plain one until a loss): the same poses and
    the same metric scale, which an array prior gives from every frame's prior."""
    seq, prior = pose_room
    plain = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)
    restarting = estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False,
                                restart_after_loss=True)
    assert "pieces" not in restarting.diagnostics
    assert restarting.diagnostics["metric_scale_factor"] == plain.diagnostics["metric_scale_factor"]
    assert np.allclose(restarting.poses, plain.poses, atol=1e-9)


def test_tracking_starts_again_after_a_loss_as_a_new_piece(pose_room):
    """restart_after_loss (what --on-break segments asks for): 30 frames of the room, a cut to
    12 frames of noise, then the room walked backwards. The front end tracks the first piece,
    gives the noise no pose (each noise frame loses the camera at once) and tracks the room
    again as a second piece; the scale watch breaks at the restart (kind "lost"), both pieces
    are within 2 % of their (half-metre) paths, and the quality gate leaves the noise out."""
    from recon.poses.checks.quality import gate_trajectory

    seq, prior = pose_room
    noise = np.random.default_rng(0).integers(0, 256, size=(12, 240, 320, 3), dtype=np.uint8)
    back = np.arange(35, 5, -1)
    frames = np.concatenate([seq.rgb[:30], noise, seq.rgb[back]])
    depth = np.concatenate([prior[:30], prior[:12], prior[back]])
    truth = np.concatenate([seq.poses[:30], np.tile(np.eye(4), (12, 1, 1)), seq.poses[back]])
    with pytest.raises(TrackingLostError, match="tracking lost at frame 30"):
        estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False)
    res = estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False, restart_after_loss=True)
    pieces = [p for p in res.diagnostics["pieces"] if p["tracked"]]
    assert [p["frames"] for p in pieces] == [[0, 29], [42, 71]]
    assert [(b["before"], b["after"]) for b in res.diagnostics["scale_watch"]["breaks"]
            if b["kind"] == "lost"] == [(29, 42)]
    assert not np.isfinite(res.poses[30:42]).any() and np.isfinite(res.poses[:30]).all()
    for a, b in ((0, 30), (42, 72)):
        ate = ate_rmse(res.poses[a:b], truth[a:b], "sim3")["rmse"]
        assert ate <= 0.02 * path_length(truth[a:b]), (a, ate)
    assert res.keyframes.min() == 0 and res.keyframes.max() >= 42 and len(res.keyframe_depth) == len(res.keyframes)
    assert [p.get("why") for p in res.diagnostics["pieces"]] == [
        None, "tracking, started again after the camera was lost, lost it again within 22 frames", None]
    gate = gate_trajectory(res)
    assert gate.keep[:30].all() and not gate.keep[30:42].any() and gate.keep[42:].all()


def test_frames_whose_tracking_failed_before_a_loss_get_no_pose():
    """The synthetic walk-through's corner (frames 150-229: the plain corridor, the turn out of
    it from frame 174, room B through the door): the front end loses the camera at frame 186,
    but its map goes wrong from the corner's start, and the frames in between pass every check
    one by one. With restarts, a new piece starts at the loss, and the frames before it whose
    tracking was failing (failing_inlier) get no pose: a piece of their own, between the
    corner's start (within 5 frames) and the loss, said so. Kept, the frames from the corner
    on come back farther off the truth than those before it (the plain corridor's own error:
    3-20 cm).

    Whether the evidence of the corner's frames falls below the rule's 85 % depends on the
    machine's floating point (the rendering's ray casting and the flow differ in their last
    bits between CPUs): on an AMD EPYC the first piece gave up frames 175-185, on an AVX-512
    Intel Xeon the same frames explained 85-93 % of their flow and were kept, 1.5-2x off."""
    from recon.synthetic import simulate_prior
    from recon.synthetic.walkthrough import render_walkthrough

    walk = render_walkthrough(320, 240, seed=0, frames=slice(150, 230))
    corner = walk.cuts[1] - 150
    prior = simulate_prior(walk.depth, seed=1)

    def track(**options):
        return estimate_poses(walk.rgb, prior, walk.intrinsics, method="frontend", progress=False,
                              restart_after_loss=True, **options)

    res = track()
    pieces = [(p["frames"], p["tracked"]) for p in res.diagnostics["pieces"]]
    assert pieces[0][1] and pieces[-1][1] and pieces[-1][0][0] == 36  # the loss at walk frame 186
    ends = pieces[0][0][1]
    if len(pieces) == 3:
        (_, ends), (failing, lost), _ = [f for f, _ in pieces]
        assert not pieces[1][1] and abs(ends + 1 - corner) <= 5 and lost + 1 == 36
        assert res.diagnostics["pieces"][1]["why"] == "tracking was failing there before the camera was lost"
    else:
        assert len(pieces) == 2 and ends + 1 == 36
    assert [(b["before"], b["after"]) for b in res.diagnostics["scale_watch"]["breaks"] if b["kind"] == "lost"] \
        == [(ends, 36)]
    # Kept, the corner's frames come back farther off the truth than the frames before them.
    kept = track(failing_inlier=0.0)
    assert [p["frames"] for p in kept.diagnostics["pieces"]][0] == [0, 35]
    rot, trans, scale = align(kept.poses[:corner], walk.poses[:corner], "sim3")
    off = np.linalg.norm(scale * kept.poses[:36, :3, 3] @ rot.T + trans - walk.poses[:36, :3, 3], axis=1)
    before, during = off[:corner], off[corner:]
    assert np.median(during) > 1.5 * np.median(before) and during.max() > 1.5 * before.max(), np.round(off, 3)


def test_the_walkthrough_breaks_within_five_frames_of_its_cuts():
    """Issue 45's acceptance, with the joining switched off: the synthetic walk-through
    (320x240, 406 frames, simulated prior, intrinsics given) tracked as ``recon run`` tracks
    it (restarts after a loss) breaks into segments whose ends lie within 5 frames of the
    cuts the scene was built with (the corner, the fast turn): the nearer of where the
    segment before a break ends and where the next starts (frames between them get no pose),
    as ``benchmarks/walkthrough_breaks.py`` reports it. The plain corridor's break is a creep
    of the map's scale (``scale_watch``: ``drift``), called where the smoothed ratio has
    moved x1.3; how fast it moves follows the prior's noise and the machine's floating point
    (5, 13 and 23 frames after the cut on three machines), so that break must fall inside
    the textureless stretch, not before it and not after it. No break falls anywhere else."""
    from recon.synthetic import simulate_prior
    from recon.synthetic.walkthrough import render_walkthrough

    walk = render_walkthrough(320, 240, seed=0)
    res = estimate_poses(walk.rgb, simulate_prior(walk.depth, seed=1), walk.intrinsics, method="frontend",
                         progress=False, restart_after_loss=True)
    posed = np.isfinite(res.poses).all(axis=(1, 2))
    breaks = res.diagnostics["scale_watch"]["breaks"]
    ends = [int(np.flatnonzero(posed[: b["after"]])[-1]) for b in breaks]

    def near(cut: int) -> int:  # frames from the cut to the nearest break's nearer boundary
        return min(min(abs(e + 1 - cut), abs(b["after"] - cut)) for e, b in zip(ends, breaks))

    corridor, *sharp = walk.cuts
    first, stop = walk.stretches["textureless"]
    assert first == corridor
    in_textureless = [first - 5 <= b["after"] < stop for b in breaks]
    near_sharp = [min(min(abs(e + 1 - c), abs(b["after"] - c)) for c in sharp) <= 15 for e, b in zip(ends, breaks)]
    assert len(breaks) >= len(walk.cuts), breaks
    assert all(near(c) <= 5 for c in sharp) and any(in_textureless), (walk.cuts, ends, [b["after"] for b in breaks])
    called = [t or n for t, n, b in zip(in_textureless, near_sharp, breaks) if b["kind"] != "lost"]
    assert all(called), (walk.cuts, breaks)


def _stream(seq, prior, intrinsics, config=None):
    """StreamingFrontend fed the room frame by frame: (the front end, what add returned per
    frame, the result of finish with the frames read back from seq.rgb)."""
    from recon.poses.frontend.streaming import StreamingFrontend

    stream = StreamingFrontend(intrinsics, lambda i, frame: prior[i], config)
    live = [stream.add(i, frame) for i, frame in enumerate(seq.rgb)]
    return stream, live, stream.finish(lambda i: seq.rgb[i])


def test_streaming_frontend_gives_the_batch_poses_and_live_poses(pose_room):
    """Fed one frame at a time with the frames read back at the end, the streaming front end
    is the batch one (bit for bit); the poses add returns while tracking are the final ones
    up to the global BA and the metric scale."""
    from recon.poses.frontend.streaming import estimate_poses_frontend

    seq, prior = pose_room
    stream, live, res = _stream(seq, prior, seq.intrinsics)
    batch = estimate_poses_frontend(seq.rgb, lambda i, frame: prior[i], seq.intrinsics, progress=False)
    assert np.array_equal(res.poses, batch.poses)
    assert np.array_equal(res.keyframes, batch.keyframes) and np.array_equal(res.keyframe_depth, batch.keyframe_depth)
    assert res.diagnostics["frame_status"] == batch.diagnostics["frame_status"]
    status = [s for s, _ in live]
    assert status[0] == "keyframe" and np.array_equal(live[0][1], np.eye(4))
    assert set(status) <= {"keyframe", "tracked"} and status.count("keyframe") >= 3
    # Every frame add called a keyframe is one (a frame said "tracked" may become one later).
    assert set(res.keyframes.tolist()) >= {i for i, s in enumerate(status) if s == "keyframe"}
    poses = np.stack([p for _, p in live])
    assert poses.shape == (36, 4, 4) and np.isfinite(poses).all()
    # Before the global BA, the final non-keyframe alignment and the metric rescale: 13 mm
    # (2 % of the path) from the final poses after a Sim(3) alignment, the scale 8 % apart.
    length = path_length(res.poses)
    drift = ate_rmse(poses, res.poses, "sim3")
    assert drift["rmse"] <= 0.03 * length, f"live poses {drift['rmse']:.4f} m from the final ones ({length:.2f} m path)"
    assert 0.8 < drift["scale"] < 1.25
    assert rpe(poses, res.poses, delta=10)["rot_rmse_deg"] < 1.0  # the true 10-frame rotation is ~4 deg
    # Per non-keyframe the state keeps a few numbers and 4x4 poses, no images or flows.
    s = stream.state
    per_frame = [s.frame_T, s.rel, s.refs, s.status, s.inlier]
    tensors = [v for d in per_frame for v in d.values() if isinstance(v, torch.Tensor)]
    tensors += [x for d in per_frame for v in d.values() if isinstance(v, tuple) for x in v
                if isinstance(x, (torch.Tensor, np.ndarray))]
    assert all(t.numel() <= 16 for t in tensors)


def test_the_filler_takes_trackings_flow_from_the_park_instead_of_making_it_again(pose_room, monkeypatch):
    """With a park, finish makes one flow pair fewer per non-keyframe tracking aligned
    unseeded (the filler takes that flow, pooled, from the park) and returns the same poses
    bit for bit; a parked flow against another keyframe is not taken."""
    from recon.poses.frontend.park import MemoryPark
    from recon.poses.frontend.streaming import StreamingFrontend
    from recon.poses.matching import flow as fl

    seq, prior = pose_room
    made = []
    flow_pair = fl.flow_pair
    monkeypatch.setattr(fl, "flow_pair", lambda *args, **kwargs: made.append(1) or flow_pair(*args, **kwargs))
    results, flows = [], []
    for park in (None, MemoryPark()):
        stream = StreamingFrontend(seq.intrinsics, lambda i, frame: prior[i], park=park)
        for i, frame in enumerate(seq.rgb):
            stream.add(i, frame)
        made.clear()
        results.append(stream.finish(lambda i: seq.rgb[i]))
        flows.append(len(made))
    state = stream.state
    unseeded = [i for i, (_, seeded) in state.refs.items() if not seeded]
    assert len(unseeded) >= 20 and all(state.tracked_edge(i, state.refs[i][0]) is not None for i in unseeded)
    assert flows[0] - flows[1] == len(unseeded)
    assert np.array_equal(results[0].poses, results[1].poses)
    i = unseeded[0]
    assert state.tracked_edge(i, next(k for k in range(len(state.graph)) if k != state.refs[i][0])) is None


def test_finish_forgets_frames_from_stop_keyframes_included(pose_room):
    """finish(stop=...) (where a new piece takes over) forgets the later frames, keyframes and
    their edges included, and solves the rest again: poses of frames [0, stop) only, every
    keyframe before stop, as accurate as the front end given only those frames."""
    from recon.poses.frontend.streaming import StreamingFrontend

    seq, prior = pose_room
    _, _, whole = _stream(seq, prior, seq.intrinsics)
    stream = StreamingFrontend(seq.intrinsics, lambda i, frame: prior[i])
    for i, frame in enumerate(seq.rgb):
        stream.add(i, frame)
    stop = 24
    assert any(k >= stop for k in stream.state.graph.frames)
    res = stream.finish(lambda i: seq.rgb[i], stop=stop)
    assert res.poses.shape == (stop, 4, 4) and np.isfinite(res.poses).all()
    assert res.keyframes.max() < stop and set(res.keyframes.tolist()) == {k for k in whole.keyframes if k < stop}
    assert all(i < len(res.keyframes) and j < len(res.keyframes) for i, j in stream.state.graph.edges)
    assert len(res.diagnostics["frame_status"]) == stop and len(res.keyframe_depth) == len(res.keyframes)
    alone = estimate_poses(seq.rgb[:stop], prior[:stop], seq.intrinsics, method="frontend", progress=False)
    ate, ate_alone = (ate_rmse(p, seq.poses[:stop], "sim3")["rmse"] for p in (res.poses, alone.poses))
    assert ate <= ate_alone + 1e-3, (ate, ate_alone)  # 8.1 mm both, to the micrometre


def test_streaming_frontend_buffers_frames_for_the_focal_search(pose_room):
    """Without intrinsics the first 8 * calib_keyframes frames wait for the focal search;
    the frame that completes the buffer starts tracking, and the result is the batch one."""
    from recon.poses.frontend.streaming import StreamingFrontend, estimate_poses_frontend

    seq, prior = pose_room
    cfg = FrontendConfig(calib_keyframes=4)  # a 32-frame buffer, so that tracking starts mid-video
    stream, live, res = _stream(seq, prior, None, cfg)
    assert live[:31] == [("buffered", None)] * 31
    assert live[31][0] in ("keyframe", "tracked") and all(p is not None for _, p in live[31:])
    status, pose = stream.current(0)
    assert status == "keyframe" and np.array_equal(pose, np.eye(4))
    batch = estimate_poses_frontend(seq.rgb, lambda i, frame: prior[i], None, progress=False, config=cfg)
    assert np.array_equal(res.poses, batch.poses) and res.intrinsics == batch.intrinsics
    assert res.diagnostics["focal_search"] == batch.diagnostics["focal_search"]
    with pytest.raises(RuntimeError, match="twice"):
        stream.finish(lambda i: seq.rgb[i])
    with pytest.raises(ReconInputError, match="frame 2 given where frame 0 was expected"):
        StreamingFrontend(seq.intrinsics, prior).add(2, seq.rgb[2])
