"""The Schur complement of the dense BA (:mod:`recon.poses.ba.bundle`): the depths eliminated.

The depth block of the Gauss-Newton Hessian is diagonal (a pixel's inverse depth appears
only in its own residuals), so it is eliminated exactly, leaving the reduced camera system
(6 per pose, plus k1 when estimated); the depths follow by back-substitution (Triggs et al.,
"Bundle Adjustment - A Modern Synthesis", 2000, section 6.1; as in DROID-SLAM and COLMAP).
The input is what :mod:`recon.poses.ba.normal_equations` builds (its keys are documented there).
Shapes: K keyframes, E edges (ii, jj (E,)), P pixels per keyframe, N = K (+1 with k1) nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.geometry import lie

# Bytes of pose-depth couplings formed at once: a batch of keyframes at a time (the edges'
# couplings, their slots per keyframe, and the two products the complement takes of them).
COUPLING_BYTES = 96 * 2**20


@dataclass
class Couplings:
    """Per-keyframe pose-depth couplings, the layout the Schur complement works in.

    The depth of pixel p of keyframe k couples to pose k (through every edge leaving k) and
    to pose jj[e] of each edge e leaving k. B (L, 6 m, P) stacks those Jacobian products for
    each keyframe whose depths are free (rows (L,): their ids; a held depth couples to
    nothing): slot 0 is pose k (the sum over k's edges of -Ad(T_ij)^T Ej), slot s >= 1 the
    s-th edge leaving k (Ej), zero-padded to the largest out-degree n. When k1 is estimated it is
    node K, padded to a pose's 6 rows, in one last slot. pose (L, m) is the node each slot
    belongs to (padding points at k itself with zero coupling).
    """

    B: torch.Tensor
    pose: torch.Tensor
    rows: torch.Tensor

    @property
    def slots(self) -> int:
        return self.pose.shape[1]


def couplings(sys: dict, edge_ii: torch.Tensor, edge_jj: torch.Tensor, num_kf: int, rows: torch.Tensor
              ) -> Couplings:
    """The couplings of the keyframes `rows` (Couplings), from the normal equations `sys`
    of edges (edge_ii, edge_jj)."""
    K = num_kf
    L = rows.numel()
    on = {"device": rows.device}
    local = torch.full((K,), -1, dtype=torch.int64, **on)
    local[rows] = torch.arange(L, **on)
    # Edges leaving held depths (the window BA's) couple to nothing.
    keep = (local[edge_ii] >= 0).nonzero(as_tuple=True)[0]
    Ej, T_ij = sys["Ej"][keep], sys["Tij"][keep]
    ii, jj = local[edge_ii[keep]], edge_jj[keep]  # ii: the keyframe's row in B
    E, _, P = Ej.shape
    order = torch.argsort(ii, stable=True)
    counts = torch.bincount(ii, minlength=L)
    first = torch.cumsum(counts, 0) - counts
    slot = torch.empty(E, dtype=torch.int64, **on)
    slot[order] = torch.arange(E, **on) - first[ii[order]] + 1
    n = int(counts.max()) if E else 0
    m = n + 1 + ("Ek" in sys)
    B = torch.zeros(L, m, 6, P, dtype=Ej.dtype, **on)
    B[ii, slot] = Ej
    # Pose k enters each edge only through T_kj: its coupling is -Ad(T_kj)^T times the
    # edge's, summed over k's edges as one product over the slots.
    A = torch.zeros(L, m, 6, 6, dtype=Ej.dtype, **on)
    A[ii, slot] = -lie.adjoint(T_ij).transpose(1, 2).to(Ej.dtype)
    B[:, 0] = A.permute(0, 2, 1, 3).reshape(L, 6, 6 * m) @ B.reshape(L, 6 * m, P)
    pose = rows[:, None].repeat(1, m)
    pose[ii, slot] = jj
    if "Ek" in sys:
        B[:, -1, 0] = sys["Ek"][rows].to(Ej.dtype)
        pose[:, -1] = K
    return Couplings(B.reshape(L, 6 * m, P), pose, rows)


def reduced_system(
    sys: dict, ii: torch.Tensor, jj: torch.Tensor, Q: torch.Tensor, wz: torch.Tensor, num_kf: int,
    free_disp: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Schur complement over the depths: blocks S (N, N, 6, 6) and gradient g (N, 6). N = K
    poses, plus k1 as node K (its first row) when the system has it. free_disp (K,) bool:
    keyframes whose depths are eliminated (the others are held and drop out).

    Eliminating keyframe k's depths (diagonal Hessian 1 / Q) subtracts B_k Q_k B_k^T from
    the poses it couples to and B_k Q_k w_k from their gradient: one batched product over
    keyframes covers pose k, every edge target and every pair of edges leaving k. The
    keyframes go in batches (:func:`keyframe_batches`), so that a whole video's graph never
    holds every keyframe's couplings at once.
    """
    dt = Q.dtype
    K = num_kf
    N = K + ("Hkk" in sys)
    S = torch.zeros(N * N, 6, 6, dtype=dt, device=Q.device)
    S.index_add_(0, ii * N + ii, sys["Hii"])
    S.index_add_(0, ii * N + jj, sys["Hij"])
    S.index_add_(0, jj * N + ii, sys["Hij"].transpose(1, 2))
    S.index_add_(0, jj * N + jj, sys["Hjj"])
    g = torch.zeros(N, 6, dtype=dt, device=Q.device)
    g.index_add_(0, ii, sys["vi"])
    g.index_add_(0, jj, sys["vj"])
    if N > K:
        for pose, H in ((ii, sys["Hki"]), (jj, sys["Hkj"])):
            row = torch.zeros(len(ii), 6, 6, dtype=dt, device=Q.device)
            row[:, 0] = H
            S.index_add_(0, K * N + pose, row)
            S.index_add_(0, pose * N + K, row.transpose(1, 2))
        S[K * N + K, 0, 0] += sys["Hkk"]
        g[K, 0] += sys["vk"]

    for rows in keyframe_batches(sys, ii, free_disp):
        cpl = couplings(sys, ii, jj, K, rows)
        B, m, L = cpl.B, cpl.slots, rows.numel()
        blocks = ((B * Q[rows].to(B.dtype)[:, None, :]) @ B.transpose(1, 2)).to(dt)  # (L, 6m, 6m)
        blocks = blocks.reshape(L, m, 6, m, 6).permute(0, 1, 3, 2, 4).reshape(-1, 6, 6)
        r = cpl.pose[:, :, None].expand(L, m, m)
        c = cpl.pose[:, None, :].expand(L, m, m)
        S.index_add_(0, (r * N + c).reshape(-1), -blocks)
        gz = (B @ (Q[rows] * wz[rows]).to(B.dtype)[..., None])[..., 0].to(dt)  # (L, 6m)
        g.index_add_(0, cpl.pose.reshape(-1), -gz.reshape(-1, 6))
    return S.reshape(N, N, 6, 6), g


def keyframe_batches(sys: dict, ii: torch.Tensor, free_disp: torch.Tensor) -> list[torch.Tensor]:
    """The keyframes whose depths are free (free_disp (K,) bool), in batches whose
    couplings (and the two products formed from them) fit in COUPLING_BYTES."""
    rows = free_disp.nonzero(as_tuple=True)[0]
    if not rows.numel():
        return []
    Ej = sys["Ej"]
    slots = int(torch.bincount(ii, minlength=free_disp.numel()).max()) + 2
    per_keyframe = 4 * slots * Ej.shape[1] * Ej.shape[2] * Ej.itemsize
    size = max(1, COUPLING_BYTES // max(per_keyframe, 1))
    return list(rows.split(size))


def solve_spd(S: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """x with S x = g for a symmetric positive (semi)definite S (n, n), robust to near-singularity."""
    L, info = torch.linalg.cholesky_ex(S)
    if int(info) == 0:
        return torch.cholesky_solve(g[:, None], L)[:, 0]
    return torch.linalg.lstsq(S, g[:, None]).solution[:, 0]


def back_substitute(
    sys: dict, ii: torch.Tensor, jj: torch.Tensor, free_disp: torch.Tensor, dx: torch.Tensor, Q: torch.Tensor,
    wz: torch.Tensor,
) -> torch.Tensor:
    """The depth step dz (K, P) = Q (w - B^T dx) of the pose step dx (N, 6), over the poses
    each keyframe's depths couple to, batch by batch as in :func:`reduced_system` (the
    couplings formed again rather than kept); held keyframes get 0."""
    dz = torch.zeros_like(Q)
    for rows in keyframe_batches(sys, ii, free_disp):
        cpl = couplings(sys, ii, jj, Q.shape[0], rows)
        dx_slots = dx[cpl.pose].reshape(rows.numel(), -1, 1).to(cpl.B.dtype)
        rhs = wz[rows] - (cpl.B.transpose(1, 2) @ dx_slots)[..., 0].to(wz.dtype)
        dz[rows] = Q[rows] * rhs
    return dz
