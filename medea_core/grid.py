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
    """Linear interpolation weights from size_in samples to size_out, end points aligned.

    Args:
        size_out: number of output samples.
        size_in: number of input samples.
        device: device of the result; None: the default device.

    Returns:
        (size_out, size_in) matrix W: out = W @ in interpolates as
        F.interpolate(mode="linear", align_corners=True).
    """
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
        log_scales: (B, h, w) log-scale grids.
        size: (H, W) frame size in pixels.
        lattice: optional (row slice, column slice) to evaluate only those pixels.

    Returns:
        (B, H, W) scale field, or (B, H', W') on the lattice.
    """
    rows = interpolation_matrix(size[0], log_scales.shape[-2], log_scales.device)
    cols = interpolation_matrix(size[1], log_scales.shape[-1], log_scales.device)
    if lattice is not None:
        rows, cols = rows[lattice[0]], cols[lattice[1]]
    return rows @ log_scales.exp() @ cols.T


def sample_scale_field(log_scales: torch.Tensor, uv: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """The scale field S at arbitrary pixel coordinates of a frame.

    Samples the coarse grid directly, so frame j's scale at warped positions costs a
    grid_sample over (h, w) values instead of one over a full-resolution field.

    Args:
        log_scales: (B, h, w) log-scale grids.
        uv: (B, H', W', 2) pixel coordinates (u, v) in the frame; outside the frame the
            border value is used.
        size: (H, W) frame size in pixels.

    Returns:
        (B, H', W') scale S = B(exp(l)) at uv.
    """
    height, width = size
    scale = uv.new_tensor([2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)])
    grid = uv * scale - 1.0
    sampled = F.grid_sample(log_scales.exp()[:, None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return sampled[:, 0]


def adjust_depth(prior_depth: torch.Tensor, log_scales: torch.Tensor) -> torch.Tensor:
    """Apply the log-scale grids to the prior depth: D = D0 * S.

    Args:
        prior_depth: (B, H, W) prior depth in metres, 0 = invalid.
        log_scales: (B, h, w) log-scale grids.

    Returns:
        (B, H, W) adjusted depth in metres; invalid (0) stays 0.
    """
    return prior_depth * scale_field(log_scales, prior_depth.shape[-2:])


def vertex_cells(height: int, width: int, grid: tuple[int, int], device=None) -> torch.Tensor:
    """Index of the grid vertex nearest to each pixel centre.

    Args:
        height: frame height H in pixels.
        width: frame width W in pixels.
        grid: (h, w) grid size in vertices.
        device: device of the result; None: the default device.

    Returns:
        (H, W) int64 row-major vertex index, row * w + column.
    """
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
        values: (B, H, W) per-pixel values.
        valid: (B, H, W) bool, which values count.
        grid: (h, w) grid size in vertices.

    Returns:
        (B, h, w) pooled medians.
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
