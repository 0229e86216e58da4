"""Peak memory of training on patches against the mesh (docs/SUBDOMAIN.md, "Memory"):
``python -m benchmarks.cost.patchmem``.

Per learner (MeshGraphNet, Implicit-Energy and MeshODENet, their ``quick`` presets on triangle
meshes; MeshODENet's windows of ``--window`` steps, its driven halo on patches) and
per resolution ``r`` of ``plate_cantilever@rN``, one fresh process (one thread, under an
address-space limit of ``--max-memory-gb``, ``RLIMIT_AS``, as ``scaleprocs.train_child``)
loads synthetic trajectories (``scalecore.synthetic_training``: the cost of a step does not
depend on the values; ``--traj`` trajectories of ``--frames`` frames), builds the learner (its
statistics from them) and, with ``--budget`` > 0, ``PatchTraining`` around it, then runs
``--steps`` optimizer steps of ``--batch`` samples through the engine's ``train_epoch``.

Measured from ``/proc/self/status``: ``VmRSS`` after the data are loaded (``data_mb``: the
process with the trajectories and torch, nothing else), the peak ``VmHWM`` of building the
model and its patches (``build_peak_mb``), then, the peak reset (``/proc/self/clear_refs``),
``VmRSS`` before the steps (``before_steps_mb``) and the peak of the steps (``peak_mb``);
``step_mb = peak_mb - before_steps_mb`` is what the steps themselves hold. A process that
does not fit its limit is recorded as such. Rows to ``--out`` (CSV) and a table to stdout.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

FIELDS = ("learner", "r", "n_nodes", "budget", "count", "k", "patch_nodes_max", "batch", "steps",
          "window",
          "data_mb", "build_peak_mb", "before_steps_mb", "peak_mb", "step_mb", "step_s",
          "status")
LEARNERS = ("mgn", "implicit_energy", "meshodenet")
SAVE_DT = 0.01


def _status_mb(key: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak() -> None:
    Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS (Linux >= 4.0)


def write_arrays(r: int, traj: int, frames: int, path: Path) -> int:
    """The synthetic training arrays of ``plate_cantilever@r{r}`` to ``path``; its nodes."""
    from benchmarks.cost.scalecore import synthetic_training
    from benchmarks.suite.registry import get_case

    case = get_case(f"plate_cantilever@r{r}")
    edges, cells, node_type = case.mesh()
    arrays = dict(edges=np.asarray(edges, np.int64), cells=np.asarray(cells, np.int64),
                  node_type=np.asarray(node_type, np.int64), rest_pos=case.rest_positions(),
                  youngs=np.array([case.reference_youngs]),
                  case=np.array(case.id), case_hash=np.array(case.hash()), **case.loads())
    arrays = synthetic_training(arrays, traj, frames, SAVE_DT)
    arrays["youngs"] = case.reference_youngs * np.linspace(0.5, 1.5, traj)  # a spread to normalise
    np.savez(path, **arrays)
    return len(arrays["rest_pos"])


def child(learner: str, path: str, params: dict, q) -> None:
    """One measurement in a fresh process; puts a row (dict) or an error text."""
    cap = int(params["max_memory_gb"] * 1024**3)
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    try:
        q.put(_measure(learner, path, params))
    except (MemoryError, RuntimeError) as e:
        q.put(f"does not fit {params['max_memory_gb']:g} GB: {type(e).__name__}: "
              f"{str(e).splitlines()[0][:120]}")
    except BaseException as e:  # noqa: BLE001 - reported to the parent
        q.put(f"error: {type(e).__name__}: {e}"[:300])


def _measure(learner: str, path: str, params: dict) -> dict:
    import dataclasses

    import torch

    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.registry import get_model_spec
    from meshodenet.subdomain import PatchTraining
    from meshodenet.training.train import make_optimizer, train_epoch

    torch.set_num_threads(1)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    mesh = Mesh.from_arrays(arrays)
    data = Trajectories.from_arrays(arrays)
    del arrays
    row = {"data_mb": _status_mb("VmRSS")}
    spec = get_model_spec(learner)
    train_cfg, model_cfg = spec.presets("quick", mesh.kind)
    if learner == "meshodenet" and params["window"]:
        model_cfg = dataclasses.replace(model_cfg, shooting=params["window"])
    cfg = dataclasses.replace(train_cfg, batch_size=params["batch"], patch_nodes=params["budget"],
                              patch_budget=params["count"])
    torch.manual_seed(0)
    model = spec.build(mesh, model_cfg, data)
    if cfg.patch_nodes:
        model = PatchTraining(model, cfg.patch_nodes, budget=cfg.patch_budget)
        row.update(k=model.k, patch_nodes_max=max(p.n_nodes for p in model.patches))
    else:
        row.update(k=1, patch_nodes_max=mesh.n_nodes)
    opt, _ = make_optimizer(model, cfg)
    gen = torch.Generator().manual_seed(0)
    row["build_peak_mb"] = _status_mb("VmHWM")
    _reset_peak()
    row["before_steps_mb"] = _status_mb("VmRSS")
    t0 = time.process_time()
    train_epoch(model, opt, data, cfg, gen, max_batches=params["steps"])
    row["step_s"] = (time.process_time() - t0) / params["steps"]
    row["peak_mb"] = _status_mb("VmHWM")
    row["step_mb"] = row["peak_mb"] - row["before_steps_mb"]
    return dict(row, n_nodes=mesh.n_nodes, status="ok")


def measure(learner: str, r: int, budget: int, path: Path, n_nodes: int, args) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    params = dict(budget=budget, count=args.count, batch=args.batch, steps=args.steps,
                  window=args.window, max_memory_gb=args.max_memory_gb)
    proc = ctx.Process(target=child, args=(learner, str(path), params, q))
    proc.start()
    try:
        out = q.get(timeout=args.timeout)
    except Exception:  # noqa: BLE001 - a child that died or hung
        out = f"no result within {args.timeout} s (exit code {proc.exitcode})"
    proc.join(5)
    if proc.is_alive():
        proc.kill()
    base = dict(learner=learner, r=r, n_nodes=n_nodes, budget=budget,
                count=args.count if budget else "", batch=args.batch, steps=args.steps,
                window=args.window if learner == "meshodenet" else "")
    return dict(base, **out) if isinstance(out, dict) else dict(base, status=out)


def table(rows: list) -> str:
    lines = ["| learner | r | nodes | budget | k | largest patch | before steps MB | "
             "peak MB | steps' own MB | s/step | status |", "|---" * 11 + "|"]
    for w in rows:
        def f(k, fmt="{:.0f}", w=w):
            return fmt.format(w[k]) if k in w else "-"

        budget = f"{w['budget']} ({w['count']})" if w["budget"] else "whole"
        lines.append(f"| {w['learner']} | {w['r']} | {w['n_nodes']} | {budget} "
                     f"| {f('k')} | {f('patch_nodes_max')} | {f('before_steps_mb')} | "
                     f"{f('peak_mb')} | {f('step_mb')} | {f('step_s', '{:.2f}')} | "
                     f"{w['status']} |")
    return "\n".join(lines)


def main(argv=None) -> list:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rs", type=int, nargs="+", default=[8, 16])
    p.add_argument("--whole", type=int, nargs="*", default=[8],
                   help="resolutions also trained on the whole mesh")
    p.add_argument("--learners", nargs="+", default=list(LEARNERS), choices=LEARNERS)
    p.add_argument("--budget", type=int, default=2000)
    p.add_argument("--count", choices=("inner", "total"), default="inner",
                   help="what --budget counts: a part's inner nodes (the halo on top) or the "
                   "whole patch (TrainConfig.patch_budget)")
    p.add_argument("--window", type=int, default=5,
                   help="meshodenet: steps per training window (shooting; 0: the preset's "
                   "whole rollouts of --frames - 1 steps)")
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--traj", type=int, default=2)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--max-memory-gb", type=float, default=12.0)
    p.add_argument("--timeout", type=float, default=1800.0)
    p.add_argument("--out", type=Path, default=Path("patchmem.csv"))
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in args.rs:
            path = Path(tmp) / f"r{r}.npz"
            n = write_arrays(r, args.traj, args.frames, path)
            for learner in args.learners:
                for budget in [args.budget] + ([0] if r in args.whole else []):
                    rows.append(measure(learner, r, budget, path, n, args))
                    print(table(rows[-1:]).splitlines()[-1], flush=True)
    from benchmarks.cost.scalecore import write_rows

    write_rows(args.out, FIELDS, rows, 4, extra="ignore")
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
