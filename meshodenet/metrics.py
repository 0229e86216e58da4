"""Position RMSE, defined once for the whole project (numpy arrays and torch tensors alike).

``rmse(pred, true, over)``: ``sqrt(mean_over |x_pred - x_true|^2)`` in m, with ``|.|`` the
Euclidean norm of the last axis (the 3-vector) and the mean over the axes ``over`` of what is
left. Each library reduces its own arrays (numpy for the suite's metrics.csv, torch for
training's validation and a run's test metrics), so each number keeps its arithmetic.
Say the axes with every number reported:

- ``position_rmse(pred, true)``: over trajectories ``b``, predicted frames ``k >= 1`` (frame 0
  is the given initial state) and all nodes ``i`` (clamped ones included);
- ``rmse_per_frame``: the same, per frame ``k`` (``(T,)``, frame 0 included and zero);
- the suite's per-trajectory RMSEs (``benchmarks.suite.metrics``): over nodes at each frame,
  and over nodes and frames ``k >= 1``;
- the no-motion baseline is the prediction ``x(t) = x(0)`` scored by the same functions.
"""

from __future__ import annotations


def rmse(pred, true, over=None):
    """``sqrt(mean over the axes over of |pred - true|^2)``, m; ``pred, true (..., 3)`` numpy
    arrays or torch tensors of one shape, ``over`` an axis, a tuple of axes or None (all)."""
    err = ((pred - true) ** 2).sum(-1)
    # exponent 0.5 is sqrt in numpy and torch alike (both special-case it; sqrt is exact)
    return (err.mean() if over is None else err.mean(over)) ** 0.5


def _check_shapes(pred, true) -> None:
    if pred.shape != true.shape:
        raise ValueError(f"pred has shape {tuple(pred.shape)} but true {tuple(true.shape)}")


def rmse_per_frame(pred, true):
    """``(T,)`` position RMSE per frame over trajectories and nodes; ``pred, true (B, T, N, 3)``
    torch tensors, reduced in float64."""
    _check_shapes(pred, true)
    return rmse(pred.double(), true.double(), (0, 2))


def position_rmse(pred, true) -> float:
    """Scalar position RMSE (m) over trajectories, frames ``k >= 1`` and nodes (torch, float64)."""
    _check_shapes(pred, true)
    return float(rmse(pred[:, 1:].double(), true[:, 1:].double()))


def no_motion(true):
    """The no-motion prediction ``x(t) = x(0)`` for ``true (B, T, N, 3)`` (torch)."""
    return true[:, :1].expand_as(true)
