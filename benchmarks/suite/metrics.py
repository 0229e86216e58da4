"""The suite's error tables, from the RMSE defined in ``meshodenet.metrics.rmse``.

**RMSE at step k** (per trajectory): the root of the mean over *all* nodes of the squared
Euclidean position error at saved frame k (time ``k * save_dt``; frame 0 is the initial
state, whose error is zero for every model):

    RMSE_k = sqrt( (1/N) sum_i |x_hat_i(t_k) - x_i(t_k)|^2 )      [m]

**Full-rollout RMSE** (per trajectory): the same mean taken over nodes and frames 1..T-1.
Clamped nodes are included (their error is zero for every model that holds them).

**The paper's convention** (``rmse_coord``): the authors' evaluation takes the root of the mean
over nodes *and the three coordinates* of the squared error (docs/SUITE.md). For a trajectory
at a step it is exactly ``RMSE_k / sqrt(3)``: the per-node squared norm is the sum over the
three coordinates, so the mean over coordinates is a third of it. ``rmse_at_step_table`` reports
both; every comparison with the paper's Tables 1 and 2 is made in the paper's.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

# The steps of the paper's Tables 1 and 2.
PAPER_STEPS = {"rod_falling": (1, 30, 60, 90, 120, 150, 180),
               "plate_cantilever": (1, 25, 50, 150, 250, 350),
               "plate_hanging": (1, 25, 50, 150, 250, 350)}

#: The paper's Tables 1 and 2 (means over the test trajectories, m, in the paper's convention:
#: per coordinate), by case, model and step.
PAPER_TABLES = {
    "rod_falling": {
        "meshodenet": dict(zip(PAPER_STEPS["rod_falling"],
                               (2.62e-4, 5.79e-4, 4.61e-4, 3.05e-4, 1.89e-4, 1.62e-4, 2.03e-4))),
        "mgn": dict(zip(PAPER_STEPS["rod_falling"],
                        (4.14e-4, 19.74e-4, 28.32e-4, 37.98e-4, 64.71e-4, 116.53e-4, 192.58e-4)))},
    "plate_cantilever": {
        "meshodenet": dict(zip(PAPER_STEPS["plate_cantilever"],
                               (0.32e-4, 8.29e-4, 6.84e-4, 3.11e-4, 2.49e-4, 2.72e-4))),
        "mgn": dict(zip(PAPER_STEPS["plate_cantilever"],
                        (1.73e-4, 19.61e-4, 60.87e-4, 188.06e-4, 267.20e-4, 354.18e-4)))},
}

#: Per-coordinate RMSE over the per-node Euclidean one, for 3-vectors.
PER_COORDINATE = 1.0 / np.sqrt(3.0)


def table_steps(case_id: str, n_frames: int) -> tuple:
    """The steps of a case's table: the paper's for its two cases, the case's own
    ``table_steps`` attribute for a registered case that has one, else step 1 and five
    evenly spaced steps up to the last frame. A refined case ``CASE@rN`` (the same save times)
    has the steps of ``CASE``."""
    case_id = case_id.partition("@")[0]
    if case_id in PAPER_STEPS:
        return PAPER_STEPS[case_id]
    from benchmarks.suite.registry import CASES

    own = getattr(CASES.get(case_id), "table_steps", None)
    if own:
        return tuple(int(s) for s in own)
    last = n_frames - 1
    return tuple(sorted({1, *(int(round(last * k / 5)) for k in range(1, 6))} - {0}))


def _check(pred: np.ndarray, true: np.ndarray):
    pred, true = np.asarray(pred, float), np.asarray(true, float)
    if pred.shape != true.shape or pred.ndim != 4 or pred.shape[-1] != 3:
        raise ValueError(f"pred and true must both have shape (B, T, N, 3); got {pred.shape} "
                         f"and {true.shape}")
    return pred, true


def rmse_per_step(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(B, T, N, 3)`` twice -> ``(B, T)`` RMSE at every saved frame, m."""
    from meshodenet.metrics import rmse  # here: importing meshodenet loads torch

    pred, true = _check(pred, true)
    return rmse(pred, true, -1)


def full_rollout_rmse(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(B, T, N, 3)`` twice -> ``(B,)`` RMSE over nodes and frames 1..T-1, m."""
    from meshodenet.metrics import rmse

    pred, true = _check(pred, true)
    return rmse(pred[:, 1:], true[:, 1:], (1, 2))


def rmse_per_coordinate(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``(B, T, N, 3)`` twice -> ``(B, T)``: the authors' per-step position RMSE, the root of
    the mean over nodes and coordinates of the squared error (``rmse_per_step / sqrt(3)``)."""
    pred, true = _check(pred, true)
    return np.sqrt(((pred - true) ** 2).mean(axis=(2, 3)))


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
    per case and model, with each model's relative increase over ``reference_model`` in %;
    ``rmse_coord_mean`` and ``rmse_coord_std`` are the same in the paper's convention (each
    trajectory's RMSE times ``PER_COORDINATE``).

    ``metrics`` has columns ``case, model, trajectory, step, rmse`` (other id columns such as
    ``integrator`` or ``seed`` are kept as grouping keys). The std is the population std
    (ddof=0) over trajectories, as a spread, not an error of the mean. A step at which any
    trajectory's RMSE is NaN (its rollout diverged) has NaN mean and std: pandas would
    otherwise average the others and hide the diverged one.
    """
    steps = PAPER_STEPS if steps is None else steps
    keys = [c for c in metrics.columns if c not in ("trajectory", "step", "time", "rmse")]
    rows = []
    for case, dfc in metrics.groupby("case", sort=True):
        want = steps.get(case, ())
        sel = dfc[dfc["step"].isin(want)]
        sel = sel.assign(rmse_coord=sel["rmse"] * PER_COORDINATE)
        g = sel.groupby(keys + ["step"], sort=True)
        r, c = g["rmse"], g["rmse_coord"]
        part = pd.DataFrame({"rmse_mean": r.mean(), "rmse_std": r.std(ddof=0),
                             "rmse_coord_mean": c.mean(), "rmse_coord_std": c.std(ddof=0),
                             "n_trajectories": r.size()})
        # a diverged trajectory (NaN) is never left out of the mean: the row is NaN
        gone = sel["rmse"].isna().groupby([sel[k] for k in keys + ["step"]], sort=True).any()
        part.loc[gone.reindex(part.index).to_numpy(bool),
                 ["rmse_mean", "rmse_std", "rmse_coord_mean", "rmse_coord_std"]] = np.nan
        rows.append(part.reset_index())
    table = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame(
        columns=keys + ["step", "rmse_mean", "rmse_std", "rmse_coord_mean", "rmse_coord_std",
                        "n_trajectories"])
    # match each model to the reference on the keys that both have (not the integrator or the
    # gradient mode, which only MeshODENet has); with several reference rows per match, prefer
    # MeshODENet's defaults (rk4, checkpoint), then the first.
    match = [k for k in keys if k not in ("model", "integrator", "grad_mode")] + ["step"]
    ref = table[table["model"] == reference_model].copy()
    if len(ref) and ref.duplicated(match).any():
        pref = np.zeros(len(ref))
        if "integrator" in ref:
            pref -= (ref["integrator"] == "rk4").to_numpy()
        if "grad_mode" in ref:
            pref -= (ref["grad_mode"] == "checkpoint").to_numpy()
        ref = ref.assign(_p=pref).sort_values("_p", kind="stable").drop_duplicates(match)
    ref = ref[match + ["rmse_mean"]].rename(columns={"rmse_mean": "_ref"})
    table = table.merge(ref, on=match, how="left")
    table["increase_vs_" + reference_model + "_pct"] = 100.0 * (table["rmse_mean"] / table["_ref"] - 1.0)
    table = table.drop(columns=["_ref"])
    return table.sort_values(keys + ["step"]).reset_index(drop=True)


def per_run_metrics(pred, true, t, ids: dict) -> pd.DataFrame:
    """Tidy RMSE rows of one run: every (trajectory, step), then each trajectory's
    full-rollout RMSE (``metric`` = ``full_rollout_rmse``, ``step`` = the horizon)."""
    steps = tidy_metrics(pred, true, t, ids)
    steps.insert(len(ids), "metric", "rmse_at_step")
    full = full_rollout_rmse(pred, true)
    T = np.asarray(pred).shape[1]
    rows = pd.DataFrame({**{k: v for k, v in ids.items()}, "metric": "full_rollout_rmse",
                         "trajectory": np.arange(len(full)), "step": T - 1,
                         "time": float(np.asarray(t)[-1]), "rmse": full})
    return pd.concat([steps, rows], ignore_index=True)
