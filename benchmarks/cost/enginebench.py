"""``meshbench bench``: the cost of MeshODENet's vector field, its training step and its rollouts.

Per graph (one rod; 8 and 71 rods batched; the plate of the registered ``plate_cantilever``
case, taken from the case at run time) and per regime:

- ``nograd``: one vector-field evaluation without autograd (rollouts, validation), as the
  rollouts call it (``MeshODENet.field_fn``: what does not depend on the state built once);
- ``fwdbwd``: one evaluation and its backward pass (vector-Jacobian product);
- ``train``: a whole-trajectory RK4 training step (``training_loss`` over a rollout of
  ``--train-intervals`` intervals from the initial state, then ``backward``), counted as
  ``4 * intervals`` evaluations of the rollout.

Reported: evaluations per second, achieved GFLOP/s from the FLOP count below, the machine's
measured matmul peak on the same shapes, and peak memory (peak
resident memory, ``VmHWM``, of a fresh process running that regime three times, minus its
resident memory before). Further: the ``paper``-setting epoch time of the rod and
the plate (hidden 128, batch 1, whole rollouts, ``checkpoint`` gradients; estimated from
``--epoch-steps`` optimizer steps times the steps per epoch, validation excluded) with its peak
memory, and the time per trajectory of a rollout of the paper-size surrogate against the DER /
DEP solver on the same initial states and moduli (the case's test moduli), one at a time and
batched. MeshGraphNet at its ``quick`` preset: time of one training step and of one rollout.
Implicit-Energy at its ``quick`` preset (``benchmarks.cost.energybench``, needs generated
data; ``--no-energy`` skips it): a training step, the rollout per interval and per trajectory,
against the solver at the sampling interval and the ground-truth solver.

FLOP count (stated, not measured): ``2 * rows * in * out`` per linear layer of the reference
architecture (edge MLP on the concatenation ``[e, h_i, h_j]``, node MLP on ``[h, sum e]``),
forward only; element-wise work is not counted. A forward+backward evaluation counts 3x the
forward FLOPs, a training-step evaluation also 3x (forward and backward; recomputation of
checkpointed segments is overhead, not counted). The matmul peak times ``torch.mm`` on exactly
these shapes (and their backward shapes are not separately timed).

Model weights are random (seeded) and the trajectories synthetic when the case's data is not
generated: the cost of a fixed-step rollout does not depend on the values. All timings use
``--threads`` torch threads (default 1). ``--impl`` lists the implementations to compare
(``reference``: the module-by-module layers, their sum at the receivers PyG's ``scatter``;
``handwritten``: the same with the hand-written ``index_add_`` sum;
``fast``; ``current`` = whatever the model does by default; ``authors``: a stand-in for the
authors' code, their architecture trained as they train it, ``benchmarks.cost.authors_style``, on
the per-graph regimes only): they are measured
in one process, interleaved round by round, so that their ratios are not skewed by the load of
a shared machine.

``--device`` (default ``cpu``) runs every section but the solver's on that device (``cuda``:
each timing waits for the GPU's queued work, and the peak memory of the memory and epoch
processes is also ``torch.cuda.max_memory_allocated``, ``cuda_peak_gb``; the result's
``device`` says which GPU). ``--epoch-cases`` restricts the paper-epoch estimate.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import resource
import statistics
import sys
import time

from benchmarks.cost import device as dv

GRAPHS = {"rod1": ("rod_falling", 1), "rod8": ("rod_falling", 8), "rod71": ("rod_falling", 71),
          "plate": ("plate_cantilever", 1)}
REGIMES = ("nograd", "fwdbwd", "train")
#: ``--impl authors``: the authors' architecture and training loop (``benchmarks.cost.authors_style``),
#: measured on the per-graph regimes only (not the paper epoch, surrogate or MGN sections)
AUTHORS = "authors"
PAPER_CASES = ("rod_falling", "plate_cantilever")


# --- setup shared by the parent and the memory children -------------------------------------
def _impl_config(config, impl: str):
    """``config`` with the ``engine`` / ``message_passing`` fields of ``--impl impl``."""
    import dataclasses

    if impl == "current":
        return config
    if impl == "handwritten":  # the reference engine with the layers' sum before PyG
        return dataclasses.replace(config, engine="reference", message_passing="handwritten")
    return dataclasses.replace(config, engine=impl)


def _arrays(case_id: str, n: int, frames: int):
    from benchmarks.suite.registry import get_case

    return bench_arrays(get_case(case_id), n, frames, None)


def bench_arrays(case, n: int, frames: int, data_dir):
    """The case's training arrays cut to ``n`` trajectories and ``frames`` frames, or synthetic
    ones of that shape when the data is not generated."""
    import numpy as np

    from groundtruth import store

    try:
        d = store.load_split(case, "train", data_dir)
        if d["pos"].shape[0] >= n and d["pos"].shape[1] >= frames:
            d = dict(d, pos=d["pos"][:n, :frames], vel=d["vel"][:n, :frames],
                     youngs=d["youngs"][:n], t=d["t"][:frames])
            return d, "generated"
    except store.StoreError:
        pass
    t = np.arange(frames) * case.save_dt
    rest = case.rest_positions()
    rng = np.random.default_rng(0)
    shape = (n, frames) + rest.shape
    vel = 1e-3 * rng.standard_normal(shape).cumsum(1) / np.sqrt(frames)
    pos = rest + np.cumsum(vel, 1) * case.save_dt
    return store.trajectory_arrays(case, t, pos, vel, case.sample_youngs("train")[:n]
                                   if case.n_train >= n else np.full(n, case.reference_youngs),
                                   "train"), "synthetic (no generated data found)"


def mesh_and_data(case_id: str, n_graphs: int, frames: int, dtype=None, device="cpu"):
    """``(Mesh, Trajectories, source)`` of the bench data: ``n_graphs`` trajectories of
    ``frames`` frames on ``device`` (``source`` says whether generated or synthetic)."""
    import torch

    from meshodenet.mesh.data import Mesh, Trajectories

    arrays, source = _arrays(case_id, n_graphs, frames)
    data = Trajectories.from_arrays(arrays, dtype=dtype or torch.float32, device=device)
    return Mesh.from_arrays(arrays), data, source


def build(case_id: str, n_graphs: int, frames: int, hidden: int = 128, impl: str = "current",
          dtype=None, device="cpu"):
    """A paper-size MeshODENet (seeded random weights, statistics from the bench data) on
    ``device`` and the bench trajectories there (``n_graphs`` of them)."""
    import torch

    from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig

    mesh, data, source = mesh_and_data(case_id, n_graphs, frames, dtype, device)
    torch.manual_seed(0)
    model = MeshODENet(mesh, _impl_config(MeshODENetConfig(hidden=hidden), impl), data)
    return model.to(device), data, source


def linear_shapes(model, n_graphs: int) -> list[tuple[int, int, int]]:
    """``(rows, in, out)`` of every linear layer of one evaluation (reference architecture)."""
    from torch import nn

    M = model.mesh.n_nodes * n_graphs
    D = 2 * len(model.mesh.edges) * n_graphs
    gnn = model.gnn
    rows = [(gnn.node_encoder, M), (gnn.edge_encoder, D)]
    for layer in gnn.processor:
        rows += [(layer.edge_mlp, D), (layer.node_mlp, M)]
    rows.append((gnn.decoder, M))
    return [(r, m.in_features, m.out_features) for seq, r in rows for m in seq
            if isinstance(m, nn.Linear)]


def eval_flops(shapes) -> int:
    return sum(2 * r * i * o for r, i, o in shapes)


def matmul_peak(shapes, repeats: int = 200, device="cpu") -> float:
    """GFLOP/s of ``torch.mm`` over exactly ``shapes`` on ``device`` (best of 3 rounds)."""
    import torch

    device = torch.device(device)
    ops = [(torch.randn(r, i, device=device), torch.randn(i, o, device=device))
           for r, i, o in shapes]
    flops = eval_flops(shapes) * repeats
    best = float("inf")
    for _ in range(3):
        dv.sync(device)
        t0 = time.perf_counter()
        for _ in range(repeats):
            for a, b in ops:
                torch.mm(a, b)
        dv.sync(device)
        best = min(best, time.perf_counter() - t0)
    return flops / best / 1e9


class Regime:
    """One (graph, regime, implementation) on ``device``: ``run(n)`` performs ``n`` units of
    work (and waits for the device to finish them) and returns the number of vector-field
    evaluations it stands for."""

    def __init__(self, graph: str, regime: str, impl: str, train_intervals: int,
                 device="cpu"):
        import torch

        case_id, n = GRAPHS[graph]
        frames = train_intervals + 1
        self.regime, self.n = regime, n
        self.device = torch.device(device)
        self.authors = None
        if impl == AUTHORS:  # the authors' architecture on the same graph and trajectories
            from benchmarks.cost.authors_style import AuthorsStyle

            if self.device.type != "cpu":
                raise ValueError(f"--impl {AUTHORS} runs on the CPU only, not on --device "
                                 f"{device}")
            mesh, data, self.source = mesh_and_data(case_id, n, frames)
            self.authors = AuthorsStyle(mesh, data, n, regime, train_intervals)
            self.evals = self.authors.evals
            return
        self.model, self.data, self.source = build(case_id, n, frames, impl=impl,
                                                   device=self.device)
        m = self.model
        if regime == "train":
            self.model.train()
            self.samples = torch.arange(n)
            self.evals = 4 * train_intervals
            return
        self.ctx = m.field_context(self.data.youngs[:n])
        # the field as rollouts evaluate it (static parts built once); older code: vector_field
        self.f = m.field_fn(self.ctx) if hasattr(m, "field_fn") else \
            (lambda z: m.vector_field(z, self.ctx))
        x0 = self.data.pos[:n, 1].reshape(-1, 3)
        v0 = self.data.vel[:n, 1].reshape(-1, 3)
        self.z = torch.stack([x0, v0])
        self.w = torch.randn_like(self.z)
        self.evals = 1

    def run(self, reps: int) -> int:
        if self.authors is not None:
            return self.authors.run(reps)
        n = self._run(reps)
        dv.sync(self.device)
        return n

    def _run(self, reps: int) -> int:
        import torch

        m = self.model
        if self.regime == "nograd":
            with torch.no_grad():
                for _ in range(reps):
                    self.f(self.z)
        elif self.regime == "fwdbwd":
            z = self.z.clone().requires_grad_(True)
            for _ in range(reps):
                m.zero_grad(set_to_none=True)
                (self.f(z) * self.w).sum().backward()
        else:
            for _ in range(reps):
                m.zero_grad(set_to_none=True)
                m.training_loss(self.data, self.samples).backward()
        return reps * self.evals


def _status_gb(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of this process from /proc, in GB. Not
    ``getrusage``: its ``ru_maxrss`` survives ``execve``, so a spawned child would inherit the
    parent's peak."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024**2
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


def rss_gb() -> float:
    return _status_gb("VmRSS")


def peak_gb() -> float:
    return _status_gb("VmHWM")


def _memory_child(graph: str, regime: str, impl: str, train_intervals: int,
                  threads: int, device="cpu") -> dict:
    """Fresh process: peak RSS of one regime (three repetitions) above the RSS after setup;
    on a GPU also the peak GPU memory of the three (``cuda_peak_gb``)."""
    import torch

    torch.set_num_threads(threads)
    r = Regime(graph, regime, impl, train_intervals, device)
    base = rss_gb()
    dv.reset_peak(r.device)
    r.run(3)
    peak = peak_gb()
    return {"peak_rss_gb": peak, "setup_rss_gb": base, "peak_above_setup_gb": max(peak - base, 0),
            "cuda_peak_gb": dv.cuda_peak_gb(r.device)}


def _epoch_child(case_id: str, impl: str, steps: int, threads: int, device="cpu") -> dict:
    """Fresh process: ``steps`` paper-setting optimizer steps (whole trajectories, batch 1)
    on ``device``, extrapolated to an epoch of the case's training split."""
    import torch

    from benchmarks.suite.registry import get_case
    from meshodenet.training.train import TrainConfig, make_optimizer, train_epoch

    torch.set_num_threads(threads)
    case = get_case(case_id)
    model, data, source = build(case_id, case.n_train, case.n_frames, impl=impl, device=device)
    cfg = TrainConfig(batch_size=1, epochs=1, lr_milestones=())
    opt, _ = make_optimizer(model, cfg)
    n_val = max(1, round(0.1 * case.n_train)) if case.n_train >= 2 else 0
    steps_per_epoch = case.n_train - n_val
    train_epoch(model, opt, data, cfg, torch.Generator().manual_seed(0), max_batches=1)  # warm
    base = rss_gb()
    dev = model.device
    dv.sync(dev)
    dv.reset_peak(dev)
    t0 = time.perf_counter()
    train_epoch(model, opt, data, cfg, torch.Generator().manual_seed(1), max_batches=steps)
    dv.sync(dev)
    wall = time.perf_counter() - t0
    peak = peak_gb()
    return {"case": case_id, "impl": impl, "steps_timed": steps,
            "steps_per_epoch": steps_per_epoch, "step_s": wall / steps,
            "epoch_s": wall / steps * steps_per_epoch, "peak_rss_gb": peak,
            "setup_rss_gb": base, "cuda_peak_gb": dv.cuda_peak_gb(dev), "device": str(dev),
            "intervals": case.n_frames - 1, "nodes": model.mesh.n_nodes, "data": source}


def _solver_child(case_id: str, n: int) -> dict:
    """Fresh process: the ground-truth solver on the first ``n`` test moduli, one at a time."""
    from benchmarks.suite.registry import get_case

    case = get_case(case_id)
    ys = case.sample_youngs("test")[:n]
    times = []
    for y in ys:
        t0 = time.perf_counter()
        case.simulate(float(y))
        times.append(time.perf_counter() - t0)
    return {"case": case_id, "trajectories": len(ys), "per_trajectory_s": statistics.mean(times),
            "youngs": [float(y) for y in ys]}


def _surrogate(case_id: str, impl: str, n_batch: int, repeats: int, device="cpu") -> dict:
    """Rollout time per trajectory of the paper-size model (on ``device``) from the case's
    initial state at its first ``n_batch`` test moduli: one at a time and all together (best
    of ``repeats``)."""
    import numpy as np
    import torch

    from benchmarks.suite.registry import get_case

    case = get_case(case_id)
    model, _, _ = build(case_id, 1, 3, impl=impl, device=device)
    model.eval()
    q0, v0 = case.initial_state()
    dev = model.device
    tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=dev)
    ys = tensor(case.sample_youngs("test")[:n_batch])
    t = tensor(case.t_save())
    x0, v0 = tensor(q0).reshape(-1, 3), tensor(v0).reshape(-1, 3)
    n = len(ys)

    def once(b):
        with torch.no_grad():
            model.rollout(x0.expand(b, -1, -1), v0.expand(b, -1, -1), ys[:b], t)
        dv.sync(dev)

    best1 = bestb = float("inf")
    for r in range(repeats):
        if r and best1 > 5:  # long rollouts: one repetition is enough
            break
        t0 = time.perf_counter()
        once(1)
        best1 = min(best1, time.perf_counter() - t0)
        t0 = time.perf_counter()
        once(n)
        bestb = min(bestb, (time.perf_counter() - t0) / n)
    return {"single_s": best1, "batched_per_trajectory_s": bestb, "batch": n}


# --- the parent -------------------------------------------------------------------------------
def _spawn(fn, *args):
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def run_bench(graphs, regimes, impls, *, threads=1, rounds=5, budget_s=0.3, train_intervals=20,
              epoch_steps=2, memory=True, epochs=True, solver=True, solver_trajectories=2,
              mgn=True, log=print, device="cpu", epoch_cases=PAPER_CASES, energy=True,
              energy_rounds=2) -> dict:
    """Every section of the module docstring on ``device``; the result as a JSON-able dict."""
    import torch

    torch.set_num_threads(threads)
    dev = torch.device(device)
    device = str(dev)
    out = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "cpus": os.cpu_count(), "python": sys.version.split()[0],
                       "torch": torch.__version__, "threads": threads},
           "device": dv.describe(dev),
           "settings": {"graphs": list(graphs), "regimes": list(regimes), "impls": list(impls),
                        "rounds": rounds, "budget_s": budget_s,
                        "train_intervals": train_intervals, "epoch_steps": epoch_steps,
                        "epoch_cases": list(epoch_cases),
                        "solver_trajectories": solver_trajectories, "device": device},
           "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "graphs": {}, "epochs": {}, "surrogate": {}}
    for g in graphs:
        probe = build(GRAPHS[g][0], GRAPHS[g][1], 3)[0]
        shapes = linear_shapes(probe, GRAPHS[g][1])
        fl = eval_flops(shapes)
        peak = matmul_peak(shapes, device=dev)
        entry = {"nodes": probe.mesh.n_nodes * GRAPHS[g][1],
                 "directed_edges": 2 * len(probe.mesh.edges) * GRAPHS[g][1],
                 "forward_mflop_per_eval": fl / 1e6, "matmul_peak_gflops": peak,
                 "flop_bound_forward_us": fl / (peak * 1e9) * 1e6, "regimes": {}}
        log(f"{g}: {entry['nodes']} nodes, {entry['directed_edges']} directed edges, "
            f"{fl / 1e6:.2f} MFLOP per forward evaluation; matmul peak on these shapes "
            f"{peak:.1f} GFLOP/s")
        for reg in regimes:
            objs = {i: Regime(g, reg, i, train_intervals, dev) for i in impls}
            mult = 1 if reg == "nograd" else 3
            reps = {}
            for i, o in objs.items():  # warm-up and calibration: ~budget_s per measurement
                o.run(1)
                t0 = time.perf_counter()
                o.run(1)
                reps[i] = max(1, int(budget_s / max(time.perf_counter() - t0, 1e-6)))
            samples = {i: [] for i in impls}
            for _ in range(rounds):  # interleaved rounds
                for i, o in objs.items():
                    t0 = time.perf_counter()
                    ev = o.run(reps[i])
                    samples[i].append(ev / (time.perf_counter() - t0))
            res = {}
            for i in impls:
                eps = max(samples[i])  # best round: least disturbed by other processes
                res[i] = {"evals_per_s": eps, "evals_per_s_best": eps,
                          "evals_per_s_median": statistics.median(samples[i]),
                          "gflops": eps * fl * mult / 1e9,
                          "fraction_of_peak": eps * fl * mult / 1e9 / peak}
                if memory:
                    res[i].update(_spawn(_memory_child, g, reg, i, train_intervals, threads,
                                         device))
                mem = f", peak +{res[i]['peak_above_setup_gb'] * 1024:.0f} MB" if memory else ""
                mem += gpu_peak(res[i])
                log(f"  {reg:7s} {i:9s} {eps:10.0f} evals/s  {res[i]['gflops']:6.2f} GFLOP/s "
                    f"({100 * res[i]['fraction_of_peak']:.1f}% of matmul peak){mem}")
            entry["regimes"][reg] = res
            entry["data"] = objs[impls[0]].source
        out["graphs"][g] = entry
    ours = [i for i in impls if i != AUTHORS]
    if epochs and ours:
        for c in epoch_cases:
            out["epochs"][c] = {}
            for i in ours:
                r = _spawn(_epoch_child, c, i, epoch_steps, threads, device)
                out["epochs"][c][i] = r
                log(f"paper epoch {c} [{i}]: {r['epoch_s']:.1f} s (estimated from "
                    f"{r['steps_timed']} of {r['steps_per_epoch']} optimizer steps, "
                    f"{r['step_s']:.2f} s each, validation excluded); peak RSS "
                    f"{r['peak_rss_gb']:.2f} GB{gpu_peak(r)}")
    if solver and ours:
        for c in PAPER_CASES:
            s = _spawn(_solver_child, c, solver_trajectories)
            out["surrogate"][c] = {"solver": s}
            for i in ours:
                r = _surrogate(c, i, len(_case_test_youngs(c)), 2, dev)
                r["speedup_single"] = s["per_trajectory_s"] / r["single_s"]
                r["speedup_batched"] = s["per_trajectory_s"] / r["batched_per_trajectory_s"]
                out["surrogate"][c][i] = r
                log(f"surrogate {c} [{i}]: solver {s['per_trajectory_s']:.2f} s/trajectory "
                    f"(mean of {s['trajectories']}); rollout {r['single_s']:.3f} s alone "
                    f"({r['speedup_single']:.1f}x), {r['batched_per_trajectory_s']:.4f} s per "
                    f"trajectory batched by {r['batch']} ({r['speedup_batched']:.1f}x)")
    if mgn and ours:
        out["mgn"] = {c: mgn_bench(c, ours, log=log, device=dev) for c in PAPER_CASES}
    if energy:
        from benchmarks.cost.energybench import energy_bench

        out["energy"] = {c: energy_bench(c, solver_trajectories, dev, log, rounds=energy_rounds)
                         for c in PAPER_CASES}
    out["finished"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return out


def mgn_bench(case_id: str, impls, rounds: int = 3, log=print, device="cpu") -> dict:
    """MeshGraphNet at its ``quick`` preset on ``device``: one optimizer-step's loss and
    backward on a batch of frames, and a no-grad rollout of one whole trajectory, per
    implementation, interleaved."""
    import torch

    from benchmarks.suite.registry import get_case
    from meshodenet.gnn.mgn import MeshGraphNet, mgn_presets
    from meshodenet.mesh.data import Mesh, Trajectories

    case = get_case(case_id)
    dev = torch.device(device)
    arrays, _ = _arrays(case_id, 2, case.n_frames)
    data = Trajectories.from_arrays(arrays, device=dev)
    mesh = Mesh.from_arrays(arrays)
    tcfg, mcfg = mgn_presets("quick", mesh.kind)
    models = {}
    for i in impls:
        torch.manual_seed(0)
        models[i] = MeshGraphNet(mesh, _impl_config(mcfg, i), data).to(dev)
    samples = torch.randperm(models[impls[0]].n_training_samples(data),
                             generator=torch.Generator().manual_seed(0))[:tcfg.batch_size]

    def step(m):
        m.zero_grad(set_to_none=True)
        m.training_loss(data, samples).backward()
        dv.sync(dev)

    def roll(m):
        with torch.no_grad():
            m.rollout(data.pos[:1, 0], data.vel[:1, 0], data.youngs[:1], data.t)
        dv.sync(dev)

    times = {i: {"step": [], "rollout": []} for i in impls}
    for m in models.values():
        step(m)
    for _ in range(rounds):
        for i, m in models.items():
            t0 = time.perf_counter()
            step(m)
            times[i]["step"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            roll(m)
            times[i]["rollout"].append(time.perf_counter() - t0)
    out = {"hidden": mcfg.hidden, "layers": mcfg.layers, "batch_frames": tcfg.batch_size,
           "rollout_frames": case.n_frames}
    for i in impls:
        out[i] = {"step_s": min(times[i]["step"]), "rollout_s": min(times[i]["rollout"])}
        log(f"mgn {case_id} [{i}] (quick preset: hidden {mcfg.hidden}, {mcfg.layers} blocks): "
            f"training step of {tcfg.batch_size} frames {out[i]['step_s'] * 1e3:.0f} ms, "
            f"rollout of {case.n_frames} frames {out[i]['rollout_s']:.2f} s")
    return out


def _case_test_youngs(case_id):
    from benchmarks.suite.registry import get_case

    return get_case(case_id).sample_youngs("test")


def gpu_peak(r: dict) -> str:
    """``", GPU peak X GB"`` for an entry measured on a GPU, else ``""``."""
    peak = r.get("cuda_peak_gb")
    return f", GPU peak {peak:.2f} GB" if peak is not None else ""
