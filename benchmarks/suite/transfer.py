"""A suite's runs on finer meshes than they were trained on (``Suite.resolutions``).

A suite with ``resolutions`` (the ``scale`` suite: ``quick``'s runs, 3 seeds, r = 1, 2, 4)
trains its runs on their case as any suite does (finished runs are reused), then rolls the best
checkpoint of every run out on the test split of its case at each resolution r, ``CASE@rN``
(docs/SCALE.md: the same moduli, frames and physics on a mesh r times finer; only the test
split is generated there), through ``TrajectoryModel.on_mesh`` (``runs.rollout_arrays``), and
writes ``RESULTS/SUITE/transfer/``:

- ``transfer/runs.csv``: one row per run and resolution: the rolled-out case, its nodes and
  case hash, the rollout's wall time and peak memory, where and with what it ran (git
  commit, machine, CPU, threads, library versions), and the training run's commit, wall time
  and best epoch;
- ``transfer/metrics.csv``: tidy position RMSE per run, resolution, test trajectory and step
  (and each trajectory's whole rollout), as a suite's ``metrics.csv`` with ``r`` and ``nodes``;
- ``transfer/rmse_at_step.csv``: the paper's table (``metrics.rmse_at_step_table``) per run
  and resolution, with standing still (``no_motion_rmse_mean``: every node kept where it
  starts) and each row's multiple of it (``vs_no_motion``);
- ``transfer/rmse_at_step.md``: per learner and resolution, the median over seeds of
  ``vs_no_motion`` (and the worst seed) at the table's steps;
- ``transfer/figures/transfer_CASE.png``: RMSE against step, one panel per resolution.

At r = 1 a run's rows are its own test rollout's (``test_metrics.csv``): on its training mesh
a model is itself (``on_mesh``), so a second rollout would give the same bits. Each rollout at
r > 1 runs in its own process (its peak memory its own) and is kept in
``runs/RUN_ID/transfer/CASE@rN.csv`` and ``.json``; a later run of the suite reuses it while
the test data's case hash and the checkpoint's SHA-256 are those it was made from.
"""

from __future__ import annotations

import datetime
import os
import platform
import socket
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.suite import metrics as M
from benchmarks.suite import procs
from benchmarks.suite.registry import get_case
from groundtruth import store
from groundtruth.cases.base import resolution_id

TRANSFER_DIR = "transfer"  # RESULTS/SUITE/transfer/ and RUNS/RUN_ID/transfer/
#: the README's summary: the table's steps from this one on
FROM_STEP = 25
ROLLOUT_METRICS = ("rmse_at_step", "full_rollout_rmse")
ID_KEYS = ("run", "case", "r", "nodes", "model", "preset", "integrator", "grad_mode", "seed")

README = """# transfer: learned models on finer meshes than their training mesh

Written by `meshbench run --suite {suite}` (benchmarks/suite/transfer.py, docs/SCALE.md,
"Learned models on other meshes"). Every run of the suite, trained on its case at r = 1, rolled
out by its best checkpoint on the test split of the same case on a mesh r times finer
(`CASE@rN`: the same moduli, frames and physics; `r`, `nodes` columns), r = {rs}. At r = 1 the
rows are the run's own test rollout. The CSV files are plain (no comment lines). RMSE is
defined once, in `meshodenet/metrics.py`: for one trajectory at saved frame k, the root of the
mean over all nodes of the squared Euclidean position error, in metres (clamped nodes included).

## `metrics.csv`

rmse (m): for one run, resolution and test trajectory, metric=rmse_at_step: the RMSE at saved
frame `step` (time `time`, s); metric=full_rollout_rmse: the same mean over nodes and frames
1..T-1 (step = T-1).

## `rmse_at_step.csv`

The paper's steps. rmse_mean / rmse_std (m): mean and population std over the test
trajectories of the per-trajectory RMSE at `step`; rmse_coord_mean / rmse_coord_std: the same
per coordinate (the paper's convention, / sqrt(3)); increase_vs_meshodenet_pct: 100 (mean /
MeshODENet's mean of the same seed, case and r - 1); no_motion_rmse_mean (m): the mean RMSE
of standing still (every node at its initial position) on the same trajectories;
vs_no_motion: rmse_mean / no_motion_rmse_mean. A step at which a test trajectory's rollout
diverged (NaN) has NaN mean.

## `runs.csv`

One row per run and resolution: the case rolled out on (`case`, `r`, `nodes`, `case_hash`),
the rollout's wall time over all test trajectories (`rollout_wall_time_s`; at r = 1 the
suite's own test rollout) and peak resident memory of its process (`peak_rss_mb`, r > 1),
whether a stored rollout was reused, the checkpoint's epoch and SHA-256, and the provenance of
the rollout: git commit, host, CPU, threads, kernel settings, library versions, time; and of
the training run: its commit (`train_git_sha`), wall time and best epoch.

## `rmse_at_step.md`

Per case, learner and r: the median over seeds of vs_no_motion at the table's steps, and the
worst seed.
"""


class TransferError(ValueError):
    """Rollouts on finer meshes failed (the finished ones are kept in the runs)."""


def _log(msg: str) -> None:
    print(f"[meshbench run] transfer: {msg}", file=sys.stderr, flush=True)


def _write_csv(path: Path, df: pd.DataFrame) -> None:
    text = df.to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def run_ids(rec: dict) -> dict:
    """The id columns of a run's rows (without ``case``, ``r``, ``nodes``)."""
    return {k: rec[k] for k in ("run", "model", "preset", "integrator", "grad_mode", "seed")}


def _ids(rec: dict, case_id: str, r: int, nodes: int) -> dict:
    ids = {**run_ids(rec), "case": case_id, "r": r, "nodes": nodes}
    return {k: ids[k] for k in ID_KEYS}


def stored_paths(run_dir: Path, case_id: str) -> tuple[Path, Path]:
    d = Path(run_dir) / TRANSFER_DIR
    return d / f"{case_id}.csv", d / f"{case_id}.json"


def _stored(run_dir: Path, case_id: str, case_hash: str, ck_sha: str) -> dict | None:
    csv, js = stored_paths(run_dir, case_id)
    if not (csv.exists() and js.exists()):
        return None
    try:
        import json

        rec = json.loads(js.read_text())
    except (OSError, ValueError):
        return None
    ok = rec.get("case_hash") == case_hash and rec.get("checkpoint_sha256") == ck_sha
    return rec if ok else None


def transfer_one(rec: dict, run_dir: str, r: int, data_dir, threads: int, plugin_files: tuple,
                 device: str = "auto") -> dict:
    """Roll the run's best checkpoint out on the test split of its case at resolution ``r``
    (> 1) and store its tidy metrics (``stored_paths``); reuses a stored rollout of the same
    data and checkpoint. Executes in a worker process; returns the provenance row."""
    import torch

    from benchmarks.suite import plugins
    from benchmarks.suite.runs import cpu_model, rollout_arrays

    plugins.load_all(plugin_files)
    torch.set_num_threads(threads)
    run_dir = Path(run_dir)
    case = get_case(resolution_id(rec["case"], r))
    ck_sha = store.sha256_file(run_dir / "best.pt")
    h = case.hash()
    found = _stored(run_dir, case.id, h, ck_sha)
    if found is not None:
        return {**found, "reused": True}
    arrays = store.load_split(case, "test", data_dir)
    path = store.data_dir(data_dir) / case.id / "test.npz"
    pred, m = rollout_arrays(run_dir, "test", data_dir, "best", device, data_file=path,
                             arrays=arrays)
    nodes = int(arrays["pos"].shape[2])
    df = M.per_run_metrics(pred["pos"], arrays["pos"], arrays["t"], _ids(rec, case.id, r, nodes))
    csv, js = stored_paths(run_dir, case.id)
    csv.parent.mkdir(exist_ok=True)
    text = df.to_csv(index=False, float_format="%.9g", lineterminator="\n")
    store.atomic_write(csv, lambda f: f.write(text), mode="w")
    row = {**_ids(rec, case.id, r, nodes), "case_hash": h,
           "n_trajectories": m["n_trajectories"], "rmse_m": m["rmse_m"],
           "no_motion_rmse_m": m["no_motion_rmse_m"],
           "rollout_wall_time_s": m["rollout_wall_time_s"],
           "peak_rss_mb": round(procs.peak_rss_mb(), 1), "checkpoint_epoch": m["epoch"],
           "checkpoint_sha256": ck_sha, "reused": False, "git_sha": store.git_sha(),
           "host": socket.gethostname(), "machine": platform.machine(),
           "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
           "threads": torch.get_num_threads(),
           "cpu_capability": torch.backends.cpu.get_cpu_capability(),
           "kernel_env": " ".join(f"{k}={os.environ[k]}" for k in procs.REPRO_ENV
                                  if k in os.environ) or "none",
           "versions": store.library_versions(),
           "timestamp": datetime.datetime.now(datetime.timezone.utc).isoformat(
               timespec="seconds")}
    store.save_json(js, row)
    return row


def _at_r1(rec: dict, runs_dir: Path, nodes: int) -> tuple[pd.DataFrame, dict]:
    """A run's rows at r = 1: its own test rollout's (``test_metrics.csv``), and its
    provenance row (the run's record: where and with what it was rolled out)."""
    from benchmarks.suite.runs import METRICS_FILE

    df = pd.read_csv(runs_dir / rec["run"] / METRICS_FILE)
    df = df[df["metric"].isin(ROLLOUT_METRICS)]
    ids = _ids(rec, rec["case"], 1, nodes)
    df = df.assign(**{k: ids[k] for k in ("r", "nodes")})
    row = {**ids, "case_hash": rec["config"]["case_hash"], "n_trajectories": int(
        df["trajectory"].nunique()), "rmse_m": rec["test_rmse_m"],
        "no_motion_rmse_m": rec["test_no_motion_rmse_m"],
        "rollout_wall_time_s": rec["rollout_wall_time_s"], "peak_rss_mb": np.nan,
        "checkpoint_epoch": rec.get("best_epoch"), "checkpoint_sha256": store.sha256_file(
            runs_dir / rec["run"] / "best.pt"), "reused": True,
        **{k: rec.get(k) for k in ("git_sha", "host", "machine", "cpu_model", "cpu_count",
                                   "threads", "cpu_capability", "kernel_env", "versions",
                                   "timestamp")}}
    return df, row


def test_cases(records: list, resolutions) -> list[str]:
    """The ids of the cases rolled out on: each run's case at each resolution, in order."""
    bases = dict.fromkeys(rec["case"] for rec in records)
    return [resolution_id(c, r) for c in bases for r in resolutions]


def run_transfer(out: Path, records: list, runs_dir: Path, suite, *, data_dir=None,
                 jobs: int = 1, threads: int = 1, plugin_files=(), device: str = "auto",
                 figures: bool = True, progress: bool = True, stored_only: bool = False) -> dict:
    """Generate the test splits of the suite's cases at its resolutions (r > 1), roll every
    run (``records``: the runner's) out on them and write ``out/transfer/``; returns the
    paths written. ``stored_only`` (``meshbench run --tables-only``): generate and roll out
    nothing, write the tables of the rollouts stored in the runs; those not stored yet are
    left out and named in ``rmse_at_step.md``."""
    from benchmarks.suite.generate import generate

    resolutions = tuple(suite.resolutions)
    runs_dir = Path(runs_dir)
    for cid in [] if stored_only else test_cases(records, [r for r in resolutions if r > 1]):
        rep = generate(get_case(cid), data_dir, progress=progress, splits=("test",),
                       on_wait=lambda pid, c=cid: _log(f"data {c}: process {pid or '?'} is "
                                                       "generating it; waiting for it"))
        _log(f"data {cid} (test split): " + ("up to date" if rep.reused else
                                             f"generated in {rep.wall_time_s:.0f} s"))
    root = store.data_dir(data_dir)
    tests = {cid: store.load_split(get_case(cid), "test", data_dir)
             for cid in test_cases(records, resolutions)
             if not stored_only or (root / cid / "test.npz").exists()}
    nodes = {cid: int(a["pos"].shape[2]) for cid, a in tests.items()}
    frames, rows = [], {}
    for rec in records:
        if 1 in resolutions:
            df, row = _at_r1(rec, runs_dir, nodes[rec["case"]])
            frames.append(df)
            rows[(rec["run"], 1)] = row
    tasks, missing = {}, []
    # coarsest first, then the runs whose rollout at r = 1 was quickest: an interrupted
    # suite has done the most (the stored rollouts are reused when it is run again)
    for r in resolutions:
        for rec in sorted(records, key=lambda rec: rec.get("rollout_wall_time_s") or 0.0):
            if r > 1 and stored_only:
                cid = resolution_id(rec["case"], r)
                found = cid in tests and _stored(
                    runs_dir / rec["run"], cid, get_case(cid).hash(),
                    store.sha256_file(runs_dir / rec["run"] / "best.pt"))
                if found:
                    rows[(rec["run"], r)] = {**found, "reused": True}
                else:
                    missing.append((rec["run"], r))
            elif r > 1:
                tasks[(rec["run"], r)] = (transfer_one, (
                    rec, str(runs_dir / rec["run"]), r, None if data_dir is None
                    else str(data_dir), threads, tuple(str(p) for p in plugin_files), device))
    failures = {}

    def on_result(key, kind, value):
        run, r = key
        if kind == "ok":
            rows[key] = value
            how = "reused" if value.get("reused") else \
                f"rolled out in {value['rollout_wall_time_s']:.1f} s"
            _log(f"[{len(rows) - (len(records) if 1 in resolutions else 0)}/{len(tasks)}] "
                 f"{run} on {value['case']}: {how}; RMSE {value['rmse_m']:.4g} m (no motion "
                 f"{value['no_motion_rmse_m']:.4g} m)")
        else:
            failures[key] = f"{kind}: {value}"
            _log(f"{run} at r = {r}: FAILED: {kind}: {value}")

    procs.run_tasks(tasks, min(jobs, max(1, len(tasks))), on_result)
    if failures:
        raise TransferError(f"{len(failures)} transfer rollout(s) of suite {suite.name!r} failed "
                         "(finished rollouts are kept in each run's transfer/; rerun the same "
                         "command to resume): " + "; ".join(
                             f"{k[0]} at r = {k[1]}: {v}" for k, v in failures.items()))
    for r in resolutions:
        for rec in records:
            if r > 1 and (rec["run"], r) not in missing:
                frames.append(pd.read_csv(stored_paths(runs_dir / rec["run"],
                                                       resolution_id(rec["case"], r))[0]))
    metrics = pd.concat(frames, ignore_index=True)
    metrics["r"] = metrics["r"].astype(int)
    metrics["nodes"] = metrics["nodes"].astype(int)
    metrics = metrics[list(ID_KEYS) + [c for c in metrics.columns if c not in ID_KEYS]]
    order = [(rec["run"], r) for r in resolutions for rec in records
             if (rec["run"], r) not in missing]
    if missing:
        _log(f"{len(missing)} rollout(s) not stored yet, left out: " + ", ".join(
            f"{run} at r = {r}" for run, r in missing))
    trained = {rec["run"]: {"train_git_sha": rec.get("git_sha"), "train_wall_time_s":
                            rec.get("train_wall_time_s"), "best_epoch": rec.get("best_epoch")}
               for rec in records}
    provenance = pd.DataFrame([{**_flat(rows[k]), **trained[k[0]]} for k in order])
    return write_tables(Path(out) / TRANSFER_DIR, metrics, provenance, tests, suite,
                        figures=figures, missing=missing)


def tables_from_stored(suite, results_dir, runs_dir, *, seeds=None, only=None, data_dir=None,
                       figures: bool = True) -> dict:
    """``meshbench run --tables-only`` of a suite with resolutions: ``RESULTS/SUITE/transfer/``
    from the finished runs (``record.json``) and the rollouts stored in them; trains, generates
    and rolls out nothing."""
    import json

    from benchmarks.suite.runs import RECORD_FILE

    runs_dir = Path(runs_dir)
    specs = suite.runs(seeds, only)
    records = [json.loads((runs_dir / r.run_id / RECORD_FILE).read_text()) for r in specs
               if (runs_dir / r.run_id / RECORD_FILE).exists()]
    if not records:
        raise FileNotFoundError(f"{runs_dir}: no finished run of suite {suite.name!r}; "
                                f"`meshbench run --suite {suite.name}` trains and rolls them out")
    gone = [r.run_id for r in specs if not (runs_dir / r.run_id / RECORD_FILE).exists()]
    if gone:
        _log(f"{len(gone)} run(s) not finished, left out: {', '.join(gone)}")
    return run_transfer(Path(results_dir) / suite.name, records, runs_dir, suite,
                        data_dir=data_dir, figures=figures, stored_only=True)


def _flat(row: dict) -> dict:
    out = {k: v for k, v in row.items() if k != "versions"}
    for lib, ver in sorted((row.get("versions") or {}).items()):
        out[f"version_{lib}"] = ver
    return out


def no_motion_table(tests: dict, steps: dict) -> pd.DataFrame:
    """Standing still's mean RMSE over the test trajectories at each table step, per case."""
    rows = []
    for cid in steps:
        true = tests[cid]["pos"]
        r = M.rmse_per_step(M.no_motion(true), true)
        for s in steps[cid]:
            rows.append({"case": cid, "step": int(s), "no_motion_rmse_mean": r[:, s].mean()})
    return pd.DataFrame(rows)


def rmse_table(metrics: pd.DataFrame, tests: dict) -> pd.DataFrame:
    """The paper's table per run and resolution (``metrics.rmse_at_step_table``) with standing
    still and each row's multiple of it."""
    at = metrics[metrics["metric"] == "rmse_at_step"]
    steps = {c: M.table_steps(c, int(at.loc[at["case"] == c, "step"].max()) + 1)
             for c in at["case"].unique()}
    table = M.rmse_at_step_table(at.drop(columns=["metric", "run"]), steps)
    table = table.merge(no_motion_table(tests, steps), on=["case", "step"], how="left")
    table["vs_no_motion"] = table["rmse_mean"] / table["no_motion_rmse_mean"]
    return table


def summary(table: pd.DataFrame, from_step: int = FROM_STEP) -> pd.DataFrame:
    """Per base case, model and r: the median over seeds of ``vs_no_motion`` at each step, the
    worst seed's, and over the steps from ``from_step`` on (a case whose table ends before:
    its last step): the largest median (``median_max``) and the largest of any seed
    (``worst_max``)."""
    t = table.assign(base=table["case"].str.partition("@")[0])
    g = t.groupby(["base", "model", "r", "nodes", "step"], sort=True)["vs_no_motion"]
    per = pd.DataFrame({"median": g.median(), "worst": g.max(), "seeds": g.size()}).reset_index()
    per["worst"] = g.agg(lambda s: s.max(skipna=False)).to_numpy()  # a NaN seed shows
    per["median"] = g.agg(lambda s: s.median(skipna=False)).to_numpy()
    last = per.groupby("base")["step"].transform("max")  # a short case: its last step
    late = per[per["step"] >= np.minimum(from_step, last)]
    h = late.groupby(["base", "model", "r", "nodes"], sort=True)
    tops = pd.DataFrame({"median_max": h["median"].agg(lambda s: s.max(skipna=False)),
                         "median_min": h["median"].min(),
                         "worst_max": h["worst"].agg(lambda s: s.max(skipna=False))}).reset_index()
    return per.merge(tops, on=["base", "model", "r", "nodes"], how="left")


def _fmt(x) -> str:
    return "diverged" if not np.isfinite(x) else f"{x:.2g}" if x < 10 else f"{x:.0f}"


def render_markdown(table: pd.DataFrame, suite, from_step: int = FROM_STEP,
                    missing=()) -> str:
    s = summary(table, from_step)
    lines = [f"# Suite `{suite.name}`: learned models on finer meshes", "",
             suite.description + ".", "",
             "Position RMSE as a multiple of standing still's (`vs_no_motion` of "
             "`rmse_at_step.csv`: mean over the test trajectories at the step, over the same "
             "for every node kept at its initial position), median over the seeds (the worst "
             "seed in brackets). r: the mesh r times finer than the training mesh (r = 1).",
             ""]
    if missing:
        lines += [f"**Incomplete**: {len(missing)} rollout(s) not stored yet, left out "
                  f"(`meshbench run --suite {suite.name}` rolls them out): "
                  + ", ".join(f"{run} at r = {r}" for run, r in missing) + ".", ""]
    lines += [f"## Largest over the table's steps from {from_step} on", ""]
    for base, d in s.groupby("base", sort=True):
        rs = sorted(d["r"].unique())
        nd = d.drop_duplicates("r").set_index("r")["nodes"]
        lines += [f"### {base}", "", "| model | " + " | ".join(
            f"r = {r} ({nd[r]} nodes)" for r in rs) + " |", "|---|" + "---|" * len(rs)]
        for model, dm in _models(d):
            x = dm.drop_duplicates("r").set_index("r")
            lines.append(f"| {model} | " + " | ".join(
                f"{_fmt(x.loc[r, 'median_max'])} ({_fmt(x.loc[r, 'worst_max'])})"
                if r in x.index else "" for r in rs) + " |")
        lines.append("")
    lines += ["## At every step of the table", ""]
    for base, d in s.groupby("base", sort=True):
        steps = sorted(d["step"].unique())
        lines += [f"### {base}", "", "| model | r | " + " | ".join(
            f"step {k}" for k in steps) + " |", "|---|---|" + "---|" * len(steps)]
        for model, dm in _models(d):
            for r, dr in dm.groupby("r", sort=True):
                x = dr.set_index("step")
                lines.append(f"| {model} | {r} | " + " | ".join(
                    f"{_fmt(x.loc[k, 'median'])} ({_fmt(x.loc[k, 'worst'])})" for k in steps)
                    + " |")
        lines.append("")
    return "\n".join(lines)


def _models(d: pd.DataFrame) -> list:
    """``(model, rows)`` in the suite's usual order: learners first, the solver row last."""
    from benchmarks.suite.figures import COLORS
    from benchmarks.suite.runs import trainable

    rank = {m: i for i, m in enumerate(COLORS)}
    groups = list(d.groupby("model", sort=True))
    return sorted(groups, key=lambda g: (not trainable(g[0]), rank.get(g[0], len(rank))))


def write_tables(out: Path, metrics: pd.DataFrame, provenance: pd.DataFrame, tests: dict,
                 suite, figures: bool = True, missing=()) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    table = rmse_table(metrics, tests)
    paths = {"runs": out / "runs.csv", "metrics": out / "metrics.csv",
             "rmse_at_step": out / "rmse_at_step.csv", "markdown": out / "rmse_at_step.md",
             "readme": out / "README.md"}
    _write_csv(paths["runs"], provenance)
    _write_csv(paths["metrics"], metrics)
    _write_csv(paths["rmse_at_step"], table)
    md = render_markdown(table, suite, missing=missing)
    store.atomic_write(paths["markdown"], lambda f: f.write(md), mode="w")
    rs = ", ".join(str(r) for r in sorted(metrics["r"].unique()))
    text = README.format(suite=suite.name, rs=rs)
    store.atomic_write(paths["readme"], lambda f: f.write(text), mode="w")
    if figures:
        paths["figures"] = [figure(metrics, tests, base, out / "figures" / f"transfer_{base}.png")
                            for base in dict.fromkeys(c.partition("@")[0]
                                                      for c in metrics["case"])]
    return paths


def figure(metrics: pd.DataFrame, tests: dict, base: str, path: Path) -> Path:
    """RMSE (m, mean over test trajectories) against step, one panel per resolution, one line
    per learner: the median over seeds, the band from the best to the worst seed; standing
    still dashed."""
    from benchmarks.suite.figures import _color, _plt, _save

    plt = _plt()
    m = metrics[(metrics["metric"] == "rmse_at_step") & (metrics["step"] > 0)
                & (metrics["case"].str.partition("@")[0] == base)]
    rs = sorted(m["r"].unique())
    fig, axes = plt.subplots(1, len(rs), figsize=(4.2 * len(rs), 3.8), sharey=True,
                             squeeze=False)
    for ax, r in zip(axes[0], rs):
        d = m[m["r"] == r]
        cid = d["case"].iloc[0]
        for i, (model, dm) in enumerate(_models(d)):
            per_seed = dm.groupby(["seed", "step"])["rmse"].agg(
                lambda s: s.mean(skipna=False)).unstack("seed")
            med = per_seed.median(axis=1, skipna=False)
            ax.fill_between(per_seed.index, per_seed.min(axis=1), per_seed.max(axis=1),
                            color=_color(model, i), alpha=0.2, lw=0)
            ax.plot(med.index, med, color=_color(model, i), lw=1.2, label=model)
        true = tests[cid]["pos"]
        still = M.rmse_per_step(M.no_motion(true), true).mean(axis=0)
        ax.plot(np.arange(1, len(still)), still[1:], "k--", lw=1, label="standing still")
        ax.set_yscale("log")
        ax.set_title(f"r = {r} ({int(d['nodes'].iloc[0])} nodes)")
        ax.set_xlabel(f"step (saved frame, {float(np.diff(tests[cid]['t'][:2])[0]):g} s)")
        ax.grid(alpha=0.3, which="both", lw=0.5)
    axes[0][0].set_ylabel("position RMSE (m), mean over test trajectories")
    seen = {}  # every panel's lines in one legend (a resolution may lack a learner)
    for ax in axes[0]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    axes[0][-1].legend(list(seen.values()), list(seen), fontsize=7, loc="lower right")
    fig.suptitle(f"{base}: trained at r = 1, rolled out on meshes r times finer "
                 "(median over seeds, band: best to worst seed)", fontsize=9)
    return _save(fig, path)
