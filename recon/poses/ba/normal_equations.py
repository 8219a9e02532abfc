"""The linearised system of the dense BA (:mod:`recon.poses.ba.bundle`): what one Gauss-Newton
step solves.

Per flow edge (:class:`Edges`) the residuals are linearised a chunk of edges at a time
(:class:`Linearisation`) into 6 x 6 pose blocks, per-pixel depth terms and the pose-depth
couplings that :mod:`recon.poses.ba.schur` eliminates the depths with; the couplings are
held up to COUPLING_HOLD_BYTES, else formed again where used (:class:`EdgeCouplings`). The
Huber weights are here too, shared with :mod:`recon.poses.ba.motion_only`.
Shapes: K keyframes, E edges, P pixels per keyframe; per-pixel terms are planes (pixels last).
More: docs/poses.md#the-dense-bundle-adjustment
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from recon.geometry import lie
from recon.geometry import projective as pj

# Residual pixels processed per chunk when building the normal equations; bounds the
# memory of the per-pixel Jacobians (~ 200 bytes per pixel-edge).
CHUNK_PIXELS = 400_000
# Pose-depth couplings (6 x P per edge) held from the normal equations to the depth step up
# to this size; a larger graph (a long video's global BA) forms them again per keyframe
# batch instead, at the cost of two more Jacobian passes per step.
COUPLING_HOLD_BYTES = 512 * 2**20


@dataclass
class Edges:
    """Directed frame-graph edges with their flow targets.

    ii, jj: (E,) int64 keyframe indices (source, target).
    target: (E, H, W, 2) pixel coordinates in jj of every BA pixel of ii (float32 or 64).
    weight: (E, H, W) confidence in [0, 1] (0 = no measurement).
    source: (H, W, 2) coordinates of the BA pixels themselves, shared by all keyframes (one
        camera); None for the pixel grid. Set by :meth:`undistorted`, which moves both
        ends into the pinhole image of a lens.
    whiten: (K, H, W, 2, 2) per keyframe and BA pixel, the factor L every residual from
        that keyframe (and its Jacobian) is multiplied by (``flow.flow_whitening``: its
        texture's information about the flow, L^T L), indexed by ii; None: the identity.
    """

    ii: torch.Tensor
    jj: torch.Tensor
    target: torch.Tensor
    weight: torch.Tensor
    source: torch.Tensor | None = None
    whiten: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.ii.numel())

    def source_pixels(self, dtype: torch.dtype) -> torch.Tensor:
        """(P, 2) coordinates of the BA pixels, in dtype."""
        if self.source is not None:
            return self.source.reshape(-1, 2).to(dtype)
        height, width = self.target.shape[1:3]
        return pj.pixel_grid(height, width, dtype=dtype, device=self.target.device).reshape(-1, 2)

    def to(self, device: torch.device | str) -> "Edges":
        source = None if self.source is None else self.source.to(device)
        whiten = None if self.whiten is None else self.whiten.to(device)
        return Edges(self.ii.to(device), self.jj.to(device), self.target.to(device), self.weight.to(device), source,
                     whiten)

    def select(self, mask: torch.Tensor | slice) -> "Edges":
        return Edges(self.ii[mask], self.jj[mask], self.target[mask], self.weight[mask], self.source, self.whiten)

    def remap(self, index: torch.Tensor) -> "Edges":
        """The same edges with keyframe ids replaced by index[id] (e.g. global -> window);
        the whitening goes with its keyframes."""
        whiten = self.whiten
        if whiten is not None:
            kept = torch.nonzero(index >= 0).squeeze(1)
            whiten = whiten.new_zeros(int(index.max()) + 1, *whiten.shape[1:])
            whiten[index[kept]] = self.whiten[kept]
        return Edges(index[self.ii], index[self.jj], self.target, self.weight, self.source, whiten)

    def whitening(self, index: slice | torch.Tensor, dtype: torch.dtype) -> torch.Tensor | None:
        """The factors (n, P, 2, 2) of the edges `index` in dtype (None: no whitening)."""
        if self.whiten is None:
            return None
        ii = self.ii[index]
        return self.whiten[ii].reshape(ii.numel(), -1, 2, 2).to(dtype)

    def undistorted(self, intr: torch.Tensor, k1: float) -> "Edges":
        """The same measurements in the pinhole image of a lens with radial term k1 (edges
        measured on the recorded images, source None)."""
        if k1 == 0.0:
            return self
        if self.source is not None:
            raise ValueError(
                "these edges are already in a pinhole image; undistorting them again would bend them twice"
            )
        height, width = self.target.shape[1:3]
        # In float64 whatever the edges are stored in (Newton steps), a chunk of edges at a
        # time (a global BA's float64 copy of every target would be a gigabyte).
        grid = pj.pixel_grid(height, width, dtype=torch.float64, device=self.target.device)
        intr = intr.to(torch.float64)
        target = torch.empty_like(self.target)
        for sl in chunks(len(self), height * width):
            target[sl] = pj.undistort(self.target[sl].double(), intr, k1)[0]
        return Edges(self.ii, self.jj, target, self.weight, pj.undistort(grid, intr, k1)[0], self.whiten)


def whitened(L: torch.Tensor | None, *planes: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Residual or Jacobian planes (n, 2, ..., P) multiplied pixel by pixel by the 2 x 2
    factors L (n, P, 2, 2) (``Edges.whiten``); unchanged when L is None."""
    if L is None:
        return planes
    out = []
    for x in planes:
        flat = x.reshape(x.shape[0], 2, -1, x.shape[-1])
        out.append(torch.einsum("npab,nbcp->nacp", L, flat).reshape(x.shape))
    return tuple(out)


def huber_weights(r_norm: torch.Tensor, delta: float) -> torch.Tensor:
    """IRLS weights (...) of the Huber loss for residual norms r_norm (...)."""
    return torch.where(r_norm <= delta, torch.ones_like(r_norm), delta / r_norm.clamp(min=1e-12))


def huber_cost(r_norm: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber loss (...) of residual norms (...), 0.5 r^2 inside delta, linear outside."""
    return torch.where(r_norm <= delta, 0.5 * r_norm * r_norm, delta * (r_norm - 0.5 * delta))


def chunks(num_edges: int, pixels: int) -> list[slice]:
    """Slices of the edges of a graph with `pixels` per edge, CHUNK_PIXELS pixel-edges each."""
    step = max(1, CHUNK_PIXELS // max(pixels, 1))
    return [slice(s, min(s + step, num_edges)) for s in range(0, num_edges, step)]


def pixel_sums(J: torch.Tensor, wgt: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """J^T W J (E, 6, 6) and J^T W r (E, 6) summed over pixels, of Jacobian planes J
    (E, 2, 6, P), weights (E, P) and residuals r (E, 2, P): one matrix product per residual
    row (u, v)."""
    wJ = J * wgt[:, None, None]
    JtJ = wJ[:, 0] @ J[:, 0].transpose(1, 2) + wJ[:, 1] @ J[:, 1].transpose(1, 2)
    Jtr = (wJ[:, 0] @ r[:, 0, :, None] + wJ[:, 1] @ r[:, 1, :, None])[..., 0]
    return JtJ, Jtr


@dataclass
class Linearisation:
    """The point one GN step linearises the reprojection residuals at, per chunk of edges.

    Tij: (E, 4, 4) relative poses and disp (K, P) inverse depths, both in the pixel dtype;
    uv: (1, P, 2) pinhole source pixels and duv (2, P) their derivative by k1 (None without
    k1); huber: the robust threshold the weights take.
    """

    Tij: torch.Tensor
    disp: torch.Tensor
    intr: torch.Tensor
    edges: Edges
    uv: torch.Tensor
    duv: torch.Tensor | None
    k1: float | None
    huber: float

    @classmethod
    def at(cls, Tij, disps, intr, edges: Edges, px: torch.dtype, huber: float, k1: float | None) -> "Linearisation":
        """At relative poses Tij (E, 4, 4) and inverse depths disps (K, H, W)."""
        intr_px = intr.to(px)
        duv = None
        if k1 is not None:
            uv, duv = pj.undistort(edges.source_pixels(px), intr_px, k1)
            duv = duv.T
        else:
            uv = edges.source_pixels(px)
        return cls(Tij.to(px), disps.reshape(disps.shape[0], -1).to(px), intr_px, edges, uv[None], duv, k1, huber)

    def chunk(self, index: slice | torch.Tensor) -> dict:
        """Residuals r (n, 2, P), robust weights wgt (n, P), the Jacobians Jj (n, 2, 6, P) by
        pose jj and Jz (n, 2, P) by the source depth, and with k1 Jk (n, 2, P) by k1, of the
        edges `index`."""
        ii, Tij = self.edges.ii[index], self.Tij[index]
        n = ii.numel()
        Xj = Tij @ pj.backproject(self.uv, self.disp[ii], self.intr).transpose(1, 2)
        proj, valid, Jj, Jz = pj.project_with_jacobians(Tij, Xj, self.intr)
        target = self.edges.target[index].reshape(n, -1, 2).to(Tij.dtype)
        out = {}
        if self.k1 is not None:
            target, dtarget = pj.undistort(target, self.intr, self.k1)
            # k1 moves the source ray and the measured target: d(proj - target) / d k1.
            out["Jk"] = pj.ray_jacobian(Tij, Xj, self.intr, self.duv) - dtarget.transpose(1, 2)
        r = target.transpose(1, 2) - proj
        L = self.edges.whitening(index, Tij.dtype)
        r, Jj, Jz = whitened(L, r, Jj, Jz)
        if "Jk" in out:
            (out["Jk"],) = whitened(L, out["Jk"])
        weight = self.edges.weight[index].reshape(n, -1).to(Tij.dtype)
        out.update(r=r, Jj=Jj, Jz=Jz, wgt=weight * valid * huber_weights(torch.hypot(r[:, 0], r[:, 1]), self.huber))
        return out

    def couplings(self, index: slice | torch.Tensor) -> torch.Tensor:
        """Ej (n, 6, P) = J_pose^T W J_depth for pose jj of the edges `index`."""
        c = self.chunk(index)
        return _couplings(c["Jj"], c["Jz"] * c["wgt"][:, None])


def _couplings(Jj: torch.Tensor, wJz: torch.Tensor) -> torch.Tensor:
    """Pose-depth couplings (n, 6, P) of Jacobian planes Jj (n, 2, 6, P) and weighted depth
    Jacobians wJz (n, 2, P): one product per residual row (u, v)."""
    return Jj[:, 0] * wJz[:, None, 0] + Jj[:, 1] * wJz[:, None, 1]


class EdgeCouplings:
    """The pose-depth couplings Ej (E, 6, P) of a system, indexed by edges: held when they
    fit in COUPLING_HOLD_BYTES, else formed again from the linearisation on each access (the
    Schur complement and the back-substitution take them a keyframe batch at a time), so
    that a long video's global BA does not hold a 6 x P block per edge."""

    def __init__(self, lin: Linearisation, held: torch.Tensor | None, shape: tuple[int, int, int],
                 itemsize: int):
        self.lin, self.held, self.shape, self.itemsize = lin, held, shape, itemsize

    def __getitem__(self, index: torch.Tensor) -> torch.Tensor:
        if self.held is not None:
            return self.held[index]
        if not index.numel():
            return torch.zeros(0, *self.shape[1:], dtype=self.lin.Tij.dtype, device=self.lin.Tij.device)
        return torch.cat([self.lin.couplings(index[sl]) for sl in chunks(index.numel(), self.shape[2])])


def normal_equations(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, edges: Edges, px: torch.dtype, huber: float,
    k1: float | None = None,
) -> dict:
    """Per-edge pose blocks, per-pixel depth terms and pose-depth couplings of the robust GN system.

    px: dtype of the per-pixel Jacobians; huber: the robust threshold (BA pixels). k1 None:
    the edges are already in the pinhole image. k1 a number: the edges are raw
    measurements, undistorted here with k1, which is one more unknown.
    Returns (K keyframes, E edges, P pixels):
        Hii, Hij, Hjj: (E, 6, 6) blocks of J^T W J for (ii, ii), (ii, jj), (jj, jj);
        vi, vj: (E, 6) J^T W r for the two poses;
        C, w: (K, P) depth diagonal and depth gradient (reprojection part only);
        Ej: :class:`EdgeCouplings` (E, 6, P), the pose-depth couplings J_pose^T W J_depth
            for pose jj (pose ii's are -Ad(T_ij)^T Ej, formed per keyframe in
            ``schur.couplings``);
        Tij: (E, 4, 4) the relative poses the system was linearised at;
    and with k1: Hkk, vk () for k1 itself, Hki, Hkj (E, 6) its couplings to the poses and
    Ek (K, P) to the depths. Per-pixel terms are planes (pixels last, ``projective``).
    """
    num_kf = disps.shape[0]
    P = disps[0].numel()
    E = len(edges)
    dt = T_cw.dtype
    calibrate = k1 is not None
    Tij = lie.relative(T_cw, edges.ii, edges.jj)
    lin = Linearisation.at(Tij, disps, intr, edges, px, huber, k1)
    itemsize = torch.empty((), dtype=px).element_size()
    hold = E * 6 * P * itemsize <= COUPLING_HOLD_BYTES
    on = {"device": T_cw.device}
    out = {
        "Hjj": torch.empty(E, 6, 6, dtype=dt, **on),
        "vj": torch.empty(E, 6, dtype=dt, **on),
        "C": torch.zeros(num_kf, P, dtype=dt, **on),
        "w": torch.zeros(num_kf, P, dtype=dt, **on),
    }
    held = torch.empty(E, 6, P, dtype=px, **on) if hold else None
    if calibrate:
        out.update(Hkk=torch.zeros((), dtype=dt, **on), vk=torch.zeros((), dtype=dt, **on),
                   Hkj=torch.empty(E, 6, dtype=dt, **on), Ek=torch.zeros(num_kf, P, dtype=dt, **on))
    for sl in chunks(E, P):
        ii = edges.ii[sl]
        c = lin.chunk(sl)
        Jj, Jz, r, wgt = c["Jj"], c["Jz"], c["r"], c["wgt"]
        JtJ, Jtr = pixel_sums(Jj, wgt, r)
        out["Hjj"][sl], out["vj"][sl] = JtJ.to(dt), Jtr.to(dt)
        wJz = Jz * wgt[:, None]  # (n, 2, P)
        if held is not None:
            held[sl] = _couplings(Jj, wJz)
        out["C"].index_add_(0, ii, (wJz * Jz).sum(1).to(dt))
        out["w"].index_add_(0, ii, (wJz * r).sum(1).to(dt))
        if calibrate:
            wJk = c["Jk"] * wgt[:, None]
            out["Hkk"] += (wJk * c["Jk"]).sum().to(dt)
            out["vk"] += (wJk * r).sum().to(dt)
            out["Hkj"][sl] = (Jj[:, 0] @ wJk[:, 0, :, None] + Jj[:, 1] @ wJk[:, 1, :, None])[..., 0].to(dt)
            out["Ek"].index_add_(0, ii, (wJk * Jz).sum(1).to(dt))
    out["Ej"] = EdgeCouplings(lin, held, (E, 6, P), itemsize)
    # Pose i enters only through T_ij, so its Jacobian is -Jj Ad(T_ij): map the sums per edge.
    A = lie.adjoint(Tij)
    At = A.transpose(1, 2)
    out["Hij"] = -(At @ out["Hjj"])
    out["Hii"] = At @ out["Hjj"] @ A
    out["Tij"] = Tij
    out["vi"] = -(At @ out["vj"][..., None])[..., 0]
    if calibrate:
        out["Hki"] = -(out["Hkj"][:, None, :] @ A)[:, 0]
    return out
