"""Figures of a suite's results (``results/SUITE/figures/``), drawn from the CSVs and the runs'
stored test rollouts: RMSE vs step per case, snapshots of predicted vs ground-truth shapes at
the table's steps, training / validation curves, and an animated rollout per case and model
(``benchmarks/suite/animate.py``, called by the runner)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.suite.runs import load_test_rollout
from groundtruth import store

COLORS = {"meshodenet": "tab:blue", "mgn": "tab:red", "meshodenet_imex": "tab:green",
          "implicit_energy": "tab:purple", "implicit_energy_dissipation": "tab:pink",
          "solver_h": "tab:gray"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    store.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110,
                                                   bbox_inches="tight"))
    _plt().close(fig)
    return path


def _has_scheme(model: str) -> bool:
    """Whether the model's configuration chooses an integrator and a gradient mode (its labels
    then name them)."""
    import dataclasses

    from benchmarks.suite.runs import suite_models

    spec = suite_models().get(model)
    return spec is not None and {"integrator", "grad_mode"} <= {
        f.name for f in dataclasses.fields(spec.config_cls)}


def _label(rec: dict) -> str:
    return _scheme_label(rec["model"], rec["integrator"], rec["grad_mode"])


def _scheme_label(model: str, integrator: str, grad_mode: str) -> str:
    return f"{model} ({integrator}, {grad_mode})" if _has_scheme(model) else model


def _color(model: str, i: int) -> str:
    return COLORS.get(model, f"C{(i + 2) % 10}")


def rmse_vs_step(metrics: pd.DataFrame, case: str, path: Path) -> Path:
    """RMSE against step in the paper's convention (per coordinate: each trajectory's RMSE
    over nodes and coordinates), the paper's Tables 1 and 2 as markers where the case is one of
    its two."""
    from benchmarks.suite.metrics import PAPER_TABLES, PER_COORDINATE

    plt = _plt()
    m = metrics[(metrics["case"] == case) & (metrics["metric"] == "rmse_at_step")
                & (metrics["step"] > 0)]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    groups = ["model", "integrator", "grad_mode"]
    few = m.groupby(groups).ngroups <= 2  # model colours; otherwise one colour per line
    for i, (key, d) in enumerate(m.groupby(groups, sort=True)):
        g = (d["rmse"] * PER_COORDINATE).groupby(d["step"])
        # NaN (a diverged trajectory) ends the line there: never averaged away
        mean, lo, hi = (g.agg(lambda s, f=f: getattr(s, f)(skipna=False))
                        for f in ("mean", "min", "max"))
        label = _scheme_label(*key)
        c = _color(key[0], i) if few else f"C{i}"
        ax.plot(mean.index, mean.values, color=c, label=label)
        ax.fill_between(mean.index, lo.values, hi.values, color=c, alpha=0.2, lw=0)
    for j, (model, row) in enumerate(sorted(PAPER_TABLES.get(case, {}).items())):
        ax.plot(list(row), list(row.values()), ("D" if j == 0 else "s"), ms=6, mfc="none",
                color=COLORS.get(model, "k"), ls="none",
                label=f"{model}, the paper's table")
    ax.set_yscale("log")
    ax.set_xlabel("step (saved frame)")
    ax.set_ylabel("position RMSE per coordinate (m)")
    ax.set_title(f"{case}: mean over test trajectories (band: min-max)\n"
                 "the paper's convention: root of the mean over nodes and x, y, z", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _plane(true: np.ndarray) -> tuple[int, int]:
    """The two coordinate axes along which the ground truth moves most (its plane of motion)."""
    span = true.reshape(-1, 3).max(0) - true.reshape(-1, 3).min(0)
    a, b = sorted(np.argsort(span)[-2:])
    return int(a), int(b)


def snapshots(case: str, records: list, runs_dir: Path, steps, path: Path, true: dict,
              n_show: int = 2) -> Path:
    """Predicted vs ground-truth shapes at ``steps`` for ``n_show`` test trajectories (lowest
    and highest Young's modulus), projected on the plane of motion."""
    plt = _plt()
    pos, youngs = true["pos"], np.asarray(true["youngs"]).ravel()
    order = np.argsort(youngs)
    show = [int(order[0]), int(order[-1])][:n_show] if len(order) > 1 else [0]
    steps = [s for s in steps if s < pos.shape[1]]
    ax0, ax1 = _plane(pos)
    names = "xyz"
    preds = [(r, load_test_rollout(runs_dir / r["run"])) for r in records]
    fig, axes = plt.subplots(len(show), len(steps), figsize=(2.0 * len(steps), 2.3 * len(show)),
                             squeeze=False)
    for row, j in enumerate(show):
        for col, s in enumerate(steps):
            ax = axes[row, col]
            gt = pos[j, s][:, [ax0, ax1]]
            # each panel is a square window around the ground truth at that step
            centre = 0.5 * (gt.min(0) + gt.max(0))
            half = 0.6 * max((gt.max(0) - gt.min(0)).max(), 1e-9)
            ax.plot(gt[:, 0], gt[:, 1], "o", ms=2.0, color="k", label="ground truth")
            for i, (r, p) in enumerate(preds):
                ax.plot(p[j, s, :, ax0], p[j, s, :, ax1], ".", ms=2.0, alpha=0.8,
                        color=_color(r["model"], i), label=_label(r))
            ax.set_xlim(centre[0] - half, centre[0] + half)
            ax.set_ylim(centre[1] - half, centre[1] + half)
            ax.set_aspect("equal")
            if row == 0:
                ax.set_title(f"step {s}", fontsize=9)
            if col == 0:
                ax.set_ylabel(f"Y={youngs[j]:.3g} Pa\n{names[ax1]} (m)", fontsize=8)
            if row == len(show) - 1:
                ax.set_xlabel(f"{names[ax0]} (m)", fontsize=8)
            ax.tick_params(labelsize=6)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.suptitle(f"{case}: test rollouts from the initial state (window follows the ground "
                 "truth; points outside it are off-window)", fontsize=10)
    fig.tight_layout()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8,
               bbox_to_anchor=(0.5, -0.04))
    return _save(fig, path)


def loss_curves(case: str, records: list, runs_dir: Path, path: Path) -> Path:
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    for i, r in enumerate(records):
        h = pd.read_csv(runs_dir / r["run"] / "history.csv")
        if h.empty:  # a model with nothing to learn (the solver row)
            continue
        c = _color(r["model"], i) if len(records) <= 2 else f"C{i}"
        lbl = f"{_label(r)} s{r['seed']}"
        a.plot(h["epoch"], h["train_loss"], color=c, label=lbl)
        v = h.dropna(subset=["val_rmse"])
        b.plot(v["epoch"], v["val_rmse"], "o-", ms=3, color=c, label=lbl)
    a.set_title("training loss (each model's own normalised loss)", fontsize=9)
    b.set_title("validation rollout RMSE (m)", fontsize=9)
    for ax in (a, b):
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(case, fontsize=10)
    return _save(fig, path)


def first_seed(records: list) -> list:
    """The records of the lowest seed among ``records``."""
    return [r for r in records if r["seed"] == min(x["seed"] for x in records)]


def suite_figures(out: Path, metrics: pd.DataFrame, records: list, runs_dir: Path,
                  steps: dict, tests: dict) -> list:
    """``tests[case]``: the case's test-split arrays (ground truth of the snapshots)."""
    out = Path(out)
    paths = []
    for case in sorted(metrics["case"].unique()):
        recs = [r for r in records if r["case"] == case]
        paths.append(rmse_vs_step(metrics, case, out / f"rmse_vs_step_{case}.png"))
        paths.append(snapshots(case, first_seed(recs), runs_dir, steps[case], out / f"snapshots_{case}.png",
                               tests[case]))
        paths.append(loss_curves(case, recs, runs_dir, out / f"loss_curves_{case}.png"))
    return paths
