"""The plane sweep around a depth map: hypotheses, matching cost, winner.

Each reference pixel tries ``M`` depths ``D(p) * exp(s_k)`` in a band of log offsets around
its current depth, scored by the zero-mean NCC of its patch with the source image sampled
where the hypothesis sends the patch's pixels (the patch follows the current surface, as in
COLMAP's and OpenMVS's patch-based stereo, without their normal search). A texture floor,
``cov / sqrt((var_r + f^2)(var_w + f^2))``, keeps flat patches from winning confident
matches. Box filters use integral images, so the patch size costs nothing.
More: docs/depth.md#how-the-refinement-works
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from medea_core.geometry import intrinsics_matrix, pixel_grid


def box_mean(maps: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over (2 radius + 1)^2 windows, borders replicated (so that the image edge is no texture).

    Computed by integral images (the cost does not grow with the window), in two buffers
    written in place: fresh image-sized temporaries cost more than the sums themselves.

    Args:
        maps: (..., H, W) maps.
        radius: window half-size in pixels.

    Returns:
        (..., H, W) window means.
    """
    k = 2 * radius + 1
    height, width = maps.shape[-2:]
    flat = maps.reshape(-1, height, width)
    # Integral image of the replicate-padded maps, with a zero row and column in front.
    padded = flat.new_empty(flat.shape[0], height + k, width + k)
    padded[:, 0] = 0.0
    padded[:, :, 0] = 0.0
    inner = padded[:, 1:, 1:]
    inner[:, radius : radius + height, radius : radius + width] = flat
    inner[:, radius : radius + height, :radius] = flat[:, :, :1]
    inner[:, radius : radius + height, radius + width :] = flat[:, :, -1:]
    inner[:, :radius] = inner[:, radius : radius + 1]
    inner[:, radius + height :] = inner[:, radius + height - 1 : radius + height]
    padded.cumsum_(-1)
    rows = torch.sub(padded[..., k:], padded[..., :-k]).cumsum_(-2)
    return torch.sub(rows[:, k:], rows[:, :-k]).div_(float(k * k)).reshape(maps.shape)


def patch_statistics(grey: torch.Tensor, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance over every pixel's patch.

    Args:
        grey: (..., H, W) grey image(s).
        radius: patch half-size in pixels.

    Returns:
        mean (..., H, W) and variance (..., H, W), the variance clamped at 0.
    """
    mean = box_mean(grey, radius)
    return mean, (box_mean(grey * grey, radius) - mean * mean).clamp(min=0)


def hypothesis_grid(depth: torch.Tensor, offsets: torch.Tensor, intrinsics: torch.Tensor, ref_to_src: torch.Tensor):
    """Where each pixel of the reference lands in each source, for each depth hypothesis.

    Args:
        depth: (H, W) reference depth in metres, > 0.
        offsets: (M,) log-depth offsets; hypothesis k is depth * exp(offsets[k]).
        intrinsics: (4,) fx, fy, cx, cy in pixels, shared by both views.
        ref_to_src: (S, 4, 4) reference-camera to source-camera transforms.

    Returns:
        grid (S, M, H, W, 2), the source positions in ``grid_sample`` coordinates
        (align_corners=False), and seen (S, M, H, W) bool: in front of the source and
        inside it.
    """
    height, width = depth.shape
    k = intrinsics_matrix(intrinsics.double())
    m = (k @ ref_to_src[:, :3, :3].double() @ torch.linalg.inv(k)).to(depth.dtype)  # (S, 3, 3)
    b = (k @ ref_to_src[:, :3, 3:].double())[..., 0].to(depth.dtype)  # (S, 3)
    uv = pixel_grid(height, width, dtype=depth.dtype, device=depth.device)
    # Pixel p at depth d lands at d * m [u, v, 1] + b (homogeneous); each hypothesis only
    # rescales d, so the ray direction is computed once per source.
    direction = m[:, :, 0, None, None] * uv[..., 0] + m[:, :, 1, None, None] * uv[..., 1] + m[:, :, 2, None, None]
    hyp = (depth[None] * torch.exp(offsets)[:, None, None])[None]  # (1, M, H, W)

    def row(c: int, out: torch.Tensor | None = None) -> torch.Tensor:
        return torch.addcmul(b[:, c, None, None, None], hyp, direction[:, None, c], out=out)  # (S, M, H, W)

    z = row(2)
    inv_z = z.clamp(min=1e-6).reciprocal_()
    # Written in place into the grid's planes: the same operations, in order, as
    # (x / z + 0.5) * 2 / W - 1; stacking the planes afterwards would cost more than them.
    grid = z.new_empty(*z.shape, 2)
    gx = row(0, out=grid[..., 0]).mul_(inv_z).add_(0.5).mul_(2.0 / width).sub_(1.0)
    gy = row(1, out=grid[..., 1]).mul_(inv_z).add_(0.5).mul_(2.0 / height).sub_(1.0)
    seen = z > 1e-3
    seen &= torch.abs(gx, out=inv_z) <= 1.0
    seen &= torch.abs(gy, out=inv_z) <= 1.0
    return grid, seen


def sweep_cost(
    ref: torch.Tensor,
    ref_stats: tuple[torch.Tensor, torch.Tensor],
    ref_depth: torch.Tensor,
    sources: torch.Tensor,
    intrinsics: torch.Tensor,
    ref_to_src: torch.Tensor,
    offsets: torch.Tensor,
    radius: int,
    keep_best: int,
    texture_floor: float,
) -> torch.Tensor:
    """Matching cost of M depth hypotheses per pixel, 1 - NCC in [0, 2].

    A source that does not see a pixel's hypothesis scores 1 there (no evidence either
    way); the cost of a hypothesis is the mean of its `keep_best` lowest source costs, so a
    source that is occluded there does not spoil it.

    Args:
        ref: (H, W) grey reference image.
        ref_stats: the reference's :func:`patch_statistics`, mean and variance (H, W).
        ref_depth: (H, W) the band's centre in metres.
        sources: (S, H, W) grey source images.
        intrinsics: (4,) fx, fy, cx, cy in pixels, shared by all views.
        ref_to_src: (S, 4, 4) reference-camera to source-camera transforms.
        offsets: (M,) log-depth offsets.
        radius: patch half-size in pixels.
        keep_best: number of lowest source costs averaged per hypothesis.
        texture_floor: standard deviation added to every patch's (module docstring).

    Returns:
        (M, H, W) cost.
    """
    num_src, num_hyp = ref_to_src.shape[0], offsets.shape[0]
    height, width = ref.shape
    ref_mean, ref_var = ref_stats
    floor = texture_floor**2
    ref_floor = ref_var + floor
    cost = ref.new_empty(num_src, num_hyp, height, width)
    # One source at a time: its (M, H, W) temporaries stay in cache, 2-3x faster on a CPU
    # than one pass over all sources' (S, M, H, W) tensors.
    for s in range(num_src):
        grid, seen = hypothesis_grid(ref_depth, offsets, intrinsics, ref_to_src[s : s + 1])
        # Border padding: a patch reaching past the source's edge sees the edge replicated,
        # which matches nothing, rather than a black frame, which matches the reference's edge.
        warped = F.grid_sample(sources[s, None, None], grid.reshape(1, num_hyp * height, width, 2), mode="bilinear",
                               padding_mode="border", align_corners=False).reshape(num_hyp, height, width)
        sums = box_mean(torch.stack([warped, warped * warped, warped * ref]), radius)
        # 1 - ncc, each step in place on the two temporaries (the same operations, in order).
        inv_std = torch.mul(sums[0], sums[0])
        inv_std = torch.sub(sums[1], inv_std, out=inv_std).clamp_(min=0).add_(floor).mul_(ref_floor).rsqrt_()
        ncc = torch.mul(sums[0], ref_mean)
        ncc = torch.sub(sums[2], ncc, out=ncc).mul_(inv_std).mul_(seen[0])
        torch.neg(ncc, out=cost[s]).add_(1.0)
    return mean_of_smallest(cost, min(keep_best, num_src))


def mean_of_smallest(values: torch.Tensor, keep: int) -> torch.Tensor:
    """Mean of the `keep` smallest values along the first dimension.

    The same numbers as ``values.topk(keep, dim=0, largest=False).values.mean(0)``, by an
    insertion network of elementwise minima and maxima: each value is inserted into the
    sorted `keep` smallest so far. ``topk`` along a leading dimension is 5-8x slower on a CPU.

    Args:
        values: (S, ...) values, S >= keep.
        keep: how many of the smallest to average, >= 1.

    Returns:
        (...) the mean of each position's `keep` smallest values.
    """
    smallest: list[torch.Tensor] = []
    for value in values:
        # smallest[j] becomes min(smallest[j], max(smallest[j - 1], value)), from the top down;
        # until `keep` values are in, the list grows by max(its largest, value).
        top = len(smallest) - 1
        if len(smallest) < keep:
            smallest.append(torch.maximum(smallest[-1], value) if smallest else value)
        for j in range(min(top, keep - 1), 0, -1):
            smallest[j] = torch.minimum(smallest[j], torch.maximum(smallest[j - 1], value))
        if top >= 0:
            smallest[0] = torch.minimum(smallest[0], value)
    return torch.stack(smallest).mean(0)


def select_winner(cost: torch.Tensor, offsets: torch.Tensor, separation: int = 3):
    """The best hypothesis of every pixel, refined to sub-sample precision.

    Args:
        cost: (M, H, W) matching cost per hypothesis.
        offsets: (M,) evenly spaced log-depth offsets.
        separation: hypotheses more than this many samples from the best count for the gap.

    Returns:
        offset (H, W) at the minimum of a parabola through the best sample and its
        neighbours, the best cost (H, W), the gap (H, W) between the best cost and the best
        one more than `separation` samples away (a unique minimum has a large gap; 0 when
        there is none), and at_edge (H, W) bool: the minimum is on the band's edge, so the
        true depth may lie outside the band.
    """
    num = cost.shape[0]
    best = cost.argmin(0)
    mid = best.clamp(1, num - 2)
    c0, c1, c2 = (cost.gather(0, (mid + d)[None])[0] for d in (-1, 0, 1))
    curvature = c0 - 2.0 * c1 + c2
    shift = torch.where(curvature > 1e-6, 0.5 * (c0 - c2) / curvature.clamp(min=1e-6), torch.zeros_like(c1))
    step = offsets[1] - offsets[0] if num > 1 else offsets.new_tensor(0.0)
    offset = offsets[mid] + shift.clamp(-0.5, 0.5) * step
    best_cost = cost.gather(0, best[None])[0]
    index = torch.arange(num, device=cost.device)[:, None, None]
    far = (index - best[None]).abs() > separation
    second = torch.where(far, cost, torch.full_like(cost, float("inf"))).amin(0)
    gap = torch.where(torch.isfinite(second), second - best_cost, torch.zeros_like(best_cost))
    at_edge = (best == 0) | (best == num - 1)
    return offset, best_cost, gap, at_edge
