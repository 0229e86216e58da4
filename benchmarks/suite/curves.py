"""Learning curves: position RMSE of a suite's budget checkpoints against training CPU time.

Training with ``TrainConfig.budgets_s`` leaves in each run directory ``budgets.csv`` and
``budgets/best_{budget}s.pt``, the best-so-far model on validation once the run had spent that
many CPU seconds (``meshodenet.training.train``). ``build_curves`` rolls every such checkpoint of a
suite's runs out on the run's validation split and on the test split and writes, under
``RESULTS/SUITE/``:

- ``curves.csv``: one row per (run, budget, split, step): ``run, case, model, seed, budget_s,
  cpu_s, split, step, rmse``. ``cpu_s`` is the CPU time the run had spent when the checkpoint
  was taken (at the end of the epoch that crossed ``budget_s``); ``split`` is ``val`` or
  ``test``; ``rmse`` (m) is the mean over the split's trajectories of the per-trajectory RMSE
  (``benchmarks.suite.metrics``) at saved frame ``step`` (the case's table steps), or over the
  whole rollout (frames 1..T-1) for ``step = -1`` (``ALL_STEPS``, an int so the column stays
  integer);
- ``curves_checkpoints.json``: the SHA-256 of every checkpoint evaluated, so that a second
  call recomputes only the checkpoints that are new or changed;
- ``runs/RUN_ID/``: the run's provenance, copied from its run directory (``config.json``,
  ``budgets.csv``, ``history.csv``, and ``sessions.json`` / ``record.json`` once training
  wrote them) and ``evaluation.json`` (git commit, library versions, machine and device of the
  process that evaluated its checkpoints). Small text files, committed with the table: the
  checkpoints themselves stay in ``RUNS/`` (megabytes each), and a later session, on another
  machine, adds the runs it trains to the same table without losing these;
- ``figures/curves_{case}.png``: RMSE at the last table step and over whole rollouts (test
  split) against training CPU time, log-log, one line per model (and seed), with the
  no-motion level, the paper's MeshODENet number and, where ``RESULTS/quick/`` holds them,
  the ``quick`` suite's seeds (the short end of each curve).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.suite import metrics as M
from benchmarks.suite.registry import get_case
from benchmarks.suite.runs import CONFIG_FILE, load_run_model
from benchmarks.suite.suites import Suite
from groundtruth import store

COLUMNS = ("run", "case", "model", "seed", "budget_s", "cpu_s", "split", "step", "rmse")
ALL_STEPS = -1
CURVES_FILE = "curves.csv"
INDEX_FILE = "curves_checkpoints.json"
PROVENANCE_DIR = "runs"
#: Copied from each run directory into ``RESULTS/SUITE/runs/RUN_ID/`` (those that exist).
PROVENANCE_FILES = ("config.json", "budgets.csv", "history.csv", "sessions.json", "record.json")
EVALUATION_FILE = "evaluation.json"
SPLITS = ("val", "test")


def paper_meshodenet(case: str) -> tuple | None:
    """``(step, RMSE in m)``: the paper's MeshODENet at its last table step, converted to this
    suite's per-node Euclidean convention (the paper's value is per coordinate: times sqrt 3)."""
    from benchmarks.suite.metrics import PAPER_TABLES, PER_COORDINATE

    row = PAPER_TABLES.get(case, {}).get("meshodenet")
    if not row:
        return None
    step = max(row)
    return step, row[step] / PER_COORDINATE


def _log(msg: str) -> None:
    print(f"[meshbench curves] {msg}", file=sys.stderr, flush=True)


def read_budgets(run_dir: Path) -> pd.DataFrame | None:
    """A run's ``budgets.csv`` (None when the run has none yet); ``ValueError`` naming the
    file when it lacks a column."""
    from meshodenet.training.train import BUDGET_FIELDS, BUDGETS_FILE

    path = run_dir / BUDGETS_FILE
    if not path.exists():
        return None
    df = pd.read_csv(path)
    missing = [c for c in BUDGET_FIELDS if c not in df]
    if missing:
        raise ValueError(f"{path}: not a budgets file (missing columns {missing}); delete it "
                         "and resume the run to rewrite it")
    return df


def read_config(run_dir: Path) -> dict:
    path = run_dir / CONFIG_FILE
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: unreadable ({e}); rerun `meshbench run` for this run") from None


class SplitCache:
    """Each case's train and test arrays, loaded once; ``data(config, split)`` the run's
    ``val`` trajectories (its ``split.val_idx`` of the train file) or the ``test`` ones."""

    def __init__(self, data_dir=None):
        self.data_dir, self.arrays = data_dir, {}

    def load(self, case_id: str, split: str) -> dict:
        key = (case_id, "train" if split == "val" else split)
        if key not in self.arrays:
            self.arrays[key] = store.load_split(get_case(case_id), key[1], self.data_dir)
        return self.arrays[key]

    def data(self, config: dict, split: str, model):
        """The split's trajectories on the model's device, after checking its mesh."""
        import torch

        from meshodenet.mesh.data import Mesh, Trajectories

        arrays = self.load(config["case"], split)
        name = f"{config['case']}/{'train' if split == 'val' else split}.npz"
        if str(arrays["case_hash"]) != config.get("case_hash"):
            raise ValueError(f"{name}: generated for another version of case {config['case']!r} "
                             "than the run was trained on (case_hash differs); rerun "
                             "`meshbench run` to retrain it")
        model.check_mesh(Mesh.from_arrays(arrays, name), name)
        data = Trajectories.from_arrays(arrays, device=model.device, name=name)
        if split == "val":
            data = data.subset(torch.as_tensor(config["split"]["val_idx"], dtype=torch.long))
        return data


def split_rmse(model, data, case_id: str) -> dict:
    """``{step: rmse}`` (m) of the model's rollouts of ``data``: the mean over trajectories of
    the RMSE at each table step, and over whole rollouts at ``ALL_STEPS``."""
    pos, _ = model.rollout_all(data, 16)
    pred = pos.detach().double().cpu().numpy()
    true = data.pos.detach().double().cpu().numpy()
    return rmse_summary(pred, true, case_id)


def rmse_summary(pred: np.ndarray, true: np.ndarray, case_id: str) -> dict:
    """``(B, T, N, 3)`` twice -> ``{step: mean over trajectories of the RMSE}`` at the case's
    table steps and ``ALL_STEPS`` (whole rollouts), m."""
    per_step = M.rmse_per_step(pred, true)
    T = per_step.shape[1]
    out = {int(s): float(per_step[:, s].mean()) for s in M.table_steps(case_id, T) if s < T}
    out[ALL_STEPS] = float(M.full_rollout_rmse(pred, true).mean())
    return out


def checkpoint_rows(path: Path, config: dict, ids: dict, cpu_s: float, cache: SplitCache,
                    device="cpu") -> pd.DataFrame:
    """The curve rows of one budget checkpoint: both splits, every step."""
    model = load_run_model(path, device)[0]
    rows = []
    for split in SPLITS:
        data = cache.data(config, split, model)
        if not len(data):  # a run trained without a validation split
            continue
        for step, rmse in split_rmse(model, data, config["case"]).items():
            rows.append({**ids, "cpu_s": cpu_s, "split": split, "step": step, "rmse": rmse})
    return pd.DataFrame(rows, columns=COLUMNS)


def sort_curves(df: pd.DataFrame) -> pd.DataFrame:
    """Rows in a fixed order: case, model, seed, run, budget, split, step (whole rollouts,
    step -1, first)."""
    return df.sort_values(["case", "model", "seed", "run", "budget_s", "split", "step"],
                          kind="stable").reset_index(drop=True)[list(COLUMNS)]


def write_curves(path: Path, df: pd.DataFrame) -> None:
    """``curves.csv``, sorted, floats ``%.6g``, atomically; and the directory's README.md."""
    from benchmarks.suite.runner import write_readme

    text = sort_curves(df).to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")
    write_readme(Path(path).parent)


def read_curves(out: Path) -> tuple[pd.DataFrame, dict]:
    """What an earlier call wrote: the rows of ``curves.csv`` and the checkpoint index."""
    path, index_path = out / CURVES_FILE, out / INDEX_FILE
    df = pd.read_csv(path) if path.exists() else pd.DataFrame(columns=COLUMNS)
    missing = [c for c in COLUMNS if c not in df]
    if missing:
        raise ValueError(f"{path}: not a curves file (missing columns {missing}); delete it "
                         "to rebuild it")
    try:
        index = json.loads(index_path.read_text()) if index_path.exists() else {}
    except (OSError, json.JSONDecodeError):
        index = {}  # then every checkpoint is evaluated again
    return df, index if isinstance(index, dict) else {}


def _ids(spec, budget: int) -> dict:
    return {"run": spec.run_id, "case": spec.case, "model": spec.model, "seed": spec.seed,
            "budget_s": int(budget)}


def _todo(suite: Suite, runs_dir: Path, seeds, only) -> list:
    """``(spec, config, budgets row, checkpoint path)`` of every budget checkpoint of the
    suite's runs present on disk."""
    from meshodenet.training.train import budget_checkpoint

    todo = []
    for spec in suite.runs(seeds, only):
        run_dir = runs_dir / spec.run_id
        budgets = read_budgets(run_dir) if run_dir.is_dir() else None
        if budgets is None:
            _log(f"{spec.run_id}: no budget checkpoints yet (no {run_dir}/budgets.csv)")
            continue
        config = read_config(run_dir)
        for row in budgets.itertuples(index=False):
            path = budget_checkpoint(run_dir, row.budget_s)
            if path.exists():
                todo.append((spec, config, row, path))
    return todo


def build_curves(suite: Suite, *, results_dir="results", runs_dir="runs", data_dir=None,
                 seeds: int | None = None, only: str | None = None, device="cpu",
                 figures: bool = True) -> dict:
    """Evaluate every budget checkpoint of ``suite``'s runs not evaluated yet (or changed
    since), write ``curves.csv`` after each one and the figures at the end; returns the paths
    and the counts ``computed`` / ``kept``."""
    runs_dir, out = Path(runs_dir), Path(results_dir) / suite.name
    todo = _todo(suite, runs_dir, seeds, only)
    if not todo:
        raise ValueError(f"no budget checkpoints under {runs_dir} for suite {suite.name!r}; "
                         f"train its runs first (meshbench run --suite {suite.name})")
    df, index = read_curves(out)
    cache, computed = SplitCache(data_dir), 0
    # the code's state: curves.csv and the archived run files it rewrites (committed files)
    # do not make the evaluation record say "dirty"
    sha = store.git_sha(exclude=[out])
    for spec in dict.fromkeys(t[0] for t in todo):
        archive_provenance(runs_dir / spec.run_id, out / PROVENANCE_DIR / spec.run_id)
    evaluated: set = set()
    for k, (spec, config, row, path) in enumerate(todo, 1):
        key, sha = str(int(row.budget_s)), store.sha256_file(path)
        have = (df["run"] == spec.run_id) & (df["budget_s"] == int(row.budget_s))
        if index.get(spec.run_id, {}).get(key) == sha and have.any():
            continue
        rows = checkpoint_rows(path, config, _ids(spec, row.budget_s), float(row.cpu_s),
                               cache, device)
        df = rows if df.empty else pd.concat([df[~have], rows], ignore_index=True)
        write_curves(out / CURVES_FILE, df)
        index.setdefault(spec.run_id, {})[key] = sha
        store.save_json(out / INDEX_FILE, index)
        computed += 1
        if spec.run_id not in evaluated:
            evaluated.add(spec.run_id)
            write_evaluation(out / PROVENANCE_DIR / spec.run_id / EVALUATION_FILE, device, sha)
        test_all = rows[(rows["split"] == "test") & (rows["step"] == ALL_STEPS)]["rmse"].iloc[0]
        _log(f"[{k}/{len(todo)}] {spec.run_id}: budget {key} s (CPU {row.cpu_s:.0f} s, epoch "
             f"{row.epoch}): test RMSE over rollouts {test_all:.4g} m")
    _log(f"{computed} checkpoint(s) evaluated, {len(todo) - computed} unchanged and kept")
    paths = {"curves": out / CURVES_FILE}
    if figures:
        paths["figures"] = curve_figures(out / "figures", df, cache,
                                         quick_points(Path(results_dir) / "quick"))
    return {**paths, "computed": computed, "kept": len(todo) - computed}


def archive_provenance(run_dir: Path, dest: Path) -> list:
    """Copy the run's ``PROVENANCE_FILES`` that exist into ``dest`` (atomically, only those
    that changed); returns the names copied."""
    copied = []
    for name in PROVENANCE_FILES:
        src, dst = run_dir / name, dest / name
        if not src.exists():
            continue
        data = src.read_bytes()
        if dst.exists() and dst.read_bytes() == data:
            continue
        store.atomic_write(dst, lambda f, d=data: f.write(d))
        copied.append(name)
    return copied


def write_evaluation(path: Path, device: str, git_sha: str | None = None) -> None:
    """Who evaluated a run's checkpoints: git commit (``git_sha``, taken before the evaluation
    wrote anything; default now), library versions, machine, device."""
    import datetime
    import platform

    from benchmarks.suite.runner import _cpu_model

    store.save_json(path, {
        "git_sha": git_sha or store.git_sha(), "versions": store.library_versions(),
        "host": platform.node(), "machine": platform.machine(), "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(), "device": str(device),
        "timestamp": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})


def quick_points(quick_dir: Path) -> pd.DataFrame:
    """The ``quick`` suite's seeds as points on the curves' axes, from ``quick_dir``'s
    ``metrics.csv`` (test split; per run the mean over trajectories, as in ``curves.csv``,
    then mean and std over seeds) and ``runs.csv`` (x: the median over seeds of the training
    wall time: the quick runs recorded no CPU time): columns case, model, step (``ALL_STEPS``
    for whole rollouts), x_s, rmse_mean, rmse_std, n_seeds. Empty when the files are missing
    or lack a column."""
    cols = ["case", "model", "step", "x_s", "rmse_mean", "rmse_std", "n_seeds"]
    try:
        runs = pd.read_csv(quick_dir / "runs.csv")
        met = pd.read_csv(quick_dir / "metrics.csv")
    except (OSError, ValueError, pd.errors.ParserError):
        return pd.DataFrame(columns=cols)
    need_runs, need_met = {"run", "case", "model", "seed", "train_wall_time_s"}, {
        "run", "metric", "step", "rmse"}
    if not need_runs <= set(runs) or not need_met <= set(met):
        return pd.DataFrame(columns=cols)
    runs = runs[runs["train_wall_time_s"] > 0]  # the solver row trains nothing
    met = met[met["run"].isin(runs["run"])]
    per_run = []
    for metric, step_of in (("rmse_at_step", None), ("full_rollout_rmse", ALL_STEPS)):
        d = met[met["metric"] == metric]
        g = d.groupby(["run", "step"] if step_of is None else ["run"])["rmse"].agg(
            lambda s: s.mean(skipna=False))  # a diverged trajectory makes its run's row NaN
        g = g.reset_index()
        if step_of is not None:
            g["step"] = step_of
        per_run.append(g)
    per_run = pd.concat(per_run, ignore_index=True).merge(
        runs[["run", "case", "model", "seed", "train_wall_time_s"]], on="run")
    out = per_run.groupby(["case", "model", "step"]).agg(
        x_s=("train_wall_time_s", "median"), rmse_mean=("rmse", "mean"),
        rmse_std=("rmse", "std"), n_seeds=("seed", "nunique")).reset_index()
    return out[cols]


def no_motion_levels(case_id: str, cache: SplitCache) -> dict:
    """The no-motion prediction's ``rmse_summary`` on the test split (``{step: rmse}``, m)."""
    true = np.asarray(cache.load(case_id, "test")["pos"], float)
    return rmse_summary(M.no_motion(true), true, case_id)


def curve_figures(out: Path, df: pd.DataFrame, cache: SplitCache,
                  quick: pd.DataFrame | None = None) -> list:
    quick = pd.DataFrame() if quick is None else quick
    return [curve_figure(df[df["case"] == case], case, no_motion_levels(case, cache),
                         out / f"curves_{case}.png",
                         quick[quick["case"] == case] if len(quick) else None)
            for case in sorted(df["case"].unique())]


def curve_figure(df: pd.DataFrame, case: str, no_motion: dict, path: Path,
                 quick: pd.DataFrame | None = None) -> Path:
    """Two log-log panels of the test split against training CPU time: RMSE at the last table
    step and over whole rollouts; one line per model (and seed), the no-motion level dashed,
    the paper's MeshODENet number (where it exists, converted to this figure's per-node
    convention) dotted, the ``quick`` suite's seeds (``quick_points``: mean ± std, at their
    median training wall time) as open squares."""
    from benchmarks.suite.figures import _color, _plt, _save

    plt = _plt()
    test = df[df["split"] == "test"]
    last = max(s for s in no_motion if s != ALL_STEPS)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.4), sharex=True, layout="constrained")
    seeds = test["seed"].nunique() > 1
    for ax, step, title in ((axes[0], last, f"RMSE at step {last}"),
                            (axes[1], ALL_STEPS, "RMSE over whole rollouts")):
        for i, ((model, seed), d) in enumerate(test[test["step"] == step]
                                               .groupby(["model", "seed"], sort=True)):
            d = d.sort_values("cpu_s")
            ax.plot(d["cpu_s"], d["rmse"], "o-", color=_color(model, i),
                    label=f"{model} s{seed}" if seeds else model)
        if quick is not None and len(quick):
            q = quick[(quick["step"] == step) & quick["model"].isin(test["model"].unique())]
            for j, r in enumerate(q.itertuples(index=False)):
                ax.errorbar([r.x_s], [r.rmse_mean], yerr=[[0.0 if pd.isna(r.rmse_std) else
                                                          min(r.rmse_std, 0.9 * r.rmse_mean)],
                                                         [0.0 if pd.isna(r.rmse_std) else
                                                          r.rmse_std]],
                            fmt="s", mfc="none", color=_color(r.model, j), capsize=3,
                            label=f"{r.model}, quick ({r.n_seeds} seeds; x: wall time)")
        ax.axhline(no_motion[step], color="0.5", ls="--", label="no motion")
        paper = paper_meshodenet(case)
        if paper and step == paper[0]:
            ax.axhline(paper[1], color="tab:blue", ls=":",
                       label="paper MeshODENet (GPU; its table value × √3: per node)")
        ax.set(xscale="log", yscale="log", xlabel="training CPU time (s)", ylabel="RMSE (m)",
               title=title)
        _budget_ticks(ax, sorted(test["budget_s"].unique()))
        ax.grid(True, which="both", alpha=0.3)
    # below the panels: with three or more models an in-axes legend hides points
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncol=3,
               fontsize=8)
    fig.suptitle(f"{case}: test error against training time")
    return _save(fig, path)


def _budget_label(seconds: float) -> str:
    """``120`` -> ``"120 s\n2 min"``, ``7200`` -> ``"7200 s\n2 h"``: a budget tick's label."""
    human = f"{seconds / 3600:g} h" if seconds >= 3600 else f"{seconds / 60:g} min"
    return f"{seconds:g} s\n{human}"


def _budget_ticks(ax, budgets) -> None:
    """Major x ticks at the budgets (labelled in seconds and minutes or hours), no minor
    labels: matplotlib's default log-axis labels overlap on a one-and-a-half-decade axis."""
    from matplotlib.ticker import FixedLocator, NullFormatter

    if not len(budgets):
        return
    ax.xaxis.set_major_locator(FixedLocator([float(b) for b in budgets]))
    ax.set_xticklabels([_budget_label(float(b)) for b in budgets])
    ax.xaxis.set_minor_formatter(NullFormatter())
