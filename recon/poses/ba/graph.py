"""The keyframe graph of the front end (as in DROID-SLAM's ``factor_graph``): keyframe state,
directed flow edges, and the choice of which keyframes to connect.

:class:`FrameGraph` holds per keyframe its video frame, flow-resolution grey image,
world-to-camera pose, BA-grid inverse depth and prior; per directed edge (i, j) its flow
target and confidence on the BA grid and its kind ("temporal", "proximity", "reloc").
The functions here measure induced flow (DROID's frame distance) to pick proximity edges
and predict the flow that seeds DIS on long edges.
More: docs/poses.md#the-front-ends-parts
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from recon.geometry import lie
from recon.geometry import projective as pj
from recon.poses.ba import bundle as ba


@dataclass
class EdgeData:
    """One directed edge: BA-grid target (H, W, 2) float32 in j's pixels, weight (H, W) float32."""

    target: torch.Tensor
    weight: torch.Tensor
    kind: str


class FrameGraph:
    """Keyframes and directed edges. Keyframe ids are positions 0..K-1 in insertion order."""

    def __init__(self, ba_shape: tuple[int, int]):
        self.ba_shape = ba_shape
        self.frames: list[int] = []
        self.gray: list[np.ndarray] = []
        self._T: list[torch.Tensor] = []
        self._disp: list[torch.Tensor] = []
        self._prior: list[torch.Tensor] = []
        self._prior_w: list[torch.Tensor] = []
        self._whiten: list[torch.Tensor | None] = []
        self.edges: dict[tuple[int, int], EdgeData] = {}

    # ------------------------------------------------------------------ keyframes

    def __len__(self) -> int:
        return len(self.frames)

    def add_keyframe(self, frame: int, gray: np.ndarray, T_cw: torch.Tensor, disp: torch.Tensor,
                     prior: torch.Tensor, prior_w: torch.Tensor, whiten: torch.Tensor | None = None) -> int:
        """Append a keyframe; returns its id. whiten: (h, w, 2, 2) the factor of residuals
        of edges from it (``flow.flow_whitening``), or None."""
        self.frames.append(int(frame))
        self._whiten.append(whiten)
        self.gray.append(gray)
        self._T.append(T_cw.clone())
        self._disp.append(disp.clone())
        self._prior.append(prior)
        self._prior_w.append(prior_w)
        return len(self.frames) - 1

    def poses(self, ids=None) -> torch.Tensor:
        """World-to-camera poses (K, 4, 4) float64 of `ids` (all when None)."""
        ids = range(len(self)) if ids is None else ids
        return torch.stack([self._T[i] for i in ids])

    def disps(self, ids=None) -> torch.Tensor:
        ids = range(len(self)) if ids is None else ids
        return torch.stack([self._disp[i] for i in ids])

    def priors(self, ids=None) -> tuple[torch.Tensor, torch.Tensor]:
        ids = range(len(self)) if ids is None else ids
        return torch.stack([self._prior[i] for i in ids]), torch.stack([self._prior_w[i] for i in ids])

    def whitening(self, ids=None) -> torch.Tensor | None:
        """(K, h, w, 2, 2) the keyframes' residual factors (``ba.Edges.whiten``), None
        when they have none."""
        ids = range(len(self)) if ids is None else ids
        factors = [self._whiten[i] for i in ids]
        return None if any(f is None for f in factors) else torch.stack(factors)

    def drop_from(self, k: int) -> None:
        """Forget keyframes k, k+1, ... and every edge that touches one of them."""
        for keyframes in (self.frames, self.gray, self._T, self._disp, self._prior, self._prior_w, self._whiten):
            del keyframes[k:]
        self.edges = {p: e for p, e in self.edges.items() if p[0] < k and p[1] < k}

    def set_state(self, ids, T_cw: torch.Tensor, disps: torch.Tensor) -> None:
        for n, i in enumerate(ids):
            self._T[i] = T_cw[n].clone()
            self._disp[i] = disps[n].clone()

    def scale_world(self, s: float) -> None:
        """Multiply the world by s (translations x s, inverse depths / s, priors unchanged)."""
        for i in range(len(self)):
            self._T[i] = self._T[i].clone()
            self._T[i][:3, 3] *= s
            self._disp[i] = self._disp[i] / s

    # ------------------------------------------------------------------ edges

    def add_edge(self, i: int, j: int, target: torch.Tensor, weight: torch.Tensor, kind: str) -> None:
        self.edges[(int(i), int(j))] = EdgeData(target.float(), weight.float(), kind)

    def remove_edge(self, i: int, j: int) -> None:
        self.edges.pop((int(i), int(j)), None)

    def connected(self, i: int, j: int) -> bool:
        return (i, j) in self.edges or (j, i) in self.edges

    def neighbours(self, k: int) -> set[int]:
        return {j for (i, j) in self.edges if i == k} | {i for (i, j) in self.edges if j == k}

    def edge_list(self, ids=None) -> tuple[list[tuple[int, int]], "ba.Edges"]:
        """Edges with at least one end in `ids` (all when None), as global-id ba.Edges
        (float32, as measured: a long video's global BA stacks every edge)."""
        keep = None if ids is None else set(int(i) for i in ids)
        pairs = [p for p in self.edges if keep is None or p[0] in keep or p[1] in keep]
        if not pairs:
            h, w = self.ba_shape
            empty = torch.zeros(0, dtype=torch.int64)
            return [], ba.Edges(empty, empty, torch.zeros(0, h, w, 2), torch.zeros(0, h, w))
        ii = torch.tensor([p[0] for p in pairs])
        jj = torch.tensor([p[1] for p in pairs])
        target = torch.stack([self.edges[p].target for p in pairs])
        weight = torch.stack([self.edges[p].weight for p in pairs])
        if len(pairs) == len(self.edges):
            # Every edge at once (the global BA): the graph keeps views of the stack
            # instead of its own copies, so that the edges are held once, not twice.
            for n, p in enumerate(pairs):
                self.edges[p].target, self.edges[p].weight = target[n], weight[n]
        return pairs, ba.Edges(ii, jj, target, weight)

    def kinds(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for e in self.edges.values():
            out[e.kind] = out.get(e.kind, 0) + 1
        return out


def _landing(X: torch.Tensor, rel: torch.Tensor, intr: torch.Tensor, height: int, width: int
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels (C, M, 2) where homogeneous points X (C, M, 4) land under transforms rel
    (C, 4, 4), and whether they land inside a (height, width) image, in front (C, M)."""
    proj, valid = pj.project(pj.transform(rel, X), intr)
    inside = (valid & (proj[..., 0] > -0.5) & (proj[..., 0] < width - 0.5)
              & (proj[..., 1] > -0.5) & (proj[..., 1] < height - 0.5))
    return proj, inside


def _mean_inside(values: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
    """Mean (C,) of values (C, M) over the pixels inside; inf where none is."""
    mean = torch.where(inside, values, torch.zeros_like(values)).sum(1) / inside.sum(1).clamp(min=1)
    return torch.where(inside.any(1), mean, torch.full_like(mean, float("inf")))


def induced_flow(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, k: int, others: torch.Tensor, stride: int = 4
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean induced flow (C,) in BA pixels from keyframe k to each of `others` (C,), and the
    fraction (C,) of k's (subsampled) pixels that land inside the other image in front of it.

    T_cw: (K, 4, 4); disps: (K, H, W). Pixels are taken every `stride` on the BA grid.
    """
    height, width = disps.shape[-2:]
    sub = disps[k, ::stride, ::stride]
    uv = pj.pixel_grid(height, width, dtype=T_cw.dtype)[::stride, ::stride]
    X = pj.backproject(uv, sub.double(), intr).reshape(1, -1, 4).expand(len(others), -1, -1)
    proj, inside = _landing(X, T_cw[others] @ lie.inv(T_cw[k : k + 1]), intr, height, width)
    move = (proj - uv.reshape(1, -1, 2)).norm(dim=-1)
    return _mean_inside(move, inside), inside.double().mean(1)


def parallax_into(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, T: torch.Tensor, stride: int = 4
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean parallax (C,) and mean induced flow (C,) in BA pixels from each of C keyframes
    (T_cw (C, 4, 4), disps (C, H, W)) into a camera at world-to-camera pose T (4, 4), and the
    fraction (C,) of their (subsampled) pixels that land inside it, in front.

    Parallax is the induced flow minus the flow of points at infinity (the rotation's part),
    the keyframe policy's measure (``motion_filter``) predicted from the map instead of
    measured. Pixels are taken every `stride` on the BA grid.
    """
    height, width = disps.shape[-2:]
    uv = pj.pixel_grid(height, width, dtype=T_cw.dtype)[::stride, ::stride]
    X = pj.backproject(uv[None], disps[:, ::stride, ::stride].double(), intr).reshape(len(T_cw), -1, 4)
    rel = T[None] @ lie.inv(T_cw)
    proj, inside = _landing(X, rel, intr, height, width)
    at_infinity = X.clone()
    at_infinity[..., 3] = 0.0
    rotated, _ = pj.project(pj.transform(rel, at_infinity), intr)
    move = (proj - uv.reshape(1, -1, 2)).norm(dim=-1)
    parallax = (proj - rotated).norm(dim=-1)
    return _mean_inside(parallax, inside), _mean_inside(move, inside), inside.double().mean(1)


def select_proximity(
    candidates: list[int], dist: np.ndarray, frac: np.ndarray, max_edges: int, max_dist: float,
    min_overlap: float, nms: int,
) -> list[int]:
    """Up to `max_edges` candidate keyframes, nearest first, with dist <= max_dist and overlap
    >= min_overlap, none within `nms` keyframe ids of an already chosen one."""
    order = np.argsort(dist)
    chosen: list[int] = []
    for n in order:
        if len(chosen) >= max_edges:
            break
        if not (dist[n] <= max_dist and frac[n] >= min_overlap):
            continue
        c = candidates[n]
        if any(abs(c - o) <= nms for o in chosen):
            continue
        chosen.append(c)
    return chosen


def predicted_flow(
    T_cw: torch.Tensor, disps: torch.Tensor, intr: torch.Tensor, i: int, j: int, flow_shape: tuple[int, int],
    k1: float = 0.0,
) -> np.ndarray:
    """Flow (hf, wf, 2) float32 from keyframe i to j at the flow resolution predicted by the
    current poses and BA depth, between the recorded images of a lens with radial term k1
    (a seed for DIS); points behind j keep zero flow."""
    height, width = disps.shape[-2:]
    grid = pj.pixel_grid(height, width, dtype=disps.dtype)
    source, _ = pj.undistort(grid, intr, k1)
    uv, valid = pj.reproject(T_cw, disps, intr, torch.tensor([i]), torch.tensor([j]), source)
    flow = (pj.distort(uv[0], intr, k1) - grid) * valid[0, ..., None]
    hf, wf = flow_shape
    scale = np.array([wf / width, hf / height], dtype=np.float32)
    up = cv2.resize(flow.numpy().astype(np.float32), (wf, hf), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(up * scale)


def seed_flows(T_kf: torch.Tensor, T: torch.Tensor, disp_kf: torch.Tensor, intr: torch.Tensor,
               flow_shape: tuple[int, int], k1: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Flows (hf, wf, 2) from a keyframe (pose T_kf (4, 4), BA depth disp_kf (H, W)) to a frame
    at pose T (4, 4) and back, as its depth predicts them (which stands in for the frame's
    on the way back): DIS seeds for a frame whose motion is beyond DIS's unseeded reach."""
    T_pair, D_pair = torch.stack([T_kf, T]), torch.stack([disp_kf, disp_kf])
    return (predicted_flow(T_pair, D_pair, intr, 0, 1, flow_shape, k1),
            predicted_flow(T_pair, D_pair, intr, 1, 0, flow_shape, k1))
