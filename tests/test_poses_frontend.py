"""The dense pose front end on the synthetic room: accuracy, metric scale, focal search,
tracking loss; and the geometry it rests on (Lie maps, Jacobians, Schur-complement BA)."""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import pytest
import torch

from recon.errors import ReconInputError
from recon.eval.trajectory import ate_rmse, path_length, rpe, scale_error
from recon.lens import distort_images
from recon.poses import TrackingLostError, estimate_poses, intrinsics_from_fov
from recon.poses import ba, lie
from recon.poses import flow as fl
from recon.poses.frontend import FrontendConfig
from recon.poses.sfm import SfMConfig
from recon.poses import projective as pj
from recon.synthetic import render_sequence, simulate_prior


@pytest.fixture(scope="module")
def room():
    seq = render_sequence(36, 320, 240, seed=0)
    return seq, simulate_prior(seq.depth, seed=1)


# --------------------------------------------------------------------------- geometry


def test_se3_exp_log_round_trip_and_adjoint():
    g = torch.Generator().manual_seed(0)
    xi = torch.randn(64, 6, generator=g, dtype=torch.float64) * torch.tensor([1, 1, 1, 0.8, 0.8, 0.8])
    xi[:4, 3:] *= 1e-6  # small-angle branch
    T = lie.se3_exp(xi)
    assert torch.allclose(lie.se3_log(T), xi, atol=1e-9)
    assert torch.allclose(lie.inv(T) @ T, torch.eye(4, dtype=torch.float64).expand(64, 4, 4), atol=1e-12)
    d = torch.randn(64, 6, generator=g, dtype=torch.float64) * 0.1
    assert torch.allclose(T @ lie.se3_exp(d) @ lie.inv(T), lie.se3_exp((lie.adjoint(T) @ d[..., None])[..., 0]),
                          atol=1e-10)


def test_projection_jacobians_match_finite_differences():
    g = torch.Generator().manual_seed(1)
    intr = torch.tensor([80.0, 82.0, 39.5, 29.5], dtype=torch.float64)
    Tij = lie.se3_exp(torch.randn(3, 6, generator=g, dtype=torch.float64) * 0.1)
    uv = torch.rand(3, 50, 2, generator=g, dtype=torch.float64) * torch.tensor([80.0, 60.0])
    disp = 0.2 + torch.rand(3, 50, generator=g, dtype=torch.float64)
    X = pj.backproject(uv, disp, intr)
    proj, valid, Jj, Jz = pj.reproject_with_jacobians(Tij, X.transpose(1, 2), intr)
    proj, Jj, Jz = proj.transpose(1, 2), Jj.permute(0, 3, 1, 2), Jz.transpose(1, 2)  # planes -> per pixel
    assert valid.all()
    eps = 1e-6
    for k in range(6):
        step = torch.zeros(6, dtype=torch.float64)
        step[k] = eps
        moved, _ = pj.project(pj.transform(lie.se3_exp(step)[None] @ Tij, X), intr)
        assert torch.allclose((moved - proj) / eps, Jj[..., k], atol=1e-3)
    Xd = pj.backproject(uv, disp + eps, intr)
    moved, _ = pj.project(pj.transform(Tij, Xd), intr)
    assert torch.allclose((moved - proj) / eps, Jz, atol=1e-3)


def test_undistort_inverts_the_lens_and_its_derivatives_match_finite_differences():
    intr = torch.tensor([80.0, 82.0, 39.5, 29.5], dtype=torch.float64)
    uv = pj.pixel_grid(60, 80)
    eps = 1e-6
    for k1 in (-0.15, 0.0, 0.1):
        pinhole, d_k1 = pj.undistort(uv, intr, k1)
        assert torch.allclose(pj.distort(pinhole, intr, k1), uv, atol=1e-6)
        moved = pj.undistort(uv, intr, k1 + eps)[0]
        assert torch.allclose((moved - pinhole) / eps, d_k1, atol=1e-4)
    # Moving the source pixels moves their projections by ray_jacobian (depth held).
    g = torch.Generator().manual_seed(3)
    Tij = lie.se3_exp(torch.randn(2, 6, generator=g, dtype=torch.float64) * 0.1)
    src = torch.rand(50, 2, generator=g, dtype=torch.float64) * torch.tensor([80.0, 60.0])
    dray = torch.randn(50, 2, generator=g, dtype=torch.float64)
    disp = 0.2 + torch.rand(2, 50, generator=g, dtype=torch.float64)
    X = pj.backproject(src, disp, intr)
    proj, _ = pj.project(pj.transform(Tij, X), intr)
    moved, _ = pj.project(pj.transform(Tij, pj.backproject(src + eps * dray, disp, intr)), intr)
    Jray = pj.ray_jacobian(Tij, pj.transform(Tij, X).transpose(1, 2), intr, dray.T)
    assert torch.allclose((moved - proj) / eps, Jray.transpose(1, 2), atol=1e-4)


def _exact_edges(seq, ids, h, w, k1=0.0):
    """BA-grid poses, depth, intrinsics and exact flow edges (measured through a lens k1)."""
    intr = torch.tensor(pj.scale_intrinsics(seq.intrinsics, w / seq.rgb.shape[2]), dtype=torch.float64)
    s = seq.rgb.shape[2] // w
    depth = torch.from_numpy(np.stack([seq.depth[i][s // 2 :: s, s // 2 :: s] for i in ids])).double()
    T_gt = torch.from_numpy(np.linalg.inv(seq.poses[ids]))
    ii, jj = zip(*[(a, b) for a in range(len(ids)) for b in range(len(ids)) if a != b and abs(a - b) <= 2])
    ii, jj = torch.tensor(ii), torch.tensor(jj)
    # A lens moves the pixels themselves too: the BA pixel at recorded position p sees the
    # pinhole ray of undistort(p), whose depth is read there.
    source, _ = pj.undistort(pj.pixel_grid(h, w), intr, k1)
    grid_depth = torch.from_numpy(distort_images(depth.numpy(), intr.tolist(), k1, nearest=True))
    target, valid = pj.reproject(T_gt, 1.0 / grid_depth, intr, ii, jj, source)
    edges = ba.Edges(ii, jj, pj.distort(target, intr, k1), valid.double())
    return intr, grid_depth, T_gt, edges


def test_dis_flow_does_not_depend_on_earlier_calls(room):
    """A seeded DIS call must not change a later unseeded one (OpenCV keeps state in the
    instance; shared instances made front-end results depend on what ran before)."""
    seq, _ = room
    cfg = fl.FlowConfig()
    a, b, c = (fl.prepare_gray(seq.rgb[i], (320, 240)) for i in (0, 3, 9))
    first = fl.dis_flow(a, b, cfg)
    fl.dis_flow(a, c, cfg, init=2.0 * first + 5.0)
    np.testing.assert_array_equal(fl.dis_flow(a, b, cfg), first)


def test_dense_ba_calibrates_the_lens_radial_term(room):
    """Flow measured through a barrel lens (k1 = -0.08): the BA, started as a pinhole camera
    from perturbed poses, finds k1 and the poses; held at k1 = 0 it cannot."""
    torch.set_num_threads(1)
    seq, _ = room
    intr, depth, T_gt, edges = _exact_edges(seq, [0, 4, 8, 12, 16], 30, 40, k1=-0.08)
    noise = lie.se3_exp(torch.randn(5, 6, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.01)
    noise[0] = torch.eye(4)
    disp = 1.0 / depth
    weight = torch.full_like(depth, 0.01)
    errors = {}
    for calibrate in (True, False):
        T, _, report = ba.bundle_adjust(noise @ T_gt, disp.clone(), intr, edges, disp, weight,
                                        opts=ba.BAOptions(iters=20, calibrate_k1=calibrate))
        errors[calibrate] = float((lie.inv(T) - lie.inv(T_gt))[:, :3, 3].norm(dim=-1).max())
        if calibrate:
            assert abs(report.k1 + 0.08) < 0.004, report.k1
    assert errors[True] < 2e-3, errors  # metres
    assert errors[False] > 2 * errors[True], errors


def test_dense_ba_recovers_poses_and_depth_from_exact_flow(room):
    """Exact targets from ground truth; perturbed poses and prior depths converge back."""
    torch.set_num_threads(1)  # small tensors: threads only add synchronisation
    seq, prior = room
    ids = [0, 4, 8, 12]
    intr, depth, T_gt, edges = _exact_edges(seq, ids, 30, 40)
    noise = lie.se3_exp(torch.randn(4, 6, generator=torch.Generator().manual_seed(2), dtype=torch.float64) * 0.01)
    noise[0] = torch.eye(4)
    prior_disp = 1.0 / torch.from_numpy(np.stack([prior[i][4::8, 4::8] for i in ids])).double()
    T, D, report = ba.bundle_adjust(noise @ T_gt, prior_disp.clone(), intr, edges, 1.0 / depth,
                                    torch.full_like(depth, 0.01), opts=ba.BAOptions(iters=15))
    err = (lie.inv(T) - lie.inv(T_gt))[:, :3, 3].norm(dim=-1)
    assert float(err.max()) < 2e-3  # metres; the perturbation was ~1 cm
    assert report.costs[-1] < 1e-3 * report.costs[0]
    assert float(((1 / D - depth).abs() / depth).median()) < 0.01


# --------------------------------------------------------------------------- front end


def test_frontend_synthetic_accuracy_and_metric_scale(room):
    seq, prior = room
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


def test_frontend_calibrates_a_barrel_lens(room):
    """The room filmed through a barrel lens (k1 = -0.1, 4 % at the corners): the front end
    finds k1 and keeps the path and scale; as a pinhole camera the scale is 19 % off."""
    seq, prior = room
    rgb = distort_images(seq.rgb, seq.intrinsics, -0.1)
    depth = distort_images(prior, seq.intrinsics, -0.1, nearest=True)
    length = path_length(seq.poses)
    res = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False)
    assert abs(res.diagnostics["lens_k1"] + 0.1) < 0.02, res.diagnostics["lens_k1"]
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.01 * length
    assert scale_error(res.poses, seq.poses) <= 0.10
    pinhole = estimate_poses(rgb, depth, seq.intrinsics, method="frontend", progress=False,
                             config=replace(FrontendConfig(), calibrate_lens=False))
    assert scale_error(pinhole.poses, seq.poses) > 0.10


def test_frontend_estimates_focal_length_when_intrinsics_are_withheld(room):
    seq, prior = room
    res = estimate_poses(seq.rgb, prior, None, method="frontend", progress=False)
    f_true = seq.intrinsics[0]
    assert abs(res.intrinsics[0] / f_true - 1) <= 0.05, (res.intrinsics, f_true)
    assert res.diagnostics["focal_search"]["bracketed"]
    length = path_length(seq.poses)
    assert ate_rmse(res.poses, seq.poses, "sim3")["rmse"] <= 0.02 * length


def test_tracking_loss_names_the_frame(room):
    seq, prior = room
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, size=(14, 240, 320, 3), dtype=np.uint8)
    frames = np.concatenate([seq.rgb[:12], noise])
    depth = np.concatenate([prior[:12], prior[:14]])
    with pytest.raises(TrackingLostError, match="tracking lost at frame 12") as info:
        estimate_poses(frames, depth, seq.intrinsics, method="frontend", progress=False)
    assert info.value.frame == 12


def test_previous_frame_becomes_a_keyframe_when_the_reference_fails(room):
    """A frame that cannot be aligned to its reference keyframe (here: the keyframe's image
    is corrupted) is aligned to the previous frame, which becomes a keyframe."""
    from recon.poses.frontend_config import FrontendConfig, make_geometry
    from recon.poses.result import PriorSource
    from recon.poses.track_state import TrackState
    from recon.poses.tracker import Tracker

    seq, prior = room
    height, width = seq.rgb.shape[1:3]
    cfg = FrontendConfig()
    state = TrackState(seq.intrinsics, make_geometry(width, height, cfg.ba_stride), PriorSource(prior), cfg)
    tracker = Tracker(state)
    tracker.start(0, seq.rgb[0])
    for i in (1, 2, 3):
        tracker.track(i, seq.rgb[i])
    assert state.graph.frames == [0]
    noise = np.random.default_rng(0).integers(0, 256, size=state.graph.gray[0].shape, dtype=np.uint8)
    state.graph.gray[0] = noise
    tracker.track(4, seq.rgb[4])
    assert state.graph.frames == [0, 3] and state.status[4] == "tracked"
    T_est = np.linalg.inv(state.frame_T[4].numpy())
    T_gt = np.linalg.inv(seq.poses[0]) @ seq.poses[4]
    # While tracking, the metric scale of a two-keyframe map is provisional: check the
    # direction of travel and the rotation.
    cos = T_est[:3, 3] @ T_gt[:3, 3] / (np.linalg.norm(T_est[:3, 3]) * np.linalg.norm(T_gt[:3, 3]))
    assert cos > 0.95
    dR = T_est[:3, :3].T @ T_gt[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.8  # of ~1.6 deg turned


def test_auto_falls_back_to_sfm_when_tracking_is_lost(room, monkeypatch, capsys, caplog):
    seq, prior = room
    import recon.poses.frontend as fe
    import recon.poses.sfm as sfm

    def lost(*args, **kwargs):
        raise TrackingLostError("tracking lost at frame 7: test", frame=7)

    sentinel = fe.PoseResult(np.tile(np.eye(4), (36, 1, 1)), seq.intrinsics, np.arange(36), 0.0, {"method": "sfm"})
    monkeypatch.setattr(fe, "estimate_poses_frontend", lost)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", lambda *a, **k: sentinel)
    res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=True)
    assert res.diagnostics["fallback"]["frame"] == 7
    said = capsys.readouterr()
    assert "falling back to SfM" in said.out and said.err == ""  # said once
    with caplog.at_level(logging.WARNING, logger="recon"):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False)
    assert capsys.readouterr().out == ""
    assert [r.getMessage() for r in caplog.records] == [
        "front end failed (tracking lost at frame 7: test); the poses are from the SfM fallback (pycolmap)"]

    def sfm_fails(*args, **kwargs):
        raise TrackingLostError("SfM registered only 0 of 4 keyframes")

    monkeypatch.setattr(sfm, "estimate_poses_sfm", sfm_fails)
    with pytest.raises(TrackingLostError, match=r"front end failed \(tracking lost at frame 7: test\), and so did the "
                                                r"SfM fallback \(SfM registered only 0") as info:
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False)
    assert info.value.frame == 7
    with pytest.raises(TrackingLostError):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)


def test_bad_inputs_raise_one_line_errors(room):
    seq, prior = room
    with pytest.raises(ReconInputError, match="pose method"):
        estimate_poses(seq.rgb, prior, method="slam")
    with pytest.raises(ReconInputError, match="prior depth has 5 frames"):
        estimate_poses(seq.rgb[:8], prior[:5], seq.intrinsics, method="frontend", progress=False)
    with pytest.raises(ReconInputError, match="unknown pose option"):
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, bogus=1)
    with pytest.raises(ReconInputError, match="ba_stride must be >= 1, got 0"):  # was a ZeroDivisionError
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, config=FrontendConfig(ba_stride=0))
    with pytest.raises(ReconInputError, match="window must be >= 1"):  # the SfM's own front-end settings too
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, method="sfm", sfm_config=SfMConfig(frontend=FrontendConfig(window=0)))
    with pytest.raises(ReconInputError, match="positive focal"):
        estimate_poses(seq.rgb[:8], prior[:8], (0, 0, 1, 1))
    f = intrinsics_from_fov(90.0, 640, 480)
    assert f[0] == pytest.approx(320.0) and f[2] == 319.5
