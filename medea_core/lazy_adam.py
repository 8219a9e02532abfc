"""Adam applied lazily to the rows of a table that a step's gradient touches.

Adam (Kingma and Ba, ICLR 2015) keeps a running mean ``m`` and a running mean of squares
``v`` of the gradient and steps each parameter by ``lr * m_hat / (sqrt(v_hat) + eps)``, with
the bias corrections of step ``t``. Applied lazily, only the rows that appear in the
gradient move and only their moments decay (the update torch's ``SparseAdam`` makes, in the
same arithmetic): MEDeA's frames are rows of one table of grids, and a frame absent from a
batch keeps its grid and its moments.

Args and shapes are those of a table ``(N, D)`` and a sparse COO gradient of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class AdamMoments:
    """The optimiser's state for one table: its steps so far and the moments of every row.

    step: steps taken (the bias corrections' ``t``); exp_avg, exp_avg_sq: (N, D) running
    means of the gradient and of its square.
    """

    step: int
    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor

    @classmethod
    def zeros_like(cls, table: torch.Tensor) -> AdamMoments:
        """No step taken, zero moments for every row of a table.

        Args:
            table: (N, D) the parameters.

        Returns:
            AdamMoments with step 0 and (N, D) zero moments.
        """
        return cls(0, torch.zeros_like(table), torch.zeros_like(table))


@torch.no_grad()
def lazy_adam_step(table: torch.Tensor, grad: torch.Tensor, moments: AdamMoments, lr: float,
                   betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
    """One Adam step on the rows of ``table`` that ``grad`` holds, in place.

    Args:
        table: (N, D) parameters, changed in place.
        grad: sparse COO (N, D) gradient of ``table`` (duplicated rows are summed).
        moments: the state (AdamMoments), changed in place; its step counts only steps that
            touched a row.
        lr: learning rate of this step.
        betas: decay of the first and second moment.
        eps: added to the root of the second moment.
    """
    grad = grad.coalesce()
    rows, values = grad.indices()[0], grad.values()
    if values.numel() == 0:
        return
    moments.step += 1
    beta1, beta2 = betas
    # old <- beta * old + (1 - beta) * new, written old += (1 - beta) * (new - old).
    old_avg = moments.exp_avg[rows]
    avg_change = values.sub(old_avg).mul_(1 - beta1)
    moments.exp_avg.index_add_(0, rows, avg_change)
    old_sq = moments.exp_avg_sq[rows]
    sq_change = values.pow(2).sub_(old_sq).mul_(1 - beta2)
    moments.exp_avg_sq.index_add_(0, rows, sq_change)
    numerator = avg_change.add_(old_avg)
    denominator = sq_change.add_(old_sq).sqrt_().add_(eps)
    step_size = lr * math.sqrt(1 - beta2 ** moments.step) / (1 - beta1 ** moments.step)
    table.index_add_(0, rows, -step_size * numerator.div_(denominator))
