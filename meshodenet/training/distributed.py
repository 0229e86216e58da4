"""Data parallelism over the processes of ``torchrun`` (docs/CLUSTER.md): which rank this
process is, one optimizer step's gradients summed over the ranks, rank 0's weights to all."""

from __future__ import annotations

import math

import torch


def distributed_rank() -> tuple[int, int]:
    """``(rank, world size)`` of this process in an initialised ``torch.distributed`` process
    group of more than one process (``torchrun``); ``(0, 1)`` otherwise."""
    dist = torch.distributed
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def distributed_backward(loss_fn, model, idx, step_seed: int, rank: int, world: int,
                         max_norm):
    """Data-parallel step of one global batch ``idx``: this rank computes the loss of its
    share ``idx[rank::world]`` (``loss_fn(share, generator)``, a scalar tensor) weighted by
    ``len(share) / len(idx)``, so that the sum over ranks is the global batch's mean loss; the
    gradients and losses are then summed over the ranks (``all_reduce``): every rank holds the
    gradient one process would have computed on the whole batch (up to the order of the
    floating-point sums), and takes the same step. Randomness of the loss (training noise)
    comes from a generator seeded with ``step_seed * world + rank``; ``step_seed`` derives
    from the state of the trainer's shared generator at the start of the epoch without drawing
    from it, so the shuffling is the one process's and stays in step on every rank, and
    resuming stays exact. Returns ``(global loss, gradient norm)``."""
    dist = torch.distributed
    mine = idx[rank::world]
    params = [p for p in model.parameters() if p.requires_grad]
    local = 0.0
    if len(mine):
        lgen = torch.Generator().manual_seed(step_seed * world + rank)
        loss = loss_fn(mine, lgen) * (len(mine) / len(idx))
        local = float(loss.detach())
        if math.isfinite(local):
            loss.backward()
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1)
                      for p in params] + [torch.tensor([local], dtype=params[0].dtype,
                                                        device=params[0].device)])
    dist.all_reduce(flat)
    k = 0
    for p in params:
        p.grad = flat[k:k + p.numel()].view_as(p).clone()
        k += p.numel()
    value = float(flat[-1])
    norm = torch.nn.utils.clip_grad_norm_(params, max_norm) if math.isfinite(value) \
        else torch.tensor(math.nan)
    return value, norm


def broadcast_parameters(model: torch.nn.Module) -> None:
    """Rank 0's parameters and buffers to every rank (as ``DistributedDataParallel`` does)."""
    if distributed_rank()[1] > 1:
        for t in list(model.parameters()) + list(model.buffers()):
            torch.distributed.broadcast(t.data, 0)
