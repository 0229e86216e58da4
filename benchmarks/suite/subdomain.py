"""The sub-domain comparison (docs/SUBDOMAIN.md, "The subdomain suite").

Three ways to get an Implicit-Energy model of the r = 8 plate (9,289 nodes), each rolled out
on the whole mesh on the same six test trajectories (the paper's test moduli, identical in
``plate_cantilever_few@r8`` and ``plate_cantilever@r8``):

- ``patches``: trained on 2,000-node patches of the r = 8 mesh (``RESULTS/subdomain/``);
- ``whole mesh``: trained on the whole r = 8 mesh with the same settings
  (``RESULTS/subdomain_whole/``; optional: left out where that suite has not been run, as it
  takes about an hour of one core where the patches take minutes);
- ``paper mesh, transferred``: trained on the paper's 182-node mesh and rolled out at r = 8
  (``RESULTS/subdomain_transfer/transfer/``, r = 8).

``python -m benchmarks.suite.subdomain [--results results]`` reads those tables and writes
``RESULTS/subdomain/comparison.csv`` (per training, seed and table step: RMSE, standing
still's RMSE, their ratio), ``comparison.md`` (the largest ratio from step 25 on, training
time and memory) and ``figures/comparison.png``. Standing still's RMSE per step is the transfer
table's (``no_motion_rmse_mean``), the same test trajectories.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from groundtruth import store

FROM_STEP = 25
#: (label, suite directory, its rmse_at_step table under the directory)
SOURCES = (("patches", "subdomain", "rmse_at_step.csv"),
           ("whole mesh", "subdomain_whole", "rmse_at_step.csv"),
           ("paper mesh, transferred", "subdomain_transfer", "transfer/rmse_at_step.csv"))
COLORS = {"patches": "tab:purple", "whole mesh": "tab:orange",
          "paper mesh, transferred": "tab:gray"}
KEYS = ["training", "case", "model", "seed", "step"]


def _read(results: Path, sub: str, name: str) -> pd.DataFrame:
    path = results / sub / name
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file; run `meshbench run --suite {sub}` "
                                "first (tox -e subdomain runs all three)")
    return pd.read_csv(path)


def comparison_table(results) -> pd.DataFrame:
    """Per training, seed and table step: ``rmse_mean`` (m, mean over the test trajectories),
    ``no_motion_rmse_mean`` (m) and ``vs_no_motion``, with each run's training wall time and
    peak memory (``runs.csv``)."""
    results = Path(results)
    transfer = _read(results, "subdomain_transfer", "transfer/rmse_at_step.csv")
    transfer = transfer[transfer["r"] == 8]
    still = transfer.groupby("step")["no_motion_rmse_mean"].first()
    frames = []
    for label, sub, name in SOURCES:
        if sub == "subdomain_whole" and not (results / sub / name).exists():
            continue  # optional (module docstring)
        cost = ["train_wall_time_s", "peak_rss_mb"]
        if sub == "subdomain_transfer":  # trained on another mesh: its cost is quick's
            part = transfer.assign(**{c: np.nan for c in cost})
        else:
            part = _read(results, sub, name).merge(
                _read(results, sub, "runs.csv")[["seed"] + cost], on="seed", how="left")
        frames.append(part[["case", "model", "seed", "step", "rmse_mean"] + cost]
                      .assign(training=label))
    out = pd.concat(frames, ignore_index=True)
    missing = sorted(set(out["step"]) - set(still.index))
    if missing:
        raise ValueError(f"standing still's RMSE is missing at steps {missing} of the transfer "
                         "table; the tables are not of the same test trajectories")
    out["no_motion_rmse_mean"] = out["step"].map(still)
    out["vs_no_motion"] = out["rmse_mean"] / out["no_motion_rmse_mean"]
    cols = KEYS + ["rmse_mean", "no_motion_rmse_mean", "vs_no_motion", "train_wall_time_s",
                   "peak_rss_mb"]
    return out[cols].sort_values(KEYS, kind="stable").reset_index(drop=True)


def _fmt(x) -> str:
    return "diverged" if not np.isfinite(x) else f"{x:.2g}"


def render_markdown(table: pd.DataFrame) -> str:
    lines = ["# Implicit-Energy on the r = 8 plate (9,289 nodes): patches, whole mesh, "
             "transferred", "",
             "Written by `python -m benchmarks.suite.subdomain` from the tables of the "
             "`subdomain`, `subdomain_whole` and `subdomain_transfer` suites "
             "(docs/SUBDOMAIN.md). Position RMSE over the six test trajectories as a multiple "
             "of standing still's (`vs_no_motion` of `comparison.csv`); median over seeds, "
             "the worst seed in brackets.", "",
             f"| training | seeds | largest from step {FROM_STEP} | " + " | ".join(
                 f"step {s}" for s in sorted(table["step"].unique())) +
             " | training wall time (s) | training peak RSS (MB) |",
             "|---|---|---|" + "---|" * table["step"].nunique() + "---|---|"]
    for label, _, _ in SOURCES:
        d = table[table["training"] == label]
        if d.empty:
            continue
        g = d.groupby("step")["vs_no_motion"]
        med = g.agg(lambda s: s.median(skipna=False))
        worst = g.agg(lambda s: s.max(skipna=False))
        late = med.index >= FROM_STEP
        cells = [f"{_fmt(med[s])} ({_fmt(worst[s])})" for s in med.index]
        tw, rss = d.groupby("seed")[["train_wall_time_s", "peak_rss_mb"]].first().median()
        lines.append(f"| {label} | {d['seed'].nunique()} | {_fmt(med[late].max())} "
                     f"({_fmt(worst[late].max())}) | " + " | ".join(cells) +
                     f" | {'' if np.isnan(tw) else f'{tw:.0f}'} | "
                     f"{'' if np.isnan(rss) else f'{rss:.0f}'} |")
    lines += ["", "The transferred runs were trained on the paper's mesh (their training time "
              "and memory are the `quick` suite's, results/quick/runs.csv).", ""]
    return "\n".join(lines)


def figure(table: pd.DataFrame, path: Path) -> Path:
    """RMSE (m) against step at the table's steps: the median over seeds, the band from the
    best to the worst seed, standing still dashed."""
    from benchmarks.suite.figures import _plt, _save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, _, _ in SOURCES:
        d = table[(table["training"] == label) & (table["step"] > 0)]
        if d.empty:
            continue
        g = d.groupby("step")["rmse_mean"]
        med, lo, hi = g.median(), g.min(), g.max()
        ax.plot(med.index, med.values, "o-", color=COLORS[label],
                label=f"{label} ({d['seed'].nunique()} seeds)")
        ax.fill_between(med.index, lo.values, hi.values, color=COLORS[label], alpha=0.2, lw=0)
    still = table[table["step"] > 0].groupby("step")["no_motion_rmse_mean"].first()
    ax.plot(still.index, still.values, "k--", label="standing still")
    ax.set_yscale("log")
    ax.set_xlabel("step (saved frame, 3 ms)")
    ax.set_ylabel("position RMSE (m), mean over test trajectories")
    ax.set_title("Implicit-Energy on the r = 8 plate (9,289 nodes), whole-mesh rollouts",
                 fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def write(results) -> dict:
    out = Path(results) / "subdomain"
    table = comparison_table(results)
    paths = {"csv": out / "comparison.csv", "markdown": out / "comparison.md",
             "figure": out / "figures" / "comparison.png"}
    text = table.to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(paths["csv"], lambda f: f.write(text), mode="w")
    md = render_markdown(table)
    store.atomic_write(paths["markdown"], lambda f: f.write(md), mode="w")
    figure(table, paths["figure"])
    return paths


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.suite.subdomain",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--results", default="results", help="results directory (default results)")
    args = p.parse_args(argv)
    try:
        paths = write(args.results)
    except (FileNotFoundError, ValueError) as e:
        print(f"benchmarks.suite.subdomain: {e}", file=sys.stderr)
        return 2
    print(Path(paths["markdown"]).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
