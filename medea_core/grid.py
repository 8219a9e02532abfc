"""The depth deformation model: a per-frame log-scale grid l_i of size (h, w) whose
exponential, bilinearly interpolated to the frame size, multiplies the prior depth:

    D_i = D0_i * S_i,   S_i = B(exp(l_i), H, W).

The grid vertices sit on the image corners and are evenly spaced (bilinear interpolation
with align_corners=True), so the same grid gives the same field at any resolution.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def interpolation_matrix(size_out: int, size_in: int, device=None) -> torch.Tensor:
    """(size_out, size_in) linear interpolation weights, end points aligned."""
    eye = torch.eye(size_in, device=device)[None]
    return F.interpolate(eye, size=size_out, mode="linear", align_corners=True)[0].T


def scale_field(
    log_scales: torch.Tensor, size: tuple[int, int], lattice: tuple[slice, slice] | None = None
) -> torch.Tensor:
    """S = B(exp(l), H, W): bilinear interpolation with the vertices on the image corners.

    Evaluated as two small matrix products (rows, then columns), which is the same
    bilinear interpolation as F.interpolate(align_corners=True) but much cheaper to
    differentiate.

    Args:
        log_scales: (B, h, w).
        size: (H, W).
        lattice: optional (row slice, column slice) to evaluate only those pixels.
    Returns:
        (B, H, W), or (B, H', W') on the lattice.
    """
    rows = interpolation_matrix(size[0], log_scales.shape[-2], log_scales.device)
    cols = interpolation_matrix(size[1], log_scales.shape[-1], log_scales.device)
    if lattice is not None:
        rows, cols = rows[lattice[0]], cols[lattice[1]]
    return rows @ log_scales.exp() @ cols.T


def sample_scale_field(log_scales: torch.Tensor, uv: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """S at arbitrary pixel coordinates uv (B, H', W', 2) of a (H, W) frame -> (B, H', W').

    Samples the coarse grid directly, so frame j's scale at warped positions costs a
    grid_sample over (h, w) values instead of one over a full-resolution field.
    """
    height, width = size
    scale = uv.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = uv * scale - 1.0
    sampled = F.grid_sample(log_scales.exp()[:, None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return sampled[:, 0]


def adjust_depth(prior_depth: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """D = D0 * S for priors (B, H, W) and grids (B, h, w); invalid (0) stays 0."""
    return prior_depth * scale_field(log_scales, prior_depth.shape[-2:])


def vertex_cells(height: int, width: int, grid: tuple[int, int], device=None) -> torch.Tensor:
    """(H, W) int64 index of the grid vertex nearest to each pixel centre (row-major)."""
    gh, gw = grid
    rows = torch.round(torch.arange(height, device=device) * (gh - 1) / max(height - 1, 1)).long()
    cols = torch.round(torch.arange(width, device=device) * (gw - 1) / max(width - 1, 1)).long()
    return rows[:, None] * gw + cols[None, :]


def median_pool_to_grid(values: torch.Tensor, valid: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Median of the valid values around each grid vertex ("Pool(S, h, w)" of the paper).

    Each pixel belongs to its nearest vertex, so the pooled value is centred where the
    bilinear model places it. Vertices without valid pixels take the median of the
    frame's valid values, or NaN if the frame has none.

    Args:
        values: (B, H, W).
        valid: (B, H, W) bool.
        grid: (h, w).
    Returns:
        (B, h, w).
    """
    batch, height, width = values.shape
    cells = vertex_cells(height, width, grid, values.device).flatten()
    num_cells = grid[0] * grid[1]
    # The cell layout is the same for every frame, so one gather table (cells x max
    # members, padded) turns per-cell medians into a single nanmedian over the last axis.
    order = torch.argsort(cells, stable=True)
    counts = torch.bincount(cells, minlength=num_cells)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(int(counts.max()), device=values.device)
    member = starts[:, None] + slot[None, :]
    present = slot[None, :] < counts[:, None]
    table = order[member.clamp(max=order.numel() - 1)]
    masked = torch.where(valid, values, torch.full_like(values, float("nan"))).reshape(batch, -1)
    gathered = masked[:, table]
    gathered = torch.where(present[None], gathered, torch.full_like(gathered, float("nan")))
    pooled = gathered.nanmedian(dim=-1).values
    frame_median = masked.nanmedian(dim=-1).values
    pooled = torch.where(torch.isnan(pooled), frame_median[:, None], pooled)
    return pooled.reshape(batch, *grid)
