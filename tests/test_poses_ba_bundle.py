"""The dense Schur-complement bundle adjustment (recon.poses.ba.bundle) on exact flow from the
synthetic room (conftest: pose_room): poses, depth and the lens' radial term recovered."""

from __future__ import annotations

import numpy as np
import torch

from recon.geometry import lie
from recon.geometry import projective as pj
from recon.geometry.lens import distort_images
from recon.poses.ba import bundle as ba
from recon.poses.ba import normal_equations


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


def _perturbed(seq, ids, k1, seed):
    """_exact_edges on the BA grid (30 x 40) and a ~1 cm, ~0.6 degree perturbation (K, 4, 4)
    of every pose but the first."""
    intr, depth, T_gt, edges = _exact_edges(seq, ids, 30, 40, k1=k1)
    noise = lie.se3_exp(torch.randn(len(ids), 6, generator=torch.Generator().manual_seed(seed),
                                    dtype=torch.float64) * 0.01)
    noise[0] = torch.eye(4)
    return intr, depth, T_gt, edges, noise


def test_dense_ba_calibrates_the_lens_radial_term(pose_room):
    """Flow measured through a barrel lens (k1 = -0.08): the BA, started as a pinhole camera
    from perturbed poses, finds k1 and the poses; held at k1 = 0 it cannot."""
    torch.set_num_threads(1)
    seq, _ = pose_room
    intr, depth, T_gt, edges, noise = _perturbed(seq, [0, 4, 8, 12, 16], -0.08, seed=4)
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


def test_dense_ba_recovers_poses_and_depth_from_exact_flow(pose_room):
    """Exact targets from ground truth; perturbed poses and prior depths converge back."""
    torch.set_num_threads(1)  # small tensors: threads only add synchronisation
    seq, prior = pose_room
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


def test_dense_ba_on_another_device_gives_the_same_answer(pose_room, device):
    """BAOptions.device: the solver runs there (lens estimated, pose tie on), inputs and
    results stay on the caller's device, and the answer is the CPU's up to round-off."""
    torch.set_num_threads(1)
    seq, _ = pose_room
    intr, depth, T_gt, edges = _exact_edges(seq, [0, 4, 8, 12], 30, 40, k1=-0.05)
    noise = lie.se3_exp(torch.randn(4, 6, generator=torch.Generator().manual_seed(5), dtype=torch.float64) * 0.01)
    disp = 1.0 / depth
    tie = ba.PosePrior(T_gt.clone(), torch.full((4, 6), 10.0, dtype=torch.float64))
    free = torch.zeros(4, dtype=torch.bool)

    def solve(device: str):
        opts = ba.BAOptions(iters=8, calibrate_k1=True, device=device)
        return ba.bundle_adjust(noise @ T_gt, disp.clone(), intr, edges, disp, torch.full_like(depth, 0.01), free,
                                opts, pose_prior=tie)

    T_cpu, D_cpu, report_cpu = solve("cpu")
    # "cpu:0" is another torch.device than "cpu": on a CPU-only machine it still runs the
    # path that moves the problem to the solver's device and the result back.
    T, D, report = solve("cpu:0" if device == "cpu" else device)
    assert T.device == T_gt.device and D.device == T_gt.device
    assert torch.allclose(T, T_cpu, atol=1e-9) and torch.allclose(D, D_cpu, rtol=1e-6)
    assert abs(report.k1 - report_cpu.k1) < 1e-9 and len(report.costs) == len(report_cpu.costs)


def test_dense_ba_in_keyframe_batches_gives_the_same_answer(pose_room, monkeypatch):
    """A long video's global BA forms the Schur complement a keyframe batch at a time and
    forms the pose-depth couplings again rather than holding them (memory); on a window
    with held depths and the lens estimated, that path must give the held path's answer."""
    torch.set_num_threads(1)
    seq, _ = pose_room
    intr, depth, T_gt, edges, noise = _perturbed(seq, [0, 4, 8, 12, 16], -0.05, seed=6)
    disp = 1.0 / depth
    held_depth = torch.tensor([True, False, False, False, False])

    def run():
        return ba.bundle_adjust(noise @ T_gt, disp * 1.05, intr, edges, disp, torch.full_like(depth, 0.01),
                                opts=ba.BAOptions(iters=6, calibrate_k1=True), fixed_disp=held_depth)

    T_held, D_held, rep_held = run()
    monkeypatch.setattr(normal_equations, "COUPLING_HOLD_BYTES", 0)
    monkeypatch.setattr(ba.schur, "COUPLING_BYTES", 1)  # one keyframe per batch
    T_batch, D_batch, rep_batch = run()
    # The same answer up to the float32 round-off of the per-pixel products (the batches
    # take other matrix kernels, and at convergence round-off decides whether a last tiny
    # step is taken): final costs within a millionth of where they started.
    assert rep_held.costs[-1] < 1e-3 * rep_held.costs[0]
    assert abs(rep_batch.costs[-1] - rep_held.costs[-1]) < 1e-6 * rep_held.costs[0]
    assert float((T_batch - T_held).abs().max()) < 1e-6
    assert float(((D_batch - D_held).abs() / D_held).max()) < 1e-4
    assert abs(rep_batch.k1 - rep_held.k1) < 1e-6


def test_whitened_ba_ignores_flow_along_the_directions_the_texture_does_not_measure(pose_room):
    """The aperture problem: at every pixel the flow is measured in one direction only (an
    edge's normal, random here), and along the other it is off by 1.5 BA pixels (DIS's guess
    on a plain corridor is biased, not noisy). Whitened by L = sqrt(2) n n^T (``Edges.whiten``,
    ``flow.flow_whitening`` of an edge), the BA finds the poses from perturbed ones as from
    exact flow; weighing both directions alike, the bias moves them by centimetres. Identity
    factors change nothing, and a window's remap keeps each keyframe's factors."""
    torch.set_num_threads(1)
    seq, _ = pose_room
    ids = [0, 4, 8, 12]
    intr, depth, T_gt, edges, noise = _perturbed(seq, ids, 0.0, seed=6)
    angle = torch.rand(len(ids), *depth.shape[1:], generator=torch.Generator().manual_seed(7),
                       dtype=torch.float64) * np.pi
    normal = torch.stack([torch.cos(angle), torch.sin(angle)], -1)  # (K, H, W, 2) the measured direction
    along = torch.stack([-torch.sin(angle), torch.cos(angle)], -1)
    biased = ba.Edges(edges.ii, edges.jj, edges.target + 1.5 * along[edges.ii], edges.weight)
    whiten = np.sqrt(2.0) * normal[..., :, None] * normal[..., None, :]
    disp = 1.0 / depth
    weight = torch.full_like(depth, 0.01)

    def error(e: ba.Edges) -> float:
        T, _, _ = ba.bundle_adjust(noise @ T_gt, disp.clone(), intr, e, disp, weight, opts=ba.BAOptions(iters=15))
        return float((lie.inv(T) - lie.inv(T_gt))[:, :3, 3].norm(dim=-1).max())

    whitened = error(ba.Edges(biased.ii, biased.jj, biased.target, biased.weight, whiten=whiten))
    plain = error(biased)
    assert whitened < 2e-3 and plain > 5 * whitened, (whitened, plain)
    identity = torch.eye(2, dtype=torch.float64).expand(*whiten.shape).clone()
    assert abs(error(ba.Edges(edges.ii, edges.jj, edges.target, edges.weight, whiten=identity)) - error(edges)) < 1e-7
    index = torch.tensor([-1, 0, 1, 2])  # keyframes 1..3 as a window
    window = biased.select(edges.ii > 0)
    window = ba.Edges(window.ii, window.jj, window.target, window.weight, whiten=whiten).remap(index)
    kept = edges.ii > 0
    assert torch.equal(window.whitening(slice(None), torch.float64),
                       whiten[edges.ii[kept]].reshape(int(kept.sum()), -1, 2, 2))
