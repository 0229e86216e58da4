"""``meshbench bench scale``: cost and memory of the ground truth and of every learner against
the number of nodes, on the cases refined to ``CASE@rN`` (docs/SCALE.md).

Per case and resolution r, in one fresh process (one thread, ``--device`` for the learners):

- the ground truth (``groundtruth``): ``--steps`` saved intervals simulated from the case's
  initial state at its reference modulus with its own time step, Newton settings and
  predictor, timed in CPU seconds (``time.process_time``) per internal step, with its Newton
  iterations per step; variant ``auto`` (the default linear solver: the band LU on small
  meshes, the sparse factorization beyond; ``note`` says which backend) and variant ``banded``
  (``dataclasses.replace(system, linear_solver="banded")``) run interleaved, round by round;
  and the linear solve of the first Newton matrix by each (band LU; sparse factorization and
  solve). The banded path is skipped where its band storage (the matrix and LAPACK's LU copy)
  would exceed ``--band-limit-gb``;
- the solver at h (``solver_h``): the same system stepped once per saved interval;
- each learner's rollout per saved interval (``--steps`` intervals from the same state):
  untrained weights (seeded), statistics from the base case's training data (generated data
  when present, else synthetic), moved to the refined mesh by ``TrajectoryModel.on_mesh``
  (docs/SCALE.md, "Learned models on other meshes"), ``--preset`` configuration.

All of these are measured interleaved in ``--rounds`` rounds (a measurement longer than
``REPEAT_BELOW_S`` is not repeated), the best round kept.

Then, per learner (and for MeshODENet per gradient mode: direct, adjoint, checkpoint), one
fresh process per resolution runs one optimizer step of the ``--preset`` training settings on
synthetic trajectories of ``--window`` intervals (MeshODENet and IMEX roll the whole window
out, ``shooting = 0``; MGN and the energy models take their preset's one-step samples): its
time and the process's peak resident memory (``VmHWM``; on CUDA also the peak GPU memory).
Each such process runs under an address-space limit of ``--max-memory-gb``
(``RLIMIT_AS``; on CUDA the GPU memory fraction instead), and starts only when the machine has
that much memory available plus 1 GB; one that fails to allocate is recorded as not fitting
and the learner is not tried on larger meshes.

A measurement predicted (from the last two sizes) to take longer than ``--max-seconds`` is
skipped and recorded so. The rows go to ``--out``/scale.csv (tidy: one row per case, r,
method, variant and quantity; written atomically after each resolution; ``--resume`` keeps
what is there and measures only what is missing), the fitted log-log exponents and the
crossovers to ``fits.csv``, the figure to ``scale.png``. The measuring processes are in
``benchmarks.cost.scaleprocs``, the outputs in ``benchmarks.cost.scalereport``.
"""

from __future__ import annotations

import datetime
import math
import os
import platform
import queue as queue_mod
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.cost.scalecore import (  # noqa: F401 - the command's names
    CASES,
    COLUMNS,
    CROSSOVER_RATIO,
    DEFAULT_CASES,
    DEFAULT_R,
    GRAD_MODES,
    LEARNERS,
    METHODS,
    PROVENANCE,
    REPEAT_BELOW_S,
    _row,
    _timer,
    base_model,
    fit_power,
    mem_available_gb,
    mesh_arrays,
    refined_id,
    synthetic_training,
)


# --- the driver ------------------------------------------------------------------------------
def _drain(proc, q, timeout_s, on_item):
    """Pass ``q``'s items to ``on_item`` until the process says ``done`` or ends; kill it after
    ``timeout_s``. Returns ``"done"``, ``"timeout"`` or ``"died (exit N)"``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            kind, value = q.get(timeout=1.0)
        except queue_mod.Empty:
            if not proc.is_alive():
                try:  # the last items may arrive after the exit
                    while True:
                        kind, value = q.get(timeout=1.0)
                        if kind == "done":
                            return "done"
                        on_item(kind, value)
                except queue_mod.Empty:
                    pass
                return f"died (exit {proc.exitcode})"
            if time.monotonic() > deadline:
                proc.kill()
                proc.join()
                return "timeout"
            continue
        if kind == "done":
            return "done"
        on_item(kind, value)


def _predict(history: list, nodes: int) -> float | None:
    """Seconds predicted at ``nodes`` from ``[(nodes, seconds), ...]`` (the last two sizes'
    exponent, at least 1), or None without history."""
    pts = [(n, s) for n, s in history if s is not None and np.isfinite(s) and s > 0]
    if not pts:
        return None
    n1, s1 = pts[-1]
    p = 1.0
    if len(pts) >= 2:
        n0, s0 = pts[-2]
        if n1 > n0:
            p = max(1.0, math.log(s1 / s0) / math.log(n1 / n0))
    return s1 * (nodes / n1) ** p


def provenance(args, out: Path, device: str) -> dict:
    import scipy
    import torch

    from benchmarks.suite.runner import _cpu_model
    from groundtruth import assembly, store

    return {"git_sha": store.git_sha(exclude=[out]),
            "timestamp": datetime.datetime.now(datetime.timezone.utc)
            .isoformat(timespec="seconds"),
            "machine": platform.machine(), "cpu_model": _cpu_model(),
            "cpu_count": os.cpu_count(), "threads": args.threads, "device": device,
            "linear_backend": assembly.available_backend(), "preset": args.preset,
            "steps": args.steps, "window": args.window,
            "version_python": platform.python_version(), "version_numpy": np.__version__,
            "version_scipy": scipy.__version__, "version_torch": torch.__version__}


def nodes_of(case_id: str, r: int) -> int:
    """Nodes of ``case_id`` at ``r`` from the case's counts, without meshing."""
    from benchmarks.suite.registry import get_case

    c = get_case(refined_id(case_id, r))
    if hasattr(c, "n_nodes"):
        return int(c.n_nodes)
    return len(c.node_type())


def run_scale(args, log=print) -> dict:
    """Measure (module docstring); returns ``{"csv", "fits", "figure"}`` paths."""
    import multiprocessing as mp

    import pandas as pd

    from benchmarks.cost.scaleprocs import timing_child
    from benchmarks.cost.scalereport import fit_table, plot, write_csv, write_table
    from benchmarks.suite.runs import pick_device

    out = Path(args.out)
    csv_path = out / "scale.csv"
    dev = pick_device(args.device)
    prov = provenance(args, out, str(dev))
    old = pd.read_csv(csv_path) if args.resume and csv_path.exists() else None
    rows: list[dict] = []
    if old is not None:
        rows = old[COLUMNS].to_dict("records")
        prov_old = old[[c for c in PROVENANCE if c in old]].to_dict("records")
        for rec, p in zip(rows, prov_old):
            rec["_prov"] = p
    ctx = mp.get_context("spawn")
    cache = Path(tempfile.mkdtemp(prefix="meshbench-scale-"))
    params = {"steps": args.steps, "rounds": args.rounds, "threads": args.threads,
              "device": args.device if dev.type == "cuda" else "cpu", "preset": args.preset,
              "band_limit_gb": args.band_limit_gb, "window": args.window,
              "train_traj": args.train_trajectories, "max_memory_gb": args.max_memory_gb}

    def mine(x, case, r, stage, method=None, variant=None):
        return x["case"] == case and x["r"] == r and x["stage"] == stage and \
            (method is None or x["method"] == method) and \
            (variant is None or x["variant"] == variant)

    def have(case, r, stage, method=None, variant=None):
        """Whether a stage has its result (a resumed run redoes one that was skipped, timed
        out or died: the ground truth's step time, or a probe's step time or no-fit)."""
        for x in rows:
            if not mine(x, case, r, stage, method, variant):
                continue
            if stage == "timing" and (x["method"], x["variant"], x["quantity"]) == (
                    "groundtruth", "auto", "step_cpu_s") and np.isfinite(x["value"]):
                return True
            if stage == "train" and ((x["quantity"] == "train_step_s" and np.isfinite(
                    x["value"])) or (x["quantity"] == "fits_memory_cap" and x["value"] == 0)):
                return True
        return False

    def drop(case, r, stage, method=None, variant=None):
        rows[:] = [x for x in rows if not mine(x, case, r, stage, method, variant)]

    def add(row):
        row["_prov"] = prov
        rows.append(row)

    def save():
        write_csv(csv_path, rows)

    learners = [m for m in args.methods if m in LEARNERS]
    for case in args.cases:
        stopped: dict = {}  # method or (method, variant) -> why it is not tried further
        history: dict = {}  # key -> [(nodes, seconds)]
        for x in rows:  # what a resumed run measured before predicts the next sizes
            if x["case"] == case and x["quantity"] in ("step_cpu_s", "rollout_interval_s",
                                                       "train_step_s"):
                key = x["method"] if x["quantity"] == "rollout_interval_s" else \
                    (x["method"], x["variant"], x["quantity"])
                history.setdefault(key, []).append((x["nodes"], x["value"]))
            if x["case"] == case and x["quantity"] == "fits_memory_cap" and not x["value"] > 0:
                stopped[(x["method"], x["variant"])] = f"did not fit at r = {x['r']}"
        for r in args.r[case]:
            cid = refined_id(case, r)
            n = nodes_of(case, r)
            arrays_path = cache / f"{cid}.npz"
            need_probes = [(m, v) for m in learners
                           for v in (args.grad_modes if m == "meshodenet" else ("default",))
                           if not have(case, r, "train", m, v)] if args.train else []
            if not have(case, r, "timing"):
                drop(case, r, "timing")
                cap, why = _cap(args.max_memory_gb, 0, log)
                if cap is None:
                    add(_row(case, r, n, 0, "timing", "groundtruth", "auto", "step_cpu_s", None,
                             "s", why))
                    log(f"[scale] {cid}: timing {why}")
                    save()
                    continue
                skip = {}
                for m in args.methods:
                    if m == "groundtruth":
                        continue
                    pred = _predict(history.get(m, []), n)
                    if m in stopped:
                        skip[m] = stopped[m]
                    elif pred is not None and pred * args.steps > args.max_seconds:
                        skip[m] = (f"skipped: predicted {pred:.3g} s per interval x "
                                   f"{args.steps} > --max-seconds {args.max_seconds:g}")
                prm = dict(params, train_arrays=str(arrays_path) if need_probes else "",
                           cap_bytes=cap)
                log(f"[scale] {cid} ({n} nodes): timing {', '.join(args.methods)}"
                    + (f"; skipping {', '.join(skip)}" if skip else ""))
                q = ctx.Queue()
                proc = ctx.Process(target=timing_child,
                                   args=(case, r, list(args.methods), skip, prm, q))
                proc.start()
                got = []

                def on_item(kind, value, got=got, cid=cid):
                    if kind == "row":
                        add(value)
                        got.append(value)
                    elif kind == "log":
                        log(f"[scale]   {value}")
                    else:
                        log(f"[scale]   {cid}: timing failed: {value}")
                        got.append(None)
                status = _drain(proc, q, args.stage_timeout, on_item)
                proc.join()
                nodes_e = next(((g["nodes"], g["edges"]) for g in got if g), (n, 0))
                for m, why in skip.items():
                    add(_row(case, r, *nodes_e, "timing", m, args.preset if m in LEARNERS
                             else "backward_euler", "rollout_interval_s", None, "s", why))
                if status != "done":
                    add(_row(case, r, *nodes_e, "timing", "groundtruth", "auto", "step_cpu_s",
                             None, "s", f"timing process {status} (--stage-timeout "
                             f"{args.stage_timeout:g} s)"))
                    log(f"[scale]   {cid}: timing process {status}")
                for g in got:
                    if g and g["quantity"] in ("step_cpu_s", "rollout_interval_s"):
                        key = g["method"] if g["quantity"] == "rollout_interval_s" else \
                            (g["method"], g["variant"], g["quantity"])
                        history.setdefault(key, []).append((g["nodes"], g["value"]))
                        if g["method"] in LEARNERS + ("solver_h",) and not np.isfinite(
                                g["value"]) and g["note"].startswith(("failed", "does not")):
                            stopped[g["method"]] = f"failed at r = {r}"
                save()
            for m, v in need_probes:
                key = (m, v, "train_step_s")
                nodes_e = next(((x["nodes"], x["edges"]) for x in rows
                                if x["case"] == case and x["r"] == r), (n, 0))
                why = stopped.get((m, v))
                pred = _predict(history.get(key, []), n)
                if why is None and pred is not None and pred > args.max_seconds:
                    why = (f"skipped: predicted {pred:.3g} s per training step > --max-seconds "
                           f"{args.max_seconds:g}")
                if why is None and not arrays_path.exists():
                    why = None
                    _prepare(ctx, case, r, arrays_path, params, args.stage_timeout)
                cap = None
                if why is None:
                    cap, why = _cap(args.max_memory_gb, args.memory_wait, log)
                if why is not None:
                    add(_row(case, r, *nodes_e, "train", m, v, "train_step_s", None, "s", why))
                    log(f"[scale] {cid} train {m} [{v}]: {why}")
                    save()
                    continue
                drop(case, r, "train", m, v)
                cap_gb = cap / 1024**3
                capnote = f"cap {cap_gb:.3g} GB" + (
                    "" if cap_gb >= args.max_memory_gb else
                    f" (less than --max-memory-gb {args.max_memory_gb:g}: MemAvailable - 1 GB)")
                res = _probe(ctx, m, v, str(arrays_path), dict(params, cap_bytes=cap),
                             args.stage_timeout)
                if "result" in res:
                    p = res["result"]
                    cfg = ", ".join(f"{k} {val}" for k, val in p["config"].items())
                    note = (f"{p['steps_timed']} step(s) timed, batch {p['batch_size']} of "
                            f"{p['n_samples']} samples, window {args.window}; {cfg}")
                    add(_row(case, r, *nodes_e, "train", m, v, "train_step_s", p["step_s"],
                             "s", note))
                    add(_row(case, r, *nodes_e, "train", m, v, "peak_rss_gb",
                             p["peak_rss_gb"], "GB", f"setup {p['setup_rss_gb']:.2f} GB"))
                    if p.get("cuda_peak_gb") is not None:
                        add(_row(case, r, *nodes_e, "train", m, v, "cuda_peak_gb",
                                 p["cuda_peak_gb"], "GB", p["device"]))
                    fits = p["peak_rss_gb"] <= args.max_memory_gb
                    add(_row(case, r, *nodes_e, "train", m, v, "fits_memory_cap", float(fits),
                             "1", f"--max-memory-gb {args.max_memory_gb:g}; {capnote}"))
                    history.setdefault(key, []).append((n, p["step_s"]))
                    log(f"[scale] {cid} train {m} [{v}]: {p['step_s']:.4g} s/step, peak RSS "
                        f"{p['peak_rss_gb']:.2f} GB")
                    if not fits:
                        stopped[(m, v)] = f"did not fit at r = {r}"
                else:
                    kind, text = next(iter(res.items()))
                    nofit = kind in ("nofit",) or "died" in kind
                    add(_row(case, r, *nodes_e, "train", m, v, "train_step_s", None, "s",
                             f"{kind}: {text}"[:300]))
                    if nofit:
                        full = cap_gb >= args.max_memory_gb
                        add(_row(case, r, *nodes_e, "train", m, v, "fits_memory_cap",
                                 0.0 if full else None, "1", f"{capnote}: {kind}" + (
                                     "" if full else "; inconclusive for the full cap")))
                        stopped[(m, v)] = f"did not fit at r = {r} ({capnote})"
                    else:
                        stopped[(m, v)] = f"{kind} at r = {r}"
                    log(f"[scale] {cid} train {m} [{v}]: {kind}: {text}"[:400])
                save()
            if arrays_path.exists():
                arrays_path.unlink()
    save()
    fits_path = out / "fits.csv"
    fits = fit_table(rows)
    write_table(fits_path, fits)
    fig = out / "scale.png"
    try:
        plot(fig, rows, args.max_memory_gb)
    except Exception as e:  # noqa: BLE001 - the numbers are written; say why there is no figure
        log(f"[scale] no figure: {type(e).__name__}: {e}")
        fig = None
    return {"csv": csv_path, "fits": fits_path, "figure": fig, "rows": rows, "fit_rows": fits}


def _prepare(ctx, case, r, path, params, timeout):
    """The probes' arrays of ``case`` at ``r`` when a resumed run has none (a short process)."""
    from benchmarks.cost.scaleprocs import timing_child

    q = ctx.Queue()
    proc = ctx.Process(target=timing_child, args=(case, r, [], {}, dict(
        params, train_arrays=str(path)), q))
    proc.start()
    _drain(proc, q, timeout, lambda k, v: None)
    proc.join()


#: a process is not started with less memory than this under its cap, GB
MIN_CAP_GB = 2.0


def _cap(cap_gb, wait_s, log) -> tuple:
    """``(cap in bytes, None)`` for a measuring process: ``cap_gb`` once MemAvailable >=
    ``cap_gb`` + 1 GB (waiting up to ``wait_s``), else MemAvailable - 1 GB if that is at
    least ``MIN_CAP_GB`` (a result that fits it fits the full cap; a failure under it is
    recorded as inconclusive); ``(None, why)`` when not even that is free."""
    deadline = time.monotonic() + wait_s
    said = False
    while True:
        avail = mem_available_gb()
        if avail >= cap_gb + 1:
            return int(cap_gb * 1024**3), None
        if time.monotonic() > deadline:
            if avail - 1 >= MIN_CAP_GB:
                return int((avail - 1) * 1024**3), None
            return None, (f"skipped: MemAvailable {avail:.1f} GB < {MIN_CAP_GB:g} + 1 GB after "
                          f"waiting {wait_s:g} s")
        if not said:
            log(f"[scale] waiting for memory: MemAvailable {avail:.1f} GB < {cap_gb + 1:g} GB")
            said = True
        time.sleep(5)


def _probe(ctx, method, variant, path, params, timeout) -> dict:
    from benchmarks.cost.scaleprocs import train_child

    q = ctx.Queue()
    proc = ctx.Process(target=train_child, args=(method, variant, path, params, q))
    proc.start()
    got = {}
    status = _drain(proc, q, timeout, got.__setitem__)
    proc.join()
    if got:
        return got
    if status == "timeout":
        return {"timeout": f"killed after --stage-timeout {timeout:g} s"}
    return {status: "the process ended without a result (killed for memory?)"}
