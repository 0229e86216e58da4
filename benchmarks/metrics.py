"""Error metrics, defined once.

**RMSE at step k** (per trajectory): the root of the mean over *all* nodes of the squared
Euclidean position error at saved frame k (time ``k * save_dt``; frame 0 is the initial
state, whose error is zero for every model):

    RMSE_k = sqrt( (1/N) sum_i |x_hat_i(t_k) - x_i(t_k)|^2 )      [m]

**Full-rollout RMSE** (per trajectory): the same mean taken over nodes and frames 1..T-1.
Clamped nodes are included (their error is zero for every model that holds them).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

# The steps of the paper's Tables 1 and 2.
PAPER_STEPS = {"rod_falling": (1, 30, 60, 90, 120, 150, 180),
               "plate_cantilever": (1, 25, 50, 150, 250, 350)}


def _check(pred: np.ndarray, true: np.ndarray):
    pred, true = np.asarray(pred, float), np.asarray(true, float)
    if pred.shape != true.shape or pred.ndim != 4 or pred.shape[-1] != 3:
        raise ValueError(f"pred and true must both have shape (B, T, N, 3); got {pred.shape} "
                         f"and {true.shape}")
    return pred, true


def rmse_per_step(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(B, T, N, 3)`` twice -> ``(B, T)`` RMSE at every saved frame, m."""
    pred, true = _check(pred, true)
    return np.sqrt(np.mean(np.sum((pred - true) ** 2, axis=-1), axis=-1))


def full_rollout_rmse(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(B, T, N, 3)`` twice -> ``(B,)`` RMSE over nodes and frames 1..T-1, m."""
    pred, true = _check(pred, true)
    return np.sqrt(np.mean(np.sum((pred - true)[:, 1:] ** 2, axis=-1), axis=(1, 2)))


def no_motion(true: np.ndarray) -> np.ndarray:
    """The trivial baseline: every frame equals the initial one."""
    true = np.asarray(true, float)
    return np.broadcast_to(true[:, :1], true.shape).copy()


def tidy_metrics(pred, true, t, ids: dict) -> pd.DataFrame:
    """One row per (trajectory, step) with the RMSE, plus the id columns in ``ids``."""
    r = rmse_per_step(pred, true)
    B, T = r.shape
    df = pd.DataFrame({"trajectory": np.repeat(np.arange(B), T), "step": np.tile(np.arange(T), B),
                       "time": np.tile(np.asarray(t, float), B), "rmse": r.ravel()})
    for k, v in reversed(list(ids.items())):
        df.insert(0, k, v)
    return df


def rmse_at_step_table(metrics: pd.DataFrame, steps: dict | None = None,
                       reference_model: str = "meshodenet") -> pd.DataFrame:
    """The paper's table: mean and std (over test trajectories) of RMSE at the paper's steps,
    per case and model, with each model's relative increase over ``reference_model`` in %.

    ``metrics`` has columns ``case, model, trajectory, step, rmse`` (other id columns such as
    ``integrator`` or ``seed`` are kept as grouping keys). The std is the population std
    (ddof=0) over trajectories, as a spread, not an error of the mean.
    """
    steps = PAPER_STEPS if steps is None else steps
    keys = [c for c in metrics.columns if c not in ("trajectory", "step", "time", "rmse")]
    rows = []
    for case, dfc in metrics.groupby("case", sort=True):
        want = steps.get(case, ())
        sel = dfc[dfc["step"].isin(want)]
        g = sel.groupby(keys + ["step"], sort=True)["rmse"]
        rows.append(pd.DataFrame({"rmse_mean": g.mean(), "rmse_std": g.std(ddof=0),
                                  "n_trajectories": g.size()}).reset_index())
    table = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame(
        columns=keys + ["step", "rmse_mean", "rmse_std", "n_trajectories"])
    other = [k for k in keys if k != "model"]
    ref = table[table["model"] == reference_model].set_index(other + ["step"])["rmse_mean"]
    idx = pd.MultiIndex.from_frame(table[other + ["step"]]) if len(other) + 1 > 1 else table["step"]
    base = ref.reindex(idx).to_numpy()
    table["increase_vs_" + reference_model + "_pct"] = 100.0 * (table["rmse_mean"].to_numpy() / base - 1.0)
    return table.sort_values(keys + ["step"]).reset_index(drop=True)
