"""medea_core.lazy_adam: the same steps as torch's SparseAdam, bit for bit, on rows drawn
with repeats, and rows absent from a step left as they were."""

import torch
import torch.nn.functional as F

from medea_core.lazy_adam import AdamMoments, lazy_adam_step


def _loss(table: torch.Tensor, rows: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((F.embedding(rows, table, sparse=True) - target[rows]) ** 2).sum()


def test_lazy_adam_matches_sparse_adam_bit_for_bit():
    gen = torch.Generator().manual_seed(0)
    start = torch.randn(12, 6, generator=gen)
    target = torch.randn(12, 6, generator=gen)
    ours, theirs = start.clone().requires_grad_(True), start.clone().requires_grad_(True)
    reference = torch.optim.SparseAdam([theirs], lr=0.1, eps=1e-6)
    schedule = torch.optim.lr_scheduler.ExponentialLR(reference, gamma=0.9)
    moments, lr = AdamMoments.zeros_like(ours), 0.1
    for _ in range(4):  # epochs
        for _ in range(3):  # batches, a row drawn more than once in some
            rows = torch.randint(0, 12, (8,), generator=gen)
            ours.grad = None
            _loss(ours, rows, target).backward()
            lazy_adam_step(ours, ours.grad, moments, lr, eps=1e-6)
            reference.zero_grad(set_to_none=True)
            _loss(theirs, rows, target).backward()
            reference.step()
        schedule.step()
        lr *= 0.9
    assert not torch.equal(ours, start)
    assert torch.equal(ours, theirs)
    state = reference.state[theirs]
    assert moments.step == state["step"]
    assert torch.equal(moments.exp_avg, state["exp_avg"]) and torch.equal(moments.exp_avg_sq, state["exp_avg_sq"])


def test_rows_absent_from_the_gradient_keep_their_values_and_moments():
    table = torch.arange(1.0, 16.0).view(5, 3).requires_grad_(True)  # no zero gradient
    before = table.detach().clone()
    moments = AdamMoments.zeros_like(table)
    _loss(table, torch.tensor([1, 3, 3]), torch.zeros(5, 3)).backward()
    lazy_adam_step(table, table.grad, moments, lr=0.5)
    moved = (table.detach() != before).any(dim=1)
    assert moved.tolist() == [False, True, False, True, False]
    assert (moments.exp_avg[[0, 2, 4]] == 0).all() and (moments.exp_avg[[1, 3]] != 0).all()
    # A step moves each touched entry by lr (Adam's first step is lr * sign(grad)).
    assert torch.allclose((table.detach() - before)[[1, 3]].abs(), torch.full((2, 3), 0.5))
