"""``meshbench run``: execute a suite and write its results.

For each run of the suite (see ``benchmarks/suite/suites.py``) the runner generates the case's data
if missing, trains into ``RUNS/RUN_ID`` (resuming an interrupted run, reusing a finished one
whose configuration is unchanged, retraining one whose configuration changed), rolls the best
checkpoint out on the test split and scores it. Then it writes under ``RESULTS/SUITE/``:

- ``runs.csv``: one row per run (ids, seed, preset, parameters, wall times, peak memory,
  device, threads, library versions, git SHA, timestamp);
- ``metrics.csv``: tidy RMSE per run, test trajectory and step, plus each trajectory's
  full-rollout RMSE (``metric`` column);
- ``rmse_at_step.csv`` and ``.md``: the paper's table (mean and std over test trajectories at
  the paper's steps, and the increase over MeshODENet in percent);
- ``figures/``: RMSE vs step, rollout snapshots and loss curves per case, and an animated
  rollout (GIF) per case and model.

Every run executes in its own process (so its peak memory is its own); ``jobs`` of them at a
time, each with ``threads`` torch threads. Nothing in ``RESULTS/SUITE`` is touched until every
run has finished; each file is written atomically.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shutil
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.suite import horizon as H
from benchmarks.suite import metrics as M
from benchmarks.suite import procs
from benchmarks.suite.metrics import per_run_metrics  # noqa: F401 - used here and by tests
from benchmarks.suite.registry import get_case
from benchmarks.suite.runs import METRICS_FILE, PRED_FILE, RECORD_FILE
from benchmarks.suite.runs import cpu_model as _cpu_model
from benchmarks.suite.suites import RunSpec, Suite
from groundtruth import store

ID_COLUMNS = ["run", "case", "model", "preset", "integrator", "grad_mode", "seed"]

CSV_HEADERS = {
    "metrics": (
        "metrics.csv: tidy position errors of every run on the test split.",
        "rmse (m): for one trajectory, metric=rmse_at_step: sqrt(mean over ALL nodes of "
        "|x_pred - x_true|^2) at saved frame `step` (time `time`, s; frame 0 is the initial "
        "state); metric=full_rollout_rmse: the same mean over nodes and frames 1..T-1 (step = "
        "T-1, the horizon). Clamped nodes are included.", H.CSV_NOTE),
    "rmse_at_step": (
        "rmse_at_step.csv: the paper's table (Tables 1 and 2 of MeshODENet).",
        "rmse_mean / rmse_std (m): mean and population std over the test trajectories of the "
        "per-trajectory RMSE at `step` (sqrt of the mean over all nodes of the squared "
        "Euclidean position error); rmse_coord_mean / rmse_coord_std (m): the same in the "
        "paper's convention, per coordinate (sqrt of the mean over nodes and the 3 coordinates, "
        "i.e. the per-trajectory RMSE / sqrt(3)), the one to set beside the paper's Tables 1 "
        "and 2; increase_vs_meshodenet_pct: 100 (mean / MeshODENet's mean - 1) for the same "
        "case, integrator-free keys and step. A step at which any test trajectory's rollout "
        "diverged (its RMSE NaN in metrics.csv) has NaN mean and std (n_trajectories counts "
        "it)."),
    "tolerance": (
        "tolerance.csv: relative tolerances of `meshbench run --compare-with` / `meshbench "
        "compare --tolerance`, from the spread of this suite's seeds (meshbench tolerance).",
        "rtol = max(floor, exp(factor * sqrt(2) * sigma_pooled) - 1); sigma_log = sample std "
        "over the n_seeds seeds of ln(`column`) at the row's step, seed_mean their mean (m); "
        "sigma_pooled = root mean square of sigma_log over the steps of the run key. See "
        "docs/SUITE.md."),
    "curves": (
        "curves.csv: learning curves (meshbench curves): the position error of every budget "
        "checkpoint (the best-so-far model on validation once the run had spent budget_s CPU "
        "seconds; cpu_s: the CPU time spent when it was taken) on the run's validation split "
        "(split=val) and the test split (split=test).",
        "rmse (m): mean over the split's trajectories of the per-trajectory RMSE at saved frame "
        "`step` (the case's table steps), or over frames 1..T-1 (the whole rollout) for step = "
        "-1. curves_checkpoints.json holds the SHA-256 of each checkpoint evaluated (a rerun "
        "evaluates only new or changed ones). runs/RUN_ID/ holds each run's provenance: its "
        "config.json, budgets.csv (CPU and wall time, epoch, load average at each budget), "
        "history.csv, sessions.json and record.json once written, and evaluation.json (git "
        "commit, library versions and machine of the evaluation). See docs/SUITE.md, "
        "\"Learning curves\"."),
    "runs": (
        "runs.csv: one row per training run (train_wall_time_s sums every session of the run; "
        "peak_rss_mb is the peak resident memory of the run's own process (VmHWM); "
        "cpu_capability and kernel_env: the SIMD code paths torch, MKL, oneDNN and OpenBLAS "
        "were pinned to, see docs/SUITE.md; host: the machine that ran the run, or found it "
        "finished and reused it).",),
}


#: The sidecar next to the CSVs of a results directory: what each file and column means.
README_FILE = "README.md"
README_INTRO = (
    "The CSV files here are plain (no comment lines): `pandas.read_csv(path)` and spreadsheets "
    "load them as they are. This file describes them; it is rewritten by `meshbench run` and "
    "`meshbench tolerance`. RMSE is defined once, in `meshodenet/metrics.py`: for one "
    "trajectory at saved frame k, the root of the mean over all nodes of the squared Euclidean "
    "position error, in metres (clamped nodes included). See docs/SUITE.md.")


def write_readme(directory: Path) -> Path:
    """Write ``directory/README.md`` describing every known CSV present in ``directory``."""
    directory = Path(directory)
    lines = [f"# {directory.name}: results files", "", README_INTRO, ""]
    for kind, text in CSV_HEADERS.items():
        if (directory / f"{kind}.csv").exists():
            lines += [f"## `{kind}.csv`", ""]
            for k, para in enumerate(text):
                para = para.split(": ", 1)[-1] if k == 0 else para
                lines += [para[:1].upper() + para[1:], ""]
    path = directory / README_FILE
    body = "\n".join(lines).rstrip() + "\n"
    store.atomic_write(path, lambda f: f.write(body), mode="w")
    return path


def write_csv(path: Path, df: pd.DataFrame, kind: str) -> None:
    """A plain CSV (no comment lines); its description goes to the directory's README.md
    (``write_readme``)."""
    text = df.to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")
    write_readme(Path(path).parent)


def strip_comments(path: Path) -> list[str]:
    """Remove the ``#`` comment lines of an old-style CSV in place (atomically); returns them
    (for the sidecar). The data lines are kept byte for byte."""
    path = Path(path)
    lines = path.read_text().splitlines(keepends=True)
    comments = [ln[1:].strip() for ln in lines if ln.startswith("#")]
    if comments:
        data = "".join(ln for ln in lines if not ln.startswith("#"))
        store.atomic_write(path, lambda f: f.write(data), mode="w")
    return comments


def _log(msg: str) -> None:
    print(f"[meshbench run] {msg}", file=sys.stderr, flush=True)


#: The ``integrator`` / ``grad_mode`` columns of a model that has neither a configurable nor a
#: fixed scheme: it steps itself autoregressively and trains on single transitions.
NO_INTEGRATOR = "autoregressive"
NO_GRAD_MODE = "one_step"


def check_runs(runs) -> None:
    """Fail before any work on an unknown case or model id, or on an ``integrator`` /
    ``grad_mode`` given to a model whose configuration has no such field."""
    import dataclasses

    from benchmarks.suite.runs import get_model_spec

    for r in runs:
        get_case(r.case)
        config_cls = get_model_spec(r.model).config_cls
        fields = {f.name for f in dataclasses.fields(config_cls)}
        for name in ("integrator", "grad_mode"):
            if getattr(r, name) and name not in fields:
                raise ValueError(f"run {r.run_id}: {name}={getattr(r, name)!r} but model "
                                 f"{r.model!r} has no {name} ({config_cls.__name__} has no such "
                                 "field); drop it from the RunSpec")


# --- one run (executes in a worker process) -------------------------------------------------
def _integrator_ids(config: dict) -> tuple[str, str]:
    """The run's ``integrator`` / ``grad_mode`` columns: its config's, else its model class's
    ``integrator_id`` / ``grad_mode_id`` (a model with a fixed scheme), else ``NO_INTEGRATOR``
    / ``NO_GRAD_MODE``."""
    from benchmarks.suite.runs import get_model_spec

    mc = config["model_config"]
    cls = get_model_spec(config["model"]).model_cls
    return (mc.get("integrator", getattr(cls, "integrator_id", NO_INTEGRATOR)),
            mc.get("grad_mode", getattr(cls, "grad_mode_id", NO_GRAD_MODE)))


def execute_run(spec: RunSpec, run_dir: str, data_dir: str | None, threads: int,
                plugin_files: tuple, progress: bool, device: str = "auto",
                horizon: bool = True) -> dict:
    """Train (or resume, or reuse) ``spec`` in ``run_dir``, roll it out on the test split and
    score it, and with ``horizon`` (``Suite.horizon``) add its long-horizon rows. Returns the
    run's record (also written to ``run_dir/record.json``).

    Holds ``run_dir/.lock`` (``procs.DirLock``) meanwhile; when another live process holds
    it (a second ``meshbench run`` on the same runs directory), waits for it and then reuses
    what it wrote. The kernel releases the lock of a process that died."""
    import torch

    from benchmarks.suite import plugins

    plugins.load_all(plugin_files)
    torch.set_num_threads(threads)
    run_dir = Path(run_dir)
    lock = procs.DirLock(run_dir)
    lock.acquire(wait=True, on_wait=lambda pid: _log(
        f"{spec.run_id}: process {pid or '?'} is working on this run; waiting for it"))
    try:
        rec = _execute(spec, run_dir, data_dir, progress, device, horizon)
    finally:  # left by a process killed mid-write, or by an interrupt that landed between
        procs.remove_partial_writes(run_dir)  # a write's mkstemp and its try
        lock.release()
    # where it ran (or was found finished): runs.csv only, not record.json, not the config
    return {**rec, "host": socket.gethostname()}


def _execute(spec: RunSpec, run_dir: Path, data_dir, progress: bool, device: str,
             horizon: bool = True) -> dict:
    import torch

    from benchmarks.suite.runs import (
        decide_run,
        resolve_run,
        rollout_arrays,
        train_resolved,
        trainable,
    )

    overrides = spec.all_overrides()
    resolved = resolve_run(spec.case, spec.model, spec.preset, data_dir=data_dir,
                           overrides=overrides)
    config = resolved["config"]
    decision = decide_run(run_dir, config, finished=(RECORD_FILE, METRICS_FILE),
                          ids={"run": spec.run_id, **{k: getattr(spec, k) for k in
                                                      ("case", "model", "preset", "seed")}})
    if decision.action == "reuse":  # a run finished before the horizon rows gains them now
        if horizon:
            _add_horizon(spec, run_dir, data_dir, device)
        return {**decision.stored, "reused": True}
    # every input is checked before the first epoch: a corrupt test split fails now
    true = store.load_split(get_case(spec.case), "test", data_dir)
    resume = decision.action == "resume"
    if decision.action == "retrain":
        _log(f"{spec.run_id}: {decision.why}; retraining")
        for p in run_dir.iterdir():
            if p.name != ".lock":
                shutil.rmtree(p) if p.is_dir() else p.unlink()
    rec_path = run_dir / RECORD_FILE
    rec_path.unlink(missing_ok=True)
    t0 = time.time()
    n_epochs = config["train"]["epochs"]

    def log_epoch(epoch, row):  # one line per epoch when the bars are off (--jobs > 1)
        val = row["val_rmse"]
        val = "not validated" if val != val else f"validation RMSE {val:.4g} m"  # NaN: skipped
        _log(f"{spec.run_id}: epoch {epoch}/{n_epochs}, loss {row['train_loss']:.4g}, {val}, "
             f"{row['epoch_time_s']:.0f} s")

    summary = train_resolved(resolved, run_dir, decision, data_dir=data_dir, device=device,
                             progress=progress, evaluate=False,
                             on_epoch_end=None if progress else log_epoch)
    sessions = json.loads((run_dir / "sessions.json").read_text())
    pred, m = rollout_arrays(run_dir, "test", data_dir, "best", device, arrays=true)
    store.save_npz(run_dir / PRED_FILE, pred)
    integ, grad = _integrator_ids(config)
    ids = {"run": spec.run_id, "case": spec.case, "model": spec.model, "preset": spec.preset,
           "integrator": integ, "grad_mode": grad, "seed": spec.seed}
    df = per_run_metrics(pred["pos"], true["pos"], true["t"], ids)
    text = df.to_csv(index=False, float_format="%.9g", lineterminator="\n")
    store.atomic_write(run_dir / METRICS_FILE, lambda f: f.write(text), mode="w")
    peak_mb = procs.peak_rss_mb()
    tc, mc = config["train"], config["model_config"]
    rec = {
        **ids, "config": config, "reused": False,
        "hidden": mc.get("hidden"), "layers": mc.get("layers"), "epochs": tc["epochs"],
        "best_epoch": summary["best_epoch"], "lr": tc["lr"], "batch_size": tc["batch_size"],
        "max_batches": tc["max_batches"], "n_parameters": _n_params(run_dir),
        "best_val_rmse_m": summary["best_val_rmse_m"],
        "test_rmse_m": m["rmse_m"], "test_no_motion_rmse_m": m["no_motion_rmse_m"],
        "train_wall_time_s": round(sum(s.get("wall_time_s", 0.0) for s in sessions), 2),
        "rollout_wall_time_s": m["rollout_wall_time_s"],
        "run_wall_time_s": round(time.time() - t0, 2), "resumed": resume,
        "peak_rss_mb": round(peak_mb, 1), "device": sessions[-1]["device"],
        "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "machine": platform.machine(), "cpu_model": _cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "kernel_env": " ".join(f"{k}={os.environ[k]}" for k in procs.REPRO_ENV
                               if k in os.environ) or "none", "git_sha": store.git_sha(),
        "versions": store.library_versions(),
        "timestamp": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }
    if not trainable(spec.model):  # the solver row: no epochs, no training time
        from benchmarks.suite.solver_row import UNTRAINED_RECORD

        rec.update(UNTRAINED_RECORD)
    store.save_json(rec_path, rec)
    # after the record: should it fail, the run is finished and its reuse adds the rows
    if horizon:
        _add_horizon(spec, run_dir, data_dir, device, true)
    return rec


def _add_horizon(spec: RunSpec, run_dir: Path, data_dir, device: str, arrays=None) -> None:
    """Append the run's long-horizon rows to its ``METRICS_FILE`` (``horizon.add_to_run``); a
    solver reference that cannot be computed is logged, and the run kept without the rows."""
    from groundtruth.implicit import ConvergenceError

    log = lambda msg: _log(f"{spec.run_id}: long horizon: {msg}")  # noqa: E731
    try:
        H.add_to_run(run_dir, run_dir / METRICS_FILE, data_dir, device, arrays, log)
    except (H.HorizonError, ConvergenceError) as e:  # the run itself is fine: keep it
        log(f"not computed ({type(e).__name__}: {e}); the next `meshbench run` retries")


def _n_params(run_dir: Path) -> int:
    from meshodenet.training.train import load_checkpoint

    ck = load_checkpoint(run_dir / "best.pt")
    return int(sum(v.numel() for v in ck["model"].values()))


# --- the suite ------------------------------------------------------------------------------
def run_suite(suite: Suite, *, results_dir="results", runs_dir="runs", data_dir=None,
              seeds: int | None = None, only: str | None = None, jobs: int = 1,
              threads: int = 1, plugin_files=(), progress: bool = True, device: str = "auto",
              figures: bool = True, executor: str = "local", scheduler: str | None = None,
              costs: str | Path | None = None) -> dict:
    """Run ``suite`` and write ``results_dir/SUITE/``; returns paths and the records. A suite
    with ``resolutions`` writes its runs' rollouts on finer meshes instead,
    ``results_dir/SUITE/transfer/`` (``benchmarks.suite.transfer``).

    ``costs``: a ``runs.csv`` of an earlier run of the suite (``--compare-with``'s baseline):
    runs start longest recorded training first (``longest_first``); the results' order is
    the suite's whatever the order of execution.

    ``executor``: ``"local"`` (``jobs`` spawned processes on this machine) or ``"dask"``
    (``benchmarks.suite.cluster``: one dask task per run, on the cluster of ``scheduler``, or on a
    new ``LocalCluster`` of ``jobs`` worker processes when ``scheduler`` is None)."""
    if executor not in ("local", "dask"):
        raise ValueError(f"--executor must be 'local' or 'dask', got {executor!r}")
    if scheduler is not None and executor != "dask":
        raise ValueError("--scheduler needs --executor dask")
    from benchmarks.suite.generate import generate

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"--jobs must be an int >= 1, got {jobs!r}")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"--threads must be an int >= 1, got {threads!r}")
    runs = suite.runs(seeds, only)
    check_runs(runs)
    out = Path(results_dir) / suite.name
    runs_dir = Path(runs_dir)
    t0 = time.time()
    _log(f"suite {suite.name!r}: {len(runs)} run(s): {', '.join(r.run_id for r in runs)}")
    for case_id in dict.fromkeys(r.case for r in runs):
        # on a cluster the data's trajectories are dask tasks too (the workers share data_dir)
        cluster = {"executor": "dask", "scheduler": scheduler, "workers": jobs} \
            if executor == "dask" else {}
        rep = generate(get_case(case_id), data_dir, progress=progress, on_wait=lambda pid, c=case_id: _log(
            f"data {c}: process {pid or '?'} is generating it; waiting for it"), **cluster)
        _log(f"data {case_id}: " + ("up to date" if rep.reused else
                                    f"generated in {rep.wall_time_s:.0f} s"))

    records: dict = {}
    failures: dict = {}
    procs.apply_repro_env(device)  # inherited by the spawned workers (see procs.REPRO_ENV)
    by_id = {r.run_id: r for r in runs}
    if executor == "dask":  # workers may start elsewhere: absolute paths on the shared FS
        runs_dir = runs_dir.resolve()
        data_dir = store.data_dir(data_dir).resolve()
        plugin_files = tuple(str(Path(p).resolve()) for p in plugin_files)
    order = procs.longest_first(list(by_id), costs)
    if order != list(by_id):
        _log("start order (longest recorded training first): " + ", ".join(order))
    tasks = {r.run_id: (execute_run, (r, str(runs_dir / r.run_id),
                                      None if data_dir is None else str(data_dir), threads,
                                      tuple(str(p) for p in plugin_files),
                                      progress and jobs == 1 and executor == "local", device,
                                      suite.horizon))
             for r in (by_id[k] for k in order)}
    done = []

    def on_result(run_id, kind, value):
        done.append(run_id)
        i = len(done)
        if kind == "ok":
            records[run_id] = rec = value
            how = ("reused" if rec.get("reused") else f"trained in {rec['train_wall_time_s']:.0f} s"
                   if _trainable(rec["model"]) else "recorded (nothing to train)")
            _log(f"[{i}/{len(runs)}] {run_id}: {how}; test RMSE {rec['test_rmse_m']:.4g} m "
                 f"(no motion {rec['test_no_motion_rmse_m']:.4g} m)")
            return
        if kind == "died":
            why = f"exit code {value}" if isinstance(value, int) else f"{value}"
            msg = (f"its process died ({why}: killed, or out of memory); "
                   "its finished epochs are kept")
        elif kind == "interrupted":
            msg = "its process was interrupted"
        else:
            name, text, expected = value
            if not expected:  # a bug, not a user error: say so loudly
                _log(f"{run_id}: unexpected {name}: {text}")
            msg = f"{name}: {text}"
        failures[run_id] = msg
        _log(f"[{i}/{len(runs)}] {by_id[run_id].run_id}: FAILED: {msg}")

    try:
        if executor == "dask":
            from benchmarks.suite.cluster import run_tasks_dask

            run_tasks_dask(tasks, on_result, scheduler, min(jobs, len(runs)))
        else:
            procs.run_tasks(tasks, min(jobs, len(runs)), on_result,
                            after_stop=lambda run_id: procs.sweep_after_stop(runs_dir / run_id))
    except KeyboardInterrupt:
        raise SuiteInterrupted(suite.name, sorted(records), runs_dir) from None
    if failures:
        raise SuiteError(f"{len(failures)} run(s) of suite {suite.name!r} failed (finished "
                         "runs are kept; fix the cause and rerun the same command to resume): "
                         + "; ".join(f"{k}: {v}" for k, v in failures.items()))
    ordered = [records[r.run_id] for r in runs]
    with procs.DirLock(out.parent, f".{suite.name}.lock").acquire(wait=True):
        if suite.resolutions:  # the runs on finer meshes: RESULTS/SUITE/transfer/
            from benchmarks.suite.transfer import run_transfer

            try:
                paths = run_transfer(out, ordered, runs_dir, suite, data_dir=data_dir,
                                     jobs=jobs, threads=threads, plugin_files=plugin_files,
                                     device=device, figures=figures, progress=progress)
            except KeyboardInterrupt:
                raise SuiteInterrupted(suite.name, sorted(records), runs_dir) from None
        else:
            paths = write_results(out, ordered, runs_dir, suite, figures=figures,
                                  data_dir=data_dir)
    _log(f"suite {suite.name!r} done in {time.time() - t0:.0f} s; results in {out}")
    return {"results": out, "records": ordered, "paths": paths}


class SuiteError(ValueError):
    """A suite could not finish (runs failed, a worker died); finished runs are kept."""


class SuiteInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) during ``run_suite``: the workers were stopped."""

    def __init__(self, suite: str, finished: list, runs_dir: Path):
        super().__init__(f"suite {suite!r}: {len(finished)} finished run(s) kept in {runs_dir}; "
                         "interrupted runs keep their last finished epoch (last.pt)")
        self.suite, self.finished, self.runs_dir = suite, finished, runs_dir


def runs_table(records: list) -> pd.DataFrame:
    rows = []
    for rec in records:
        row = {k: v for k, v in rec.items() if k not in ("config", "versions", "reused")}
        row["overrides"] = " ".join(rec["config"]["overrides"])
        row["case_hash"] = rec["config"]["case_hash"][:16]
        for lib, ver in sorted(rec.get("versions", {}).items()):
            row[f"version_{lib}"] = ver
        rows.append(row)
    return pd.DataFrame(rows)


def _run_metrics(runs_dir: Path, rec: dict) -> pd.DataFrame:
    """A run's ``test_metrics.csv``; its ids name figure files, so they must be the run's."""
    path = runs_dir / rec["run"] / METRICS_FILE
    df = pd.read_csv(path)
    for col in ("run", "case"):
        if col not in df or set(df[col].astype(str)) != {rec[col]}:
            raise ValueError(f"{path}: column {col!r} is not {rec[col]!r} throughout; delete "
                             f"{path.parent} and rerun to retrain it")
    return df


def write_results(out: Path, records: list, runs_dir: Path, suite: Suite, *,
                  figures: bool = True, data_dir=None) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    metrics = pd.concat([_run_metrics(runs_dir, r) for r in records], ignore_index=True)
    paths = {"runs": out / "runs.csv", "metrics": out / "metrics.csv"}
    write_csv(paths["runs"], runs_table(records), "runs")
    write_csv(paths["metrics"], metrics, "metrics")
    steps, tests, more = _write_tables(out, metrics, records, suite, data_dir)
    paths.update(more)
    if figures:
        from benchmarks.suite import animate as A
        from benchmarks.suite import figures as F

        paths["figures"] = (F.suite_figures(out / "figures", metrics, records, runs_dir,
                                            steps, tests)
                            + A.suite_animations(out / "figures", records, runs_dir, tests))
    return paths


def _write_tables(out: Path, metrics: pd.DataFrame, records: list, suite: Suite, data_dir):
    """``rmse_at_step.csv`` and ``.md`` from the tidy metrics; returns the table steps per
    case, the cases' test splits and the paths written."""
    at_step = metrics[metrics["metric"] == "rmse_at_step"]  # not the horizon's later steps
    steps = {c: M.table_steps(c, int(at_step.loc[at_step["case"] == c, "step"].max()) + 1)
             for c in metrics["case"].unique()}
    table = M.rmse_at_step_table(at_step.drop(columns=["metric", "run"]), steps)
    paths = {"rmse_at_step": out / "rmse_at_step.csv", "markdown": out / "rmse_at_step.md"}
    write_csv(paths["rmse_at_step"], table, "rmse_at_step")
    tests = {c: store.load_split(get_case(c), "test", data_dir) for c in metrics["case"].unique()}
    baseline = {}  # the trivial reference, shown in the markdown only
    for c, arrays in tests.items():
        true = arrays["pos"]
        baseline[c] = (M.rmse_per_step(M.no_motion(true), true),
                       M.full_rollout_rmse(M.no_motion(true), true))
    md = render_markdown(table, metrics, records, suite, baseline)
    store.atomic_write(paths["markdown"], lambda f: f.write(md), mode="w")
    return steps, tests, paths


def rewrite_tables(results_dir, suite: Suite, *, data_dir=None, figures: bool = True) -> dict:
    """Rewrite ``RESULTS/SUITE/rmse_at_step.csv``, ``.md`` and the RMSE-vs-step figures from
    the committed ``metrics.csv`` and ``runs.csv`` alone (no run directory, no training): a
    results directory brought up to a newer meshbench's tables. ``metrics.csv`` and
    ``runs.csv`` are not touched; the snapshots, loss curves and animations, which need the
    runs' stored rollouts, stay as they are."""
    out = Path(results_dir) / suite.name
    files = {k: out / f"{k}.csv" for k in ("metrics", "runs")}
    for f in files.values():
        if not f.exists():
            raise FileNotFoundError(f"{f}: no such file; --tables-only rewrites the tables of "
                                    f"a results directory written by `meshbench run`")
    metrics = pd.read_csv(files["metrics"], comment="#")
    records = []
    for rec in pd.read_csv(files["runs"], comment="#").to_dict("records"):
        b = rec.get("best_epoch")
        if isinstance(b, float) and b == b and b.is_integer():
            rec["best_epoch"] = int(b)
        records.append(rec)
    steps, tests, paths = _write_tables(out, metrics, records, suite, data_dir)
    if figures:
        from benchmarks.suite import figures as F

        paths["figures"] = [F.rmse_vs_step(metrics, c, out / "figures" / f"rmse_vs_step_{c}.png")
                            for c in sorted(metrics["case"].unique())]
    return paths


def _fmt(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.3g}"


def render_markdown(table: pd.DataFrame, metrics: pd.DataFrame, records: list,
                    suite: Suite, baseline: dict | None = None) -> str:
    """Tables in the paper's layout: per case, one row per model (and integrator, seed), one
    column per step with ``mean ± std`` (mm), then the increase over MeshODENet (%).
    ``baseline[case] = (per-step RMSE (B, T), full-rollout RMSE (B,))`` of the no-motion
    prediction adds a reference row."""
    lines = [f"# Suite `{suite.name}`: position RMSE on the test split", "",
             suite.description + ".", "",
             "RMSE at step k: root of the mean over all nodes of the squared position error "
             "at saved frame k, per test trajectory; mean ± std over test trajectories, in mm. "
             "Generated by `meshbench run`; see `rmse_at_step.csv`. \"diverged\": at least one "
             "test trajectory's rollout had diverged (NaN) by that step; it is never left out "
             "of a mean.", ""]
    keys = [c for c in table.columns if c not in ("case", "step", "rmse_mean", "rmse_std",
                                                   "rmse_coord_mean", "rmse_coord_std",
                                                   "n_trajectories")
            and not c.startswith("increase_vs_")]
    inc = [c for c in table.columns if c.startswith("increase_vs_")][0]
    full = metrics[metrics["metric"] == "full_rollout_rmse"]
    for case, dfc in table.groupby("case", sort=True):
        steps = sorted(dfc["step"].unique())
        n = int(dfc["n_trajectories"].max())
        lines += [f"## {case} ({n} test trajectories)", "",
                  "| " + " | ".join(keys) + " | " + " | ".join(f"step {s}" for s in steps)
                  + " | full rollout |",
                  "|" + "---|" * (len(keys) + len(steps) + 1)]
        for kv, dfm in _row_groups(dfc, keys):
            d = dfm.set_index("step")
            cells = [f"{1e3 * d.loc[s, 'rmse_mean']:.3g} ± {1e3 * d.loc[s, 'rmse_std']:.2g}"
                     if np.isfinite(d.loc[s, "rmse_mean"]) else "diverged" for s in steps]
            sel = full[(full["case"] == case)]
            for k, v in zip(keys, kv):
                sel = sel[sel[k] == v]
            whole = sel["rmse"].mean(skipna=False)
            cells.append("" if not len(sel) else f"{1e3 * whole:.3g}" if np.isfinite(whole)
                         else "diverged")
            lines.append("| " + " | ".join(str(v) for v in kv) + " | " + " | ".join(cells) + " |")
        if baseline and case in baseline:
            r, f = baseline[case]
            cells = [f"{1e3 * r[:, s].mean():.3g} ± {1e3 * r[:, s].std():.2g}" for s in steps]
            lines.append("| *no motion (x = x0)* |" + " |" * (len(keys) - 1) + " "
                         + " | ".join(cells) + f" | {1e3 * f.mean():.3g} |")
        lines += ["", f"Increase over MeshODENet (%), `{inc}`:", "",
                  "| " + " | ".join(keys) + " | " + " | ".join(f"step {s}" for s in steps) + " |",
                  "|" + "---|" * (len(keys) + len(steps))]
        for kv, dfm in _row_groups(dfc, keys):
            d = dfm.set_index("step")
            lines.append("| " + " | ".join(str(v) for v in kv) + " | "
                         + " | ".join(_fmt(d.loc[s, inc]) for s in steps) + " |")
        lines.append("")
        lines += _paper_lines(case, dfc, keys, steps)
    lines += H.markdown_lines(metrics, keys)
    n_test = table.groupby("case")["n_trajectories"].max()
    lines += ["## Runs", "", "Rollout: wall time of the test rollout per test trajectory (the "
              "learned models roll out up to 16 trajectories at once, the solver one by one).",
              "", "| run | train wall (s) | peak memory (MB) | threads | best epoch | "
              "rollout (s per trajectory) | test RMSE (mm) | no-motion RMSE (mm) |",
              "|---|---|---|---|---|---|---|---|"]
    for r in records:
        trained = _trainable(r["model"])
        lines.append(f"| {r['run']} | "
                     + (f"{r['train_wall_time_s']:.0f}" if trained else "n/a (not trained)")
                     + f" | {r['peak_rss_mb']:.0f} | {r['threads']} | "
                     + (f"{r['best_epoch']}" if trained else "n/a")
                     + f" | {r['rollout_wall_time_s'] / n_test.get(r['case'], 1):.3g} | "
                     f"{1e3 * r['test_rmse_m']:.3g} | {1e3 * r['test_no_motion_rmse_m']:.3g} |")
    return "\n".join(lines) + "\n"


def _paper_lines(case: str, dfc: pd.DataFrame, keys: list, steps: list) -> list:
    """The case's rows in the paper's convention (per coordinate, `rmse_coord_mean`) under the
    paper's own rows, in the paper's unit (1e-4 m); nothing for a case the paper has no table
    of or when the table lacks the column."""
    paper = M.PAPER_TABLES.get(case)
    if not paper or "rmse_coord_mean" not in dfc:
        return []
    lines = ["In the paper's convention (per coordinate: root of the mean over nodes and x, y, "
             "z; `rmse_coord_mean`), mean over test trajectories, 1e-4 m, beside the paper's "
             "table:", "",
             "| " + " | ".join(keys) + " | " + " | ".join(f"step {s}" for s in steps) + " |",
             "|" + "---|" * (len(keys) + len(steps))]
    for model, row in sorted(paper.items()):
        lines.append(f"| *{model}, the paper* |" + " |" * (len(keys) - 1) + " "
                     + " | ".join(f"{1e4 * row[s]:.3g}" if s in row else "" for s in steps)
                     + " |")
    for kv, dfm in _row_groups(dfc, keys):
        d = dfm.set_index("step")
        lines.append("| " + " | ".join(str(v) for v in kv) + " | "
                     + " | ".join(_fmt(1e4 * d.loc[s, "rmse_coord_mean"]) for s in steps) + " |")
    return lines + [""]


def _trainable(model: str) -> bool:
    from benchmarks.suite.runs import trainable

    return trainable(model)


def _row_groups(dfc: pd.DataFrame, keys: list) -> list:
    """``(key values, rows)`` of ``dfc`` grouped by ``keys``, sorted, with the models that
    learn nothing (reference rows: the solver) last, beside the no-motion row."""
    groups = [(kv if isinstance(kv, tuple) else (kv,), d)
              for kv, d in dfc.groupby(keys, sort=True)]
    if "model" not in keys:
        return groups
    i = keys.index("model")
    return sorted(groups, key=lambda g: not _trainable(g[0][i]))
