"""Generate the train/test trajectories of a case in parallel, resumably and atomically."""

from __future__ import annotations

import datetime
import multiprocessing
import os
import shutil
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from benchmarks.suite import plugins, procs
from benchmarks.suite.registry import safe_id
from groundtruth import store
from groundtruth.cases import SPLITS


@dataclass
class GenerateReport:
    case_id: str
    case_dir: Path
    reused: bool
    wall_time_s: float
    n_trajectories: int


def _init_worker(parent_pid: int, plugin_files: tuple) -> None:
    from benchmarks.suite import plugins

    procs.worker_init(parent_pid)
    plugins.load_all(plugin_files)


def _simulate_one(case, youngs: float, out: str) -> str:
    """Worker: one trajectory into a partial file (atomic), so an interruption loses nothing."""
    res = case.simulate(youngs)
    store.save_npz(Path(out), {"pos": res["pos"], "vel": res["vel"], "t": res["t"],
                               "youngs": np.array(youngs)})
    return out


def _simulate_task(case_id: str, plugin_files: tuple, youngs: float, out: str) -> str:
    """A cluster task (``benchmarks.suite.cluster.remote_task`` runs it in a fresh process on
    a worker): the case by id, with the client's plugins, one trajectory into ``out``."""
    from benchmarks.suite.registry import get_case

    plugins.load_all(plugin_files)
    return _simulate_one(get_case(case_id), youngs, out)


def _generate_dask(case, todo, partial: Path, results: dict, bar, workers: int,
                   scheduler: str | None) -> None:
    """One dask task per trajectory of ``todo`` (the cluster of ``scheduler``, or a loopback
    ``LocalCluster`` of ``workers`` processes); each writes its partial file on the shared
    filesystem (docs/CLUSTER.md), read back here. A trajectory that failed everywhere is an
    error naming it; the finished ones stay in ``partial`` for the next invocation."""
    from benchmarks.suite.cluster import run_tasks_dask

    files = tuple(str(Path(f).resolve()) for f in plugins.loaded_files())
    tasks = {f"generate-{case.id}-{s}-{i}": (s, i, y) for s, i, y in todo}
    failed = []

    def on_result(key, kind, value):
        s, i, y = tasks[key]
        if kind == "ok":
            results[(s, i)] = _load_partial(partial / f"{s}_{i:04d}.npz", y)
        if kind != "ok" or results[(s, i)] is None:
            results.pop((s, i), None)
            failed.append(f"{s} {i} (Y = {y:g} Pa): {kind}: {value}")
        bar.update(1)

    run_tasks_dask({k: (_simulate_task, (case.id, files, y,
                                         str((partial / f"{s}_{i:04d}.npz").resolve())))
                    for k, (s, i, y) in tasks.items()},
                   on_result, scheduler, min(workers, len(tasks)))
    if failed:
        raise RuntimeError(f"{case.id}: {len(failed)} of {len(tasks)} trajectories failed on "
                           "the cluster (the others are kept for the next run): "
                           + "; ".join(failed[:3]))


def _load_partial(path: Path, youngs: float):
    try:
        with np.load(path, allow_pickle=False) as z:
            if float(z["youngs"]) == youngs:
                return z["pos"], z["vel"], z["t"]
    except (OSError, ValueError, KeyError, EOFError):
        pass
    return None


class GenerateInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM) during ``generate``; ``kept`` finished trajectories are cached."""

    def __init__(self, case_id: str, kept: int, total: int, partial: Path):
        super().__init__(f"{case_id}: {kept} of {total} trajectories are kept in {partial}")
        self.case_id, self.kept, self.total, self.partial = case_id, kept, total, partial


def _current_splits(case_dir: Path, h: str) -> dict:
    """The ``meta.json`` entries of the splits stored in ``case_dir`` and current for case
    hash ``h`` (``store.is_current``); none when ``meta.json`` is missing, unreadable (it is
    written last, so regenerating repairs it) or of another case."""
    try:
        if not store.is_current(case_dir, h):
            return {}
        return dict(store.read_meta(case_dir)["splits"])
    except store.StoreError:
        return {}


def _current(case_dir: Path, h: str, splits=SPLITS) -> bool:
    """Every split of ``splits`` is stored and current for case hash ``h``."""
    return set(splits) <= set(_current_splits(case_dir, h))


def check_splits(splits) -> tuple:
    """``splits`` in the order of ``SPLITS``; ``ValueError`` naming an unknown one."""
    bad = [s for s in splits if s not in SPLITS]
    if bad or not splits:
        raise ValueError(f"--split {bad[0] if bad else ''!r} is not a split; valid: "
                         + ", ".join(SPLITS))
    return tuple(s for s in SPLITS if s in splits)


def generate(case, root=None, workers: int | None = None, force: bool = False,
             progress: bool = True, on_wait=None, splits=SPLITS, executor: str = "local",
             scheduler: str | None = None) -> GenerateReport:
    """Write ``ROOT/CASE/{train,test}.npz`` and ``meta.json``; reuse them if up to date.

    ``splits``: only these (e.g. ``("test",)``: a model trained on another case evaluated on
    this one); splits stored and current are kept as they are (``force`` remakes those asked
    for) and stay in ``meta.json``, whose ``splits`` lists the splits present. A split's
    trajectories do not depend on which others are made (its moduli and seed are its own).

    Holds ``ROOT/.CASE.lock`` meanwhile: a second ``generate`` of the same case (another
    ``meshbench run`` on the same data) waits for the first (``on_wait(pid)`` is told once)
    and then reuses its files.
    """
    splits = check_splits(splits)
    root = store.data_dir(root)
    case_dir = root / safe_id(case.id, "case id")
    if not force and _current(case_dir, case.hash(), splits):
        return GenerateReport(case.id, case_dir, True, 0.0, 0)
    with procs.DirLock(root, f".{case.id}.lock").acquire(wait=True, on_wait=on_wait):
        return _generate(case, root, workers, force, progress, splits, executor, scheduler)


def _generate(case, root: Path, workers: int | None, force: bool,
              progress: bool, splits=SPLITS, executor: str = "local",
              scheduler: str | None = None) -> GenerateReport:
    """Trajectories run in ``workers`` processes (default: all cores; spawned, with the
    pinned kernel settings of ``procs.REPRO_ENV``, which decide the last bits of the solver's
    results; ``meshbench`` pins them in its own process too, so ``workers=1`` runs in-process
    with the same kernels). Each finished trajectory is cached under ``.partial/HASH/`` so an interrupted
    run resumes; ``meta.json`` is written last and removed first, so a set without it is never
    taken as complete. Ctrl-C stops the workers at once (``GenerateInterrupted``)."""
    case_dir = root / case.id
    h = case.hash()
    t0 = time.perf_counter()
    current = _current_splits(case_dir, h)
    make = tuple(s for s in SPLITS if s in splits and (force or s not in current))
    if not make:
        return GenerateReport(case.id, case_dir, True, time.perf_counter() - t0, 0)
    kept = {s: v for s, v in current.items() if s not in make}  # stored and current: kept
    workers = max(1, int(workers or os.cpu_count() or 1))
    partial = case_dir / ".partial" / h[:16]
    partial.mkdir(parents=True, exist_ok=True)
    for d in (case_dir, partial):  # left by a process killed in the middle of a write
        procs.remove_partial_writes(d)
    (case_dir / "meta.json").unlink(missing_ok=True)

    moduli = {split: case.sample_youngs(split) for split in make}
    jobs = [(s, i, float(y)) for s in make for i, y in enumerate(moduli[s])]
    results: dict = {}
    todo = []
    for s, i, y in jobs:
        cached = _load_partial(partial / f"{s}_{i:04d}.npz", y)
        if cached is not None:
            results[(s, i)] = cached
        else:
            todo.append((s, i, y))
    bar = tqdm(total=len(jobs), initial=len(results), desc=f"generate {case.id}", unit="traj",
               disable=not progress, file=sys.stderr)
    if todo and executor == "dask":
        _generate_dask(case, todo, partial, results, bar, workers, scheduler)
    elif todo and workers == 1:  # in-process: easier to debug and to interrupt
        for s, i, y in todo:
            _simulate_one(case, y, str(partial / f"{s}_{i:04d}.npz"))
            results[(s, i)] = _load_partial(partial / f"{s}_{i:04d}.npz", y)
            bar.update(1)
    elif todo:
        procs.apply_repro_env()
        pool = ProcessPoolExecutor(max_workers=min(workers, len(todo)),
                                   mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_worker,
                                   initargs=(os.getpid(), tuple(plugins.loaded_files())))
        try:
            futs = {pool.submit(_simulate_one, case, y, str(partial / f"{s}_{i:04d}.npz")):
                    (s, i, y) for s, i, y in todo}
            for fut in as_completed(futs):
                s, i, y = futs[fut]
                fut.result()
                results[(s, i)] = _load_partial(partial / f"{s}_{i:04d}.npz", y)
                bar.update(1)
        except KeyboardInterrupt:
            procs.stop_pool(pool)
            procs.remove_partial_writes(partial)  # we hold the case's lock; workers are gone
            bar.close()
            kept = sum(_load_partial(partial / f"{s}_{i:04d}.npz", y) is not None
                       for s, i, y in jobs)
            raise GenerateInterrupted(case.id, kept, len(jobs), partial) from None
        except BaseException:
            procs.stop_pool(pool)
            procs.remove_partial_writes(partial)
            raise
        pool.shutdown(wait=True)
    bar.close()

    meta_splits = dict(kept)
    for s in make:
        n = len(moduli[s])
        t = case.t_save()
        pos = np.stack([results[(s, i)][0] for i in range(n)]) if n else \
            np.zeros((0, len(t), case.rest_positions().shape[0], 3))
        vel = np.stack([results[(s, i)][1] for i in range(n)]) if n else np.zeros_like(pos)
        f = case_dir / f"{s}.npz"
        store.save_npz(f, store.trajectory_arrays(case, t, pos, vel, moduli[s], s))
        lo, hi = getattr(case, f"youngs_{s}")
        meta_splits[s] = {"n": n, "seed": getattr(case, f"seed_{s}"), "youngs_range": [lo, hi],
                          "file": f.name, "sha256": store.sha256_file(f), "shape": list(pos.shape)}
    wall = time.perf_counter() - t0
    store.save_json(case_dir / "meta.json", {
        "format_version": store.FORMAT_VERSION, "case_id": case.id, "case_hash": h,
        "case": case.to_dict(), "solver": {"method": "backward Euler + Newton-Raphson",
                                           **case.solver_settings.to_dict()},
        "splits": {s: meta_splits[s] for s in SPLITS if s in meta_splits},
        "versions": store.library_versions(), "git_sha": store.git_sha(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "wall_time_s": round(wall, 3), "workers": workers,
    })
    shutil.rmtree(case_dir / ".partial", ignore_errors=True)
    return GenerateReport(case.id, case_dir, False, wall, len(jobs))
