"""Rollout error metrics. Definitions (say them with every number reported):

- ``position_rmse(pred, true)``: ``sqrt(mean_{b, k >= 1, i} |x_pred - x_true|^2)`` in m, over
  trajectories ``b``, predicted frames ``k >= 1`` (frame 0 is the given initial state) and all
  nodes ``i`` (clamped ones included), with ``|.|`` the Euclidean norm of the 3-vector.
- ``rmse_per_frame``: the same, per frame ``k`` (``(T,)``, frame 0 included and zero).
- the no-motion baseline is the prediction ``x(t) = x(0)`` scored by the same functions.
"""

from __future__ import annotations

import torch


def rmse_per_frame(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """``(T,)`` position RMSE per frame over trajectories and nodes; ``pred, true (B, T, N, 3)``."""
    if pred.shape != true.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)} but true {tuple(true.shape)}")
    err = ((pred.double() - true.double()) ** 2).sum(-1)  # (B, T, N)
    return err.mean(dim=(0, 2)).sqrt()


def position_rmse(pred: torch.Tensor, true: torch.Tensor) -> float:
    """Scalar position RMSE (m) over trajectories, frames ``k >= 1`` and nodes."""
    if pred.shape != true.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)} but true {tuple(true.shape)}")
    err = ((pred[:, 1:].double() - true[:, 1:].double()) ** 2).sum(-1)
    return float(err.mean().sqrt())


def no_motion(true: torch.Tensor) -> torch.Tensor:
    """The no-motion prediction ``x(t) = x(0)`` for ``true (B, T, N, 3)``."""
    return true[:, :1].expand_as(true)
