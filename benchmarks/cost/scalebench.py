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
crossovers to ``fits.csv``, the figure to ``scale.png``.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import platform
import queue as queue_mod
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CASES = ("rod_falling", "plate_cantilever", "plate_hanging")
DEFAULT_CASES = ("rod_falling", "plate_cantilever")
#: resolutions per case (nodes: rod 20 r + 1; plate_cantilever 182 ... ~1e5 at r = 27)
DEFAULT_R = {"rod_falling": (1, 4, 16, 64, 500),
             "plate_cantilever": (1, 2, 4, 8, 16, 27),
             "plate_hanging": (1, 2, 4, 8, 16)}
LEARNERS = ("meshodenet", "mgn", "meshodenet_imex", "implicit_energy",
            "implicit_energy_dissipation")
METHODS = ("groundtruth", "solver_h") + LEARNERS
GRAD_MODES = ("direct", "adjoint", "checkpoint")
#: a timing longer than this (s) is not repeated in later rounds
REPEAT_BELOW_S = 20.0
#: the cost ratio ground truth / learner per simulated second looked for
CROSSOVER_RATIO = 10.0
COLUMNS = ["case", "r", "nodes", "edges", "stage", "method", "variant", "quantity", "value",
           "unit", "note"]
PROVENANCE = ["git_sha", "timestamp", "machine", "cpu_model", "cpu_count", "threads", "device",
              "linear_backend", "preset", "steps", "window", "version_python", "version_numpy",
              "version_scipy", "version_torch"]


# --- small helpers ---------------------------------------------------------------------------
def refined_id(case: str, r: int) -> str:
    return case if r == 1 else f"{case}@r{r}"


def mem_available_gb() -> float:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024**2
    except OSError:
        pass
    return float("inf")


def fit_power(nodes, values) -> tuple[float, float]:
    """``(exponent, prefactor)`` of the least-squares line of log(value) on log(nodes)."""
    x, y = np.log(np.asarray(nodes, float)), np.log(np.asarray(values, float))
    p, a = np.polyfit(x, y, 1)
    return float(p), float(np.exp(a))


def _timer(device):
    """``(now, sync)``: CPU seconds of this process on the CPU, wall seconds (after the GPU's
    queue has run) on CUDA."""
    from benchmarks.cost import device as dv

    if device.type == "cuda":
        return time.perf_counter, lambda: dv.sync(device)
    return time.process_time, lambda: None


def _row(case, r, nodes, edges, stage, method, variant, quantity, value, unit, note=""):
    v = float(value) if value is not None else float("nan")
    return {"case": case, "r": int(r), "nodes": int(nodes), "edges": int(edges), "stage": stage,
            "method": method, "variant": variant, "quantity": quantity, "value": v, "unit": unit,
            "note": note}


def mesh_arrays(case, system, t, pos, vel, youngs, split="single") -> dict:
    """The store layout of ``store.trajectory_arrays`` with the loads of an already built
    ``system`` (``case.loads()`` would build it again)."""
    from groundtruth import store

    edges, cells, node_type = case.mesh()
    return {"t": np.asarray(t, float), "pos": np.asarray(pos, float),
            "vel": np.asarray(vel, float), "youngs": np.asarray(youngs, float),
            "edges": np.asarray(edges, np.int64), "cells": np.asarray(cells, np.int64),
            "node_type": np.asarray(node_type, np.int64), "rest_pos": case.rest_positions(),
            "mass": system.mass.copy(), "force": system.force.copy(),
            "damping": system.damping.copy(), "case": np.array(case.id),
            "split": np.array(split), "case_hash": np.array(case.hash()),
            "format_version": np.array(store.FORMAT_VERSION)}


def synthetic_training(arrays: dict, n_traj: int, frames: int, save_dt: float) -> dict:
    """``arrays`` with ``n_traj`` synthetic trajectories of ``frames`` frames (rest positions
    plus a small seeded random walk of the free nodes; the cost of a training step does not
    depend on the values)."""
    rest = np.asarray(arrays["rest_pos"], float)
    rng = np.random.default_rng(0)
    shape = (n_traj, frames) + rest.shape
    vel = 1e-3 * rng.standard_normal(shape).cumsum(1) / np.sqrt(frames)
    vel *= (np.asarray(arrays["node_type"]) == 0)[None, None, :, None]
    vel[:, 0] = 0.0
    pos = rest + np.cumsum(vel, 1) * save_dt
    youngs = np.full(n_traj, float(np.asarray(arrays["youngs"]).ravel()[0]))
    return dict(arrays, t=np.arange(frames) * save_dt, pos=pos, vel=vel, youngs=youngs,
                split=np.array("train"))


def base_model(method: str, case_id: str, preset: str, device, log=None):
    """An untrained ``method`` (seeded weights) on the base case's mesh, its statistics from the
    base case's training data (the generated data when present, else synthetic), and where the
    data came from."""
    import torch

    from benchmarks.cost.enginebench import bench_arrays
    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import get_model_spec
    from meshodenet.mesh.data import Mesh, Trajectories

    base = get_case(case_id.split("@")[0])
    n = min(base.n_train, 8)
    arrays, source = bench_arrays(base, n, base.n_frames, None)
    mesh = Mesh.from_arrays(arrays)
    spec = get_model_spec(method)
    _, cfg = spec.presets(preset, mesh.kind)
    torch.manual_seed(0)
    model = spec.build(mesh, cfg, Trajectories.from_arrays(arrays))
    return model.to(device), source


# --- the timing process ----------------------------------------------------------------------
def timing_child(case_id: str, r: int, methods: list, skip: dict, params: dict, out_q):
    """Fresh process: every timing of ``case_id`` at resolution ``r`` interleaved; rows and log
    lines go to ``out_q`` as they are measured (``("row", dict)``, ``("log", str)``, then
    ``("done", None)``)."""
    try:
        if not params["device"].startswith("cuda") and params.get("cap_bytes"):
            resource.setrlimit(resource.RLIMIT_AS, (params["cap_bytes"], params["cap_bytes"]))
        _timing(case_id, r, methods, skip, params, out_q)
    except BaseException as e:  # noqa: BLE001 - reported to the parent, which records it
        out_q.put(("error", f"{type(e).__name__}: {e}"))
    out_q.put(("done", None))


def _timing(case_id, r, methods, skip, params, out_q):
    import torch

    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import pick_device
    from groundtruth import assembly, implicit
    from groundtruth.store import save_npz

    torch.set_num_threads(params["threads"])
    log = lambda m: out_q.put(("log", m))  # noqa: E731
    dev = pick_device(params["device"])
    cid = refined_id(case_id, r)
    t0 = time.process_time()
    case = get_case(cid)
    edges = case.mesh()[0]
    nodes = len(case.node_type())
    y = case.reference_youngs
    system = case.system(y)
    build_s = time.process_time() - t0
    row = lambda *a, **k: out_q.put(("row", _row(case_id, r, nodes, len(edges), "timing",  # noqa: E731
                                                  *a, **k)))
    a = system.assembler
    backend = "band LU" if a.banded else f"sparse ({assembly.available_backend()})"
    row("groundtruth", "auto", "system_build_cpu_s", build_s, "s",
        f"case, mesh and system built once (not in the per-step times); {backend}")
    log(f"{cid}: {nodes} nodes, {len(edges)} edges, ndof {a.ndof}, bandwidth {a.bandwidth}; "
        f"system built in {build_s:.1f} CPU s; auto = {backend}")
    q0, v0 = case.initial_state()
    q0, v0 = q0.ravel(), v0.ravel()
    steps = params["steps"]
    t_save = np.arange(steps + 1) * case.save_dt
    settings = case.solver_settings

    variants = {"auto": system}
    band_gb = (5 * a.bandwidth + 2) * a.ndof * 8 / 1e9
    if "groundtruth" in methods:
        if band_gb > params["band_limit_gb"]:
            row("groundtruth", "banded", "step_cpu_s", None, "s",
                f"skipped: the band storage would take {band_gb:.1f} GB > --band-limit-gb "
                f"{params['band_limit_gb']:g}")
        else:
            variants["banded"] = dataclasses.replace(system, linear_solver="banded")
    best: dict = {}
    traj = {}

    def gt_run(name, sysm):
        t1 = time.process_time()
        pos, vel, st = implicit.simulate(sysm, q0, v0, t_save, settings)
        dt = time.process_time() - t1
        traj[name] = (pos, vel)
        return dt / st.steps, st.newton_iterations / st.steps, st

    def first_solve(sysm):
        """CPU s of the linear solve (factorization included) of the first Newton matrix."""
        m, c = sysm.mass_dofs, sysm.damping_dofs
        h = settings.dt
        free = ~sysm.fixed_dofs
        q = q0 + h * v0 * free
        g, K = sysm.gradient_hessian(q, m / h**2 + c / h)
        f = m * ((q - q0) / h - v0) / h + g + c * (q - q0) / h - sysm.force_dofs
        f[~free] = 0.0
        t1 = time.process_time()
        K.solve(f)
        return time.process_time() - t1

    # learners on the refined mesh, built before any timing
    models = {}
    want_learners = [m for m in LEARNERS if m in methods and m not in skip]
    if want_learners or "solver_h" in methods:
        # the real initial frames of the refined case (one interval of the auto ground truth)
        pos1, vel1, _ = implicit.simulate(system, q0, v0, t_save[:2], settings)
        arrays = mesh_arrays(case, system, t_save[:2], pos1.reshape(1, 2, nodes, 3),
                             vel1.reshape(1, 2, nodes, 3), [y])
    if params.get("train_arrays"):  # the probes' mesh, without building the system again
        save_npz(Path(params["train_arrays"]), synthetic_training(
            arrays if want_learners or "solver_h" in methods else
            mesh_arrays(case, system, t_save[:2], np.repeat(q0.reshape(1, 1, nodes, 3), 2, 1),
                        np.zeros((1, 2, nodes, 3)), [y]),
            params["train_traj"], params["window"] + 1, case.save_dt))
    if want_learners:
        from meshodenet.mesh.data import Mesh, Trajectories

        mesh = Mesh.from_arrays(arrays)
        data = Trajectories.from_arrays(arrays, device=dev)
        tt = torch.as_tensor(t_save, dtype=torch.float32, device=dev)
        for m in want_learners:
            try:
                model, source = base_model(m, case_id, params["preset"], dev)
                models[m] = model.on_mesh(mesh).to(dev)
                models[m].eval()
                log(f"{cid}: {m} built (statistics: {source}); on_mesh to {nodes} nodes")
            except Exception as e:  # noqa: BLE001 - recorded, the others go on
                row(m, params["preset"], "rollout_interval_s", None, "s",
                    f"failed to build: {type(e).__name__}: {e}"[:300])
    now, sync = _timer(dev)

    def learner_run(m):
        model = models[m]
        sync()
        t1 = now()
        with torch.no_grad():
            model.rollout(data.pos[:1, 0], data.vel[:1, 0], data.youngs[:1], tt)
        sync()
        return (now() - t1) / steps

    def solver_h_run():
        from benchmarks.suite.solver_row import SolverRow, SolverRowConfig
        from meshodenet.mesh.data import Mesh

        sh = SolverRow(Mesh.from_arrays(arrays), SolverRowConfig()).settings(t_save)
        t1 = time.process_time()
        _, _, st = implicit.simulate(system, q0, v0, t_save, sh)
        return (time.process_time() - t1) / steps, st.newton_iterations / steps

    done = set()
    failed = set()
    for rnd in range(params["rounds"]):
        if "groundtruth" in methods:
            for name, sysm in variants.items():
                key = ("groundtruth", name)
                if key in done or key in failed:
                    continue
                try:
                    per_step, its, st = gt_run(name, sysm)
                    lu = first_solve(sysm)
                except MemoryError as e:
                    failed.add(key)
                    row("groundtruth", name, "step_cpu_s", None, "s",
                        f"does not fit in the process's memory cap: MemoryError: {e}"[:300])
                    continue
                prev = best.get(key)
                if prev is None or per_step < prev[0]:
                    best[key] = (per_step, its, st.steps, st.halvings)
                best[key + ("solve",)] = min(best.get(key + ("solve",), math.inf), lu)
                log(f"{cid}: ground truth {name}: {per_step:.4g} CPU s/step, {its:.2f} Newton "
                    f"iterations/step ({st.steps} steps); first Newton matrix solved in "
                    f"{lu:.4g} s (round {rnd + 1})")
                if per_step * st.steps > REPEAT_BELOW_S:
                    done.add(key)
        if "solver_h" in methods and "solver_h" not in skip and "solver_h" not in done:
            per, its = solver_h_run()
            if per < best.get("solver_h", (math.inf,))[0]:
                best["solver_h"] = (per, its)
            log(f"{cid}: solver_h: {per:.4g} CPU s/interval, {its:.2f} Newton iterations/"
                f"interval (round {rnd + 1})")
            if per * steps > REPEAT_BELOW_S:
                done.add("solver_h")
        for m in models:
            if m in done or m in failed:
                continue
            try:
                per = learner_run(m)
            except Exception as e:  # noqa: BLE001 - a learner that fails is recorded
                failed.add(m)
                what = "does not fit in the process's memory cap" if _is_oom(e) else "failed"
                row(m, params["preset"], "rollout_interval_s", None, "s",
                    f"{what}: {type(e).__name__}: {e}"[:300])
                log(f"{cid}: {m} rollout failed: {type(e).__name__}: {e}"[:300])
                continue
            best[m] = min(best.get(m, math.inf), per)
            log(f"{cid}: {m}: {per:.4g} s/interval (round {rnd + 1})")
            if per * steps > REPEAT_BELOW_S:
                done.add(m)

    dt = settings.dt
    for name in variants:
        key = ("groundtruth", name)
        if key not in best:
            continue
        per_step, its, n_steps, halvings = best[key]
        note = backend if name == "auto" else "band LU (LAPACK solve_banded)"
        row("groundtruth", name, "step_cpu_s", per_step, "s", note)
        row("groundtruth", name, "cost_per_sim_s", per_step / dt, "s/s",
            f"CPU s per simulated second (dt = {dt:g} s)")
        row("groundtruth", name, "newton_iterations_per_step", its, "1",
            f"{n_steps} steps, {halvings} halvings")
        row("groundtruth", name, "first_solve_cpu_s", best[key + ("solve",)], "s",
            "linear solve of the first Newton matrix, factorization included")
    if "banded" in traj:
        pb, pa = traj["banded"][0], traj["auto"][0]
        diff = float(np.max(np.abs(pb - pa)) / max(np.max(np.abs(pb - pb[0])), 1e-300))
        row("groundtruth", "auto", "max_diff_vs_banded", diff, "1",
            "max |auto - banded| of the positions over max displacement")
    if "solver_h" in best:
        per, its = best["solver_h"]
        row("solver_h", "backward_euler", "rollout_interval_s", per, "s",
            f"CPU s; one backward-Euler step per save_dt = {case.save_dt:g} s; {backend}")
        row("solver_h", "backward_euler", "cost_per_sim_s", per / case.save_dt, "s/s", "")
        row("solver_h", "backward_euler", "newton_iterations_per_step", its, "1", "")
    clock = "wall s on " + str(dev) if dev.type == "cuda" else "CPU s"
    for m in models:
        if m in best:
            row(m, params["preset"], "rollout_interval_s", best[m], "s",
                f"{clock}; untrained, {params['preset']} preset; {steps} intervals of "
                f"{case.save_dt:g} s")
            row(m, params["preset"], "cost_per_sim_s", best[m] / case.save_dt, "s/s", "")


def _is_oom(e: BaseException) -> bool:
    text = str(e).lower()
    return isinstance(e, MemoryError) or (isinstance(e, RuntimeError) and (
        "alloc" in text or "memory" in text))


# --- the training probes ---------------------------------------------------------------------
def train_child(method: str, variant: str, arrays_path: str, params: dict, out_q):
    """Fresh process under the memory cap: one optimizer step of ``method`` (``variant``: a
    MeshODENet gradient mode, else ``"default"``) on the synthetic trajectories of
    ``arrays_path``; puts ``("result", dict)`` or ``("error", text)``."""
    cap = int(params.get("cap_bytes") or params["max_memory_gb"] * 1024**3)
    try:
        if not params["device"].startswith("cuda"):
            resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
        out_q.put(("result", _train(method, variant, arrays_path, params, cap)))
    except MemoryError as e:
        out_q.put(("nofit", f"MemoryError: {e}"[:300]))
    except RuntimeError as e:
        text = str(e)
        if "alloc" in text.lower() or "memory" in text.lower():
            out_q.put(("nofit", f"{type(e).__name__}: {text}"[:300]))
        else:
            out_q.put(("error", f"{type(e).__name__}: {text}"[:300]))
    except BaseException as e:  # noqa: BLE001 - reported to the parent
        out_q.put(("error", f"{type(e).__name__}: {e}"[:300]))


def _train(method, variant, arrays_path, params, cap) -> dict:
    import torch

    from benchmarks.cost import device as dv
    from benchmarks.cost.enginebench import peak_gb, rss_gb
    from benchmarks.suite.runs import get_model_spec, pick_device
    from groundtruth.store import load_npz
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.training.train import make_optimizer, train_epoch

    torch.set_num_threads(params["threads"])
    dev = pick_device(params["device"])
    if dev.type == "cuda":
        total = torch.cuda.get_device_properties(dev).total_memory
        torch.cuda.set_per_process_memory_fraction(min(1.0, cap / total), dev)
    arrays = load_npz(Path(arrays_path))
    mesh = Mesh.from_arrays(arrays)
    spec = get_model_spec(method)
    tc, mc = spec.presets(params["preset"], mesh.kind)
    changes = {}
    fields = {f.name for f in dataclasses.fields(mc)}
    if method in ("meshodenet", "meshodenet_imex") and "shooting" in fields:
        changes["shooting"] = 0  # the whole window
    if variant in GRAD_MODES and "grad_mode" in fields:
        changes["grad_mode"] = variant
    mc = dataclasses.replace(mc, **changes)
    data = Trajectories.from_arrays(arrays, device=dev)
    torch.manual_seed(0)
    model = spec.build(mesh, mc, data).to(dev)
    cfg = dataclasses.replace(tc, epochs=1, lr_milestones=(), max_batches=0)
    opt, _ = make_optimizer(model, cfg)
    model.start_epoch(max(getattr(mc, "shooting_epochs", 0) or 0, 0))
    base = rss_gb()
    dv.reset_peak(dev)
    now, sync = _timer(dev)
    times = []
    for k in range(2):
        sync()
        t0 = now()
        train_epoch(model, opt, data, cfg, torch.Generator().manual_seed(k), max_batches=1)
        sync()
        times.append(now() - t0)
        if times[0] > REPEAT_BELOW_S:
            break
    return {"step_s": min(times), "steps_timed": len(times), "peak_rss_gb": peak_gb(),
            "setup_rss_gb": base, "cuda_peak_gb": dv.cuda_peak_gb(dev),
            "batch_size": cfg.batch_size, "n_samples": model.n_training_samples(data),
            "config": {k: getattr(mc, k) for k in ("hidden", "layers", "shooting", "grad_mode",
                                                   "integrator") if k in fields},
            "device": str(dev)}


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
    q = ctx.Queue()
    proc = ctx.Process(target=train_child, args=(method, variant, path, params, q))
    proc.start()
    got = {}

    def on_item(kind, value):
        got[kind] = value
    deadline = time.monotonic() + timeout
    while not got and proc.is_alive() and time.monotonic() < deadline:
        try:
            kind, value = q.get(timeout=1.0)
            on_item(kind, value)
        except queue_mod.Empty:
            pass
    if not got:
        try:
            kind, value = q.get(timeout=2.0)
            on_item(kind, value)
        except queue_mod.Empty:
            pass
    if not got:
        if proc.is_alive():
            proc.kill()
            proc.join()
            return {"timeout": f"killed after --stage-timeout {timeout:g} s"}
        proc.join()
        return {f"died (exit {proc.exitcode})": "the process ended without a result (killed "
                "for memory?)"}
    proc.join()
    return got


# --- outputs ---------------------------------------------------------------------------------
def write_csv(path: Path, rows: list) -> None:
    import pandas as pd

    from groundtruth import store

    recs = []
    for x in rows:
        rec = {k: x[k] for k in COLUMNS}
        rec.update({k: x.get("_prov", {}).get(k, "") for k in PROVENANCE})
        recs.append(rec)
    df = pd.DataFrame(recs, columns=COLUMNS + PROVENANCE)
    text = df.to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def write_table(path: Path, recs: list) -> None:
    import pandas as pd

    from groundtruth import store

    text = pd.DataFrame(recs).to_csv(index=False, float_format="%.6g", lineterminator="\n")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def _series(rows, case, method, variant, quantity):
    pts = sorted((x["nodes"], x["value"]) for x in rows
                 if x["case"] == case and x["method"] == method and
                 (variant is None or x["variant"] == variant) and x["quantity"] == quantity
                 and np.isfinite(x["value"]) and x["value"] > 0)
    return [p[0] for p in pts], [p[1] for p in pts]


def fit_table(rows) -> list:
    """Exponents (all sizes, and sizes >= 1000 nodes) of every cost and memory series, and per
    learner the crossover with the ground truth (``CROSSOVER_RATIO`` times cheaper per
    simulated second)."""
    out = []
    keys = sorted({(x["case"], x["method"], x["variant"], x["quantity"]) for x in rows
                   if x["quantity"] in ("step_cpu_s", "rollout_interval_s", "train_step_s",
                                        "peak_rss_gb", "first_solve_cpu_s",
                                        "newton_iterations_per_step", "system_build_cpu_s")})
    for case, method, variant, quantity in keys:
        n, v = _series(rows, case, method, variant, quantity)
        for label, lo in (("all", 0), (">=1e3 nodes", 1000)):
            sel = [(a, b) for a, b in zip(n, v) if a >= lo]
            if len(sel) < 2:
                continue
            p, c = fit_power(*zip(*sel))
            out.append({"case": case, "kind": "exponent", "method": method, "variant": variant,
                        "quantity": quantity, "range": label, "points": len(sel),
                        "nodes_min": sel[0][0], "nodes_max": sel[-1][0], "value": p,
                        "prefactor": c, "note": ""})
    for case in sorted({x["case"] for x in rows}):
        gn, gv = _series(rows, case, "groundtruth", "auto", "cost_per_sim_s")
        for m in LEARNERS:
            ln, lv = _series(rows, case, m, None, "cost_per_sim_s")
            if not gn or not ln:
                continue
            out.append(crossover(case, m, dict(zip(gn, gv)), dict(zip(ln, lv))))
    return out


def crossover(case, method, gt: dict, learner: dict) -> dict:
    """Nodes at which ``learner`` (CPU s per simulated second by nodes) is ``CROSSOVER_RATIO``
    times cheaper than the ground truth ``gt``: measured (log-log interpolation between the
    two sizes around it), else predicted from the exponents fitted over the largest three
    common sizes."""
    common = sorted(set(gt) & set(learner))
    rec = {"case": case, "kind": "crossover_10x", "method": method, "variant": "",
           "quantity": "nodes", "range": "", "points": len(common),
           "nodes_min": common[0] if common else np.nan,
           "nodes_max": common[-1] if common else np.nan, "value": np.nan, "prefactor": np.nan}
    if not common:
        return dict(rec, note="no common sizes")
    ratio = {n: gt[n] / learner[n] for n in common}
    ratios = "; ".join(f"{n}: {ratio[n]:.3g}" for n in common)
    if ratio[common[0]] >= CROSSOVER_RATIO:
        return dict(rec, value=common[0], range="measured",
                    note=f"already >= {CROSSOVER_RATIO:g}x at the smallest size; ratio gt/learner "
                    f"by nodes {ratios}")
    for a, b in zip(common[:-1], common[1:]):
        if ratio[a] < CROSSOVER_RATIO <= ratio[b]:
            x = math.log(a) + (math.log(CROSSOVER_RATIO) - math.log(ratio[a])) * \
                (math.log(b) - math.log(a)) / (math.log(ratio[b]) - math.log(ratio[a]))
            return dict(rec, value=math.exp(x), range="measured",
                        note=f"between {a} and {b} nodes (log-log interpolated); ratio "
                        f"gt/learner by nodes {ratios}")
    last = common[-3:]
    if len(last) < 2:
        return dict(rec, range="not reached", note=f"one size only; ratio {ratios}")
    pg, cg = fit_power(last, [gt[n] for n in last])
    pl, cl = fit_power(last, [learner[n] for n in last])
    note = (f"not reached up to {common[-1]} nodes (ratio there {ratio[common[-1]]:.3g}); "
            f"exponents over {last[0]}-{last[-1]} nodes: ground truth {pg:.2f}, learner "
            f"{pl:.2f}")
    if pg <= pl:
        return dict(rec, range="not reached", note=note + "; the learner grows as fast or "
                    "faster: never, by these exponents")
    n_star = (CROSSOVER_RATIO * cl / cg) ** (1.0 / (pg - pl))
    return dict(rec, value=n_star, range="predicted", note=note + f"; predicted at "
                f"{n_star:.3g} nodes")


LABELS = {"groundtruth": "ground truth", "solver_h": "solver at h", "meshodenet": "MeshODENet",
          "mgn": "MGN", "meshodenet_imex": "MeshODENet-IMEX", "implicit_energy": "Implicit-Energy",
          "implicit_energy_dissipation": "Implicit-Energy, learned dissipation"}


def plot(path: Path, rows, cap_gb: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from groundtruth import store

    cases = [c for c in CASES if any(x["case"] == c for x in rows)]
    fig, axes = plt.subplots(len(cases), 2, figsize=(13, 4.6 * len(cases)), squeeze=False)
    colors = dict(zip(METHODS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    styles = {"auto": "-", "banded": ":", "direct": "-", "adjoint": "--", "checkpoint": ":"}
    for ax, case in zip(axes, cases):
        for method in METHODS:
            variants = sorted({x["variant"] for x in rows if x["case"] == case and
                               x["method"] == method and x["quantity"] == "cost_per_sim_s"})
            for v in variants:
                n, val = _series(rows, case, method, v, "cost_per_sim_s")
                if n:
                    lab = LABELS[method] + (f" ({v})" if method == "groundtruth" else "")
                    ax[0].loglog(n, val, styles.get(v, "-"), marker="o" if method in (
                        "groundtruth", "solver_h") else "s", color=colors[method], label=lab)
            for v in (GRAD_MODES if method == "meshodenet" else ("default",)):
                n, val = _series(rows, case, method, v, "peak_rss_gb")
                if n:
                    ax[1].loglog(n, val, styles.get(v, "-"), marker="s", color=colors[method],
                                 label=LABELS[method] + (f" ({v})" if method == "meshodenet"
                                                         else ""))
        ax[0].set(xlabel="nodes", ylabel="CPU s per simulated second",
                  title=f"{case}: cost per simulated second")
        ax[1].axhline(cap_gb, color="k", ls=":", label=f"{cap_gb:g} GB cap")
        ax[1].set(xlabel="nodes", ylabel="peak resident memory of one training step, GB",
                  title=f"{case}: training memory")
        for a in ax:
            a.grid(True, which="both", alpha=0.3)
            a.legend(fontsize=7)
    fig.tight_layout()

    def write(f):
        fig.savefig(f, format="png", dpi=110)
    store.atomic_write(Path(path), write)
    plt.close(fig)


# --- printed tables --------------------------------------------------------------------------
def tables(rows, fits) -> list[str]:
    lines = []
    for case in sorted({x["case"] for x in rows}):
        lines.append(f"== {case}")
        rs = sorted({x["r"] for x in rows if x["case"] == case})

        def val(r, method, variant, q, case=case):
            for x in rows:
                if (x["case"], x["r"], x["method"], x["quantity"]) == (case, r, method, q) and \
                        (variant is None or x["variant"] == variant):
                    return x["value"]
            return float("nan")
        lines.append(f"{'r':>4} {'nodes':>7} {'gt auto s/step':>14} {'banded s/step':>13} "
                     f"{'ratio':>6} {'Newton/step':>11} {'band LU solve':>13} "
                     f"{'auto/LU solve':>13}")
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            a, b = val(r, "groundtruth", "auto", "step_cpu_s"), \
                val(r, "groundtruth", "banded", "step_cpu_s")
            lu = val(r, "groundtruth", "banded", "first_solve_cpu_s")
            lines.append(f"{r:>4} {n:>7} {a:>14.4g} {b:>13.4g} {b / a:>6.2f} "
                         f"{val(r, 'groundtruth', 'auto', 'newton_iterations_per_step'):>11.2f} "
                         f"{lu:>13.4g} {a / lu:>13.3g}")
        lines.append("CPU s per simulated second (rollout per interval / save_dt; ground truth "
                     "per step / dt):")
        head = ["groundtruth", "solver_h"] + list(LEARNERS)
        lines.append(f"{'r':>4} {'nodes':>7} " + " ".join(f"{LABELS[m][:14]:>14}" for m in head))
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            vals = [val(r, m, "auto" if m == "groundtruth" else None, "cost_per_sim_s")
                    for m in head]
            lines.append(f"{r:>4} {n:>7} " + " ".join(f"{v:>14.4g}" for v in vals))
        lines.append("one training step: s / peak RSS GB")
        cols = [(m, v) for m in LEARNERS for v in (GRAD_MODES if m == "meshodenet"
                                                  else ("default",))]
        lines.append(f"{'r':>4} {'nodes':>7} " + " ".join(
            f"{(m[:10] + ('/' + v[:4] if v != 'default' else '')):>16}" for m, v in cols))
        for r in rs:
            n = next(x["nodes"] for x in rows if x["case"] == case and x["r"] == r)
            cells = []
            for m, v in cols:
                s, g = val(r, m, v, "train_step_s"), val(r, m, v, "peak_rss_gb")
                cells.append(f"{s:>8.3g}/{g:<7.3g}" if np.isfinite(s) else f"{'-':>16}")
            lines.append(f"{r:>4} {n:>7} " + " ".join(cells))
    lines.append("== fitted exponents (>= 1e3 nodes) and crossovers")
    for f in fits:
        if f["kind"] == "exponent" and f["range"] == ">=1e3 nodes" and f["quantity"] in (
                "step_cpu_s", "rollout_interval_s", "train_step_s", "peak_rss_gb"):
            lines.append(f"  {f['case']} {f['method']} [{f['variant']}] {f['quantity']}: "
                         f"N^{f['value']:.2f} over {f['points']} sizes {f['nodes_min']}-"
                         f"{f['nodes_max']}")
        elif f["kind"] == "crossover_10x":
            lines.append(f"  {f['case']} {f['method']}: 10x cheaper than ground truth: "
                         f"{f['range']} {f['value']:.4g} nodes; {f['note']}")
    return lines


if __name__ == "__main__":  # pragma: no cover
    sys.exit("use `meshbench bench scale`")
