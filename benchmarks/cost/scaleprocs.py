"""The measuring processes of ``meshbench bench scale`` (``benchmarks.cost.scalebench``): the
interleaved timing of one case at one resolution, and one training probe under the memory cap.
Each is started with the ``spawn`` method and reports through a queue."""

from __future__ import annotations

import dataclasses
import math
import resource
import time
from pathlib import Path

import numpy as np

from benchmarks.cost.scalecore import (
    GRAD_MODES,
    LEARNERS,
    REPEAT_BELOW_S,
    _row,
    _timer,
    base_model,
    mesh_arrays,
    refined_id,
    synthetic_training,
)


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
    ``arrays_path``; puts ``("result", dict)``, ``("nofit", text)`` or ``("error", text)``,
    then ``("done", None)``."""
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
    out_q.put(("done", None))


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
