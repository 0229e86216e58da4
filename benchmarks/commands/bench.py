"""``meshbench bench train``: cost of one training epoch per gradient mode (prints, never asserts).

Defaults are the paper's settings for ``rod_falling``: 71 trajectories, 200 intervals
(201 frames), hidden 128, one message-passing layer, rk4 with the step equal to the sampling
interval, one trajectory per optimizer step, whole-trajectory rollouts. Each gradient mode runs
in a fresh process, so its peak resident memory (``getrusage`` max RSS; CUDA's
``max_memory_allocated`` on a GPU) is its own. ``--max-batches K`` times K optimizer steps
and extrapolates to the epoch (said so in the output); ``--max-batches 0`` runs the full
epoch. When the case's data is not generated, synthetic trajectories of the same shapes are
used (the cost of fixed-step modes does not depend on the values).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys

from benchmarks.suite.provenance import add_allow_dirty, refuse_dirty

MODES = ("direct", "checkpoint", "adjoint")


def register(sub):
    p = sub.add_parser("bench", help="measure the cost of the models (default: `bench engine`)",
                       description="`meshbench bench [OPTIONS]` (= `meshbench bench engine "
                       "[OPTIONS]`) or `meshbench bench train` or `meshbench bench scale`.",
                       allow_abbrev=False)  # `bench scale --r` is no abbreviation of --rounds
    _engine_arguments(p)
    p.set_defaults(func=run_engine)
    bsub = p.add_subparsers(dest="what", required=False, metavar="WHAT")
    from benchmarks.cost import enginebench

    e = bsub.add_parser("engine", help="vector field, training step, paper epoch and surrogate "
                        "vs solver, per graph and regime", description=enginebench.__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    _engine_arguments(e)
    e.set_defaults(func=run_engine)
    _train_arguments(bsub)
    _scale_arguments(bsub)


def _engine_arguments(e) -> None:
    """The options of ``bench engine`` (also taken by ``bench`` itself)."""
    from benchmarks.cost import enginebench

    e.add_argument("--graphs", default=",".join(enginebench.GRAPHS),
                   help="comma-separated, of " + ", ".join(enginebench.GRAPHS))
    e.add_argument("--regimes", default=",".join(enginebench.REGIMES),
                   help="comma-separated, of " + ", ".join(enginebench.REGIMES))
    e.add_argument("--impl", default="current",
                   help="comma-separated implementations measured interleaved in one process: "
                   "current (the model's default), reference (PyG scatter), handwritten "
                   "(the reference with the hand-written index_add_), fast, authors (a "
                   "stand-in for the authors' code: their architecture, torchdiffeq rk4, direct "
                   "backprop; per-graph regimes only)")
    e.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    e.add_argument("--device", default="auto",
                   help="auto (CUDA if present, default), cpu, cuda or cuda:K (docs/GPU.md)")
    e.add_argument("--epoch-cases", default=",".join(enginebench.PAPER_CASES),
                   help="cases of the paper-epoch estimate, comma-separated, of "
                   + ", ".join(enginebench.PAPER_CASES))
    e.add_argument("--rounds", type=int, default=5, help="interleaved rounds per regime")
    e.add_argument("--budget", type=float, default=0.3, help="seconds per round and impl")
    e.add_argument("--train-intervals", type=int, default=20,
                   help="RK4 intervals of the rollout in the `train` regime")
    e.add_argument("--epoch-steps", type=int, default=2,
                   help="optimizer steps timed for the paper-epoch estimate")
    e.add_argument("--solver-trajectories", type=int, default=2,
                   help="solver runs timed per case for surrogate vs solver")
    e.add_argument("--no-memory", action="store_true", help="skip the peak-memory processes")
    e.add_argument("--no-epoch", action="store_true", help="skip the paper-epoch estimate")
    e.add_argument("--no-solver", action="store_true", help="skip surrogate vs solver")
    e.add_argument("--no-mgn", action="store_true", help="skip MeshGraphNet")
    e.add_argument("--no-energy", action="store_true",
                   help="skip Implicit-Energy's cost against the solver")
    e.add_argument("--energy-only", action="store_true",
                   help="only Implicit-Energy's cost against the solver (section energy)")
    e.add_argument("--energy-rounds", type=int, default=2,
                   help="interleaved rounds of the energy section (default 2)")
    e.add_argument("--json", default=None, help="write the results to this JSON file")
    e.add_argument("--compare", default=None, metavar="BASELINE.json",
                   help="print ratios against a JSON written by --json")
    e.add_argument("--report", default=None, metavar="RESULT.json",
                   help="print the table of a saved result instead of measuring")
    e.add_argument("--compare-impl", default=None,
                   help="implementation of BASELINE.json to compare with (default its first)")
    add_allow_dirty(e)


def _train_arguments(bsub) -> None:
    t = bsub.add_parser("train", help="time and memory of one training epoch per gradient mode",
                        description=__doc__)
    t.add_argument("--case", default="rod_falling")
    t.add_argument("--modes", default=",".join(MODES), help="comma-separated gradient modes")
    t.add_argument("--trajectories", type=int, default=71)
    t.add_argument("--frames", type=int, default=201, help="frames per trajectory (T)")
    t.add_argument("--hidden", type=int, default=128)
    t.add_argument("--integrator", default="rk4")
    t.add_argument("--batch-size", type=int, default=1, help="trajectories per optimizer step")
    t.add_argument("--max-batches", type=int, default=4,
                   help="optimizer steps to time, extrapolated to the epoch; 0 = full epoch")
    t.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    t.add_argument("--device", default="auto")
    t.add_argument("--data-dir", default=None)
    t.add_argument("--json", default=None, help="also write the results to this JSON file")
    add_allow_dirty(t)
    t.set_defaults(func=run)


def run(args):
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    bad = [m for m in modes if m not in MODES]
    if bad:
        raise ValueError(f"--modes: unknown gradient modes {bad}; valid: {', '.join(MODES)}")
    for name in ("trajectories", "hidden", "batch_size"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.frames < 2 or args.max_batches < 0:
        raise ValueError("--frames must be >= 2 and --max-batches >= 0")
    from benchmarks.suite.runs import pick_device

    pick_device(args.device)  # a bad --device fails before the first child starts
    if args.json:
        refuse_dirty(args.json, args.allow_dirty, file=True)
    params = {k: getattr(args, k) for k in ("case", "trajectories", "frames", "hidden",
                                            "integrator", "batch_size", "max_batches",
                                            "threads", "device", "data_dir")}
    ctx = mp.get_context("spawn")
    results = []
    print(f"meshbench bench train: {args.case}, {args.trajectories} trajectories x "
          f"{args.frames} frames, hidden {args.hidden}, {args.integrator}, batch "
          f"{args.batch_size} trajectories/step", flush=True)
    for mode in modes:
        with ctx.Pool(1) as pool:
            res = pool.apply(_measure, (mode, params))
        results.append(res)
        _print_row(res)
    print("(timings on a shared machine vary with its load; compare modes within one run)")
    if args.json:
        from groundtruth.store import save_json

        save_json(args.json, {"params": params, "results": results})
    return 0


def run_engine(args):
    from benchmarks.cost import enginebench as eb
    from benchmarks.cost import report as rp

    def split(text, valid, what):
        items = [x.strip() for x in text.split(",") if x.strip()]
        bad = [x for x in items if x not in valid]
        if bad or not items:
            raise ValueError(f"--{what}: unknown {bad or text!r}; valid: {', '.join(valid)}")
        return items

    graphs = split(args.graphs, eb.GRAPHS, "graphs")
    regimes = split(args.regimes, eb.REGIMES, "regimes")
    impls = split(args.impl, ("current", "reference", "handwritten", "fast", eb.AUTHORS), "impl")
    epoch_cases = split(args.epoch_cases, eb.PAPER_CASES, "epoch-cases")
    for name in ("threads", "rounds", "train_intervals", "epoch_steps", "solver_trajectories",
                 "energy_rounds"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be >= 1, got "
                             f"{getattr(args, name)}")
    if not args.budget > 0:
        raise ValueError(f"--budget must be > 0, got {args.budget}")
    base = rp.load_json(args.compare) if args.compare else None
    if args.report:
        res = rp.load_json(args.report)
        for line in rp.report(res):
            print(line)
        if base is not None:
            print(f"ratios against {args.compare} (best round):")
            for line in rp.compare(res, base, args.compare_impl):
                print("  " + line)
        return 0
    from benchmarks.suite.runs import pick_device

    dev = pick_device(args.device)
    if dev.type != "cpu" and eb.AUTHORS in impls:
        raise ValueError(f"--impl {eb.AUTHORS} runs on the CPU only; use --device cpu for it")
    only = args.energy_only
    if only and args.no_energy:
        raise ValueError("--energy-only and --no-energy exclude each other; drop one")
    if args.json:
        refuse_dirty(args.json, args.allow_dirty, file=True)
    res = eb.run_bench([] if only else graphs, regimes, impls, threads=args.threads,
                       rounds=args.rounds, budget_s=args.budget,
                       train_intervals=args.train_intervals, epoch_steps=args.epoch_steps,
                       memory=not args.no_memory, epochs=not (args.no_epoch or only),
                       solver=not (args.no_solver or only),
                       solver_trajectories=args.solver_trajectories,
                       mgn=not (args.no_mgn or only), energy=not args.no_energy,
                       energy_rounds=args.energy_rounds,
                       log=lambda m: print(m, flush=True), device=dev, epoch_cases=epoch_cases)
    print("(shared machine: compare implementations measured in the same run)")
    if args.json:
        from groundtruth.store import save_json

        save_json(args.json, res)
    if base is not None:
        print(f"ratios against {args.compare}:")
        for line in rp.compare(res, base, args.compare_impl):
            print("  " + line)
    return 0


def _print_row(r: dict) -> None:
    extra = f" (extrapolated from {r['batches_timed']} of {r['batches_per_epoch']} steps)" \
        if r["batches_timed"] < r["batches_per_epoch"] else ""
    gpu = f", GPU peak {r['cuda_peak_gb']:.2f} GB" if r.get("cuda_peak_gb") is not None else ""
    print(f"  {r['mode']:10s} epoch {r['epoch_time_s']:8.1f} s{extra}; peak RSS "
          f"{r['peak_rss_gb']:.2f} GB (process before the epoch {r['base_rss_gb']:.2f} GB){gpu};"
          f" {r['evals_per_s']:.0f} vector-field evals/s "
          f"({r['forward_evals_per_s']:.0f} rollout evals/s); data: {r['data']}", flush=True)


def _measure(mode: str, p: dict) -> dict:
    """Child process: one (possibly partial) epoch of MeshODENet training in ``mode``."""
    import time

    import torch

    from benchmarks.cost import enginebench as eb
    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import pick_device
    from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
    from meshodenet.mesh.data import Mesh, Trajectories
    from meshodenet.training.train import TrainConfig, make_optimizer, train_epoch

    if p["threads"]:
        torch.set_num_threads(p["threads"])
    dev = pick_device(p["device"])
    arrays, source = eb.bench_arrays(get_case(p["case"]), p["trajectories"], p["frames"],
                                   p["data_dir"])
    data = Trajectories.from_arrays(arrays, device=dev)
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), MeshODENetConfig(
        hidden=p["hidden"], integrator=p["integrator"], grad_mode=mode), data).to(dev)
    cfg = TrainConfig(batch_size=p["batch_size"], epochs=1, lr_milestones=())
    opt, _ = make_optimizer(model, cfg)
    n_batches = -(-model.n_training_samples(data) // cfg.batch_size)
    timed = n_batches if p["max_batches"] == 0 else min(p["max_batches"], n_batches)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    base = eb.rss_gb() * 1024**2
    model.nfe = 0
    t0 = time.perf_counter()
    train_epoch(model, opt, data, cfg, torch.Generator().manual_seed(0), max_batches=timed)
    if dev.type == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    peak = eb.peak_gb() * 1024**2  # VmHWM: ru_maxrss would include the spawning parent's peak
    steps = p["frames"] - 1
    evals_per_rollout = steps * {"euler": 1, "midpoint": 2, "rk4": 4}.get(p["integrator"], 0)
    fwd = evals_per_rollout * timed  # evaluations of the forward rollouts themselves
    kb = 1024**2  # ru_maxrss is in KiB on Linux
    return {"mode": mode, "epoch_time_s": wall * n_batches / timed, "timed_s": wall,
            "batches_timed": timed, "batches_per_epoch": n_batches,
            "peak_rss_gb": peak / kb, "base_rss_gb": base / kb,
            "cuda_peak_gb": torch.cuda.max_memory_allocated() / 1024**3
            if dev.type == "cuda" else None,
            "nfe": model.nfe, "evals_per_s": model.nfe / wall,
            "forward_evals_per_s": (fwd or model.nfe) / wall,
            "threads": torch.get_num_threads(), "device": str(dev), "data": source,
            "pid": os.getpid(), "python": sys.version.split()[0]}


# --- bench scale ---------------------------------------------------------------------------
def _scale_arguments(bsub) -> None:
    from benchmarks.cost import scalebench as sb

    s = bsub.add_parser("scale", help="cost and memory of the ground truth and the learners "
                        "against the number of nodes (CASE@rN)", description=sb.__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    s.add_argument("--cases", default=",".join(sb.DEFAULT_CASES),
                   help="comma-separated, of " + ", ".join(sb.CASES))
    s.add_argument("--r", default=None,
                   help="resolutions, comma-separated, for every case (default per case: "
                   + "; ".join(f"{c} {','.join(map(str, r))}" for c, r in sb.DEFAULT_R.items())
                   + ")")
    s.add_argument("--methods", default=",".join(sb.METHODS),
                   help="comma-separated, of " + ", ".join(sb.METHODS))
    s.add_argument("--steps", type=int, default=2,
                   help="saved intervals (the case's save_dt) simulated by the ground truth "
                   "(each of several of its time steps) and rolled out by each model per "
                   "measurement (default 2)")
    s.add_argument("--rounds", type=int, default=2, help="interleaved rounds (default 2)")
    s.add_argument("--window", type=int, default=10,
                   help="intervals of the synthetic training trajectories (default 10)")
    s.add_argument("--train-trajectories", type=int, default=8,
                   help="synthetic training trajectories (default 8)")
    s.add_argument("--preset", default="quick", help="model preset (default quick)")
    s.add_argument("--device", default="cpu",
                   help="cpu (default), auto, cuda or cuda:K for the learners (docs/GPU.md); "
                   "the ground truth runs on the CPU")
    s.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    s.add_argument("--max-memory-gb", type=float, default=16.0,
                   help="memory cap of each training probe (default 16)")
    s.add_argument("--memory-wait", type=float, default=30.0,
                   help="seconds to wait for MemAvailable >= cap + 1 GB before a training "
                   "probe runs under a lower cap, MemAvailable - 1 GB (default 30)")
    s.add_argument("--band-limit-gb", type=float, default=3.0,
                   help="skip the banded ground truth where its band storage exceeds this "
                   "(default 3)")
    s.add_argument("--max-seconds", type=float, default=300.0,
                   help="skip a measurement predicted to take longer (default 300)")
    s.add_argument("--stage-timeout", type=float, default=3600.0,
                   help="kill a measuring process after this many seconds (default 3600)")
    s.add_argument("--grad-modes", default=",".join(("direct", "adjoint", "checkpoint")),
                   help="MeshODENet's gradient modes probed in training (default all three)")
    s.add_argument("--no-train", action="store_true", help="skip the training probes")
    s.add_argument("--out", default="results/scale", help="output directory")
    s.add_argument("--resume", action="store_true",
                   help="keep the rows of OUT/scale.csv and measure only what is missing")
    add_allow_dirty(s)
    s.set_defaults(func=run_scale)


def run_scale(args):
    from benchmarks.cost import scalebench as sb
    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import check_device_name
    from meshodenet.training.presets import check_preset

    def items(text, what):
        out = [x.strip() for x in str(text).split(",") if x.strip()]
        if not out:
            raise ValueError(f"--{what}: empty value {text!r}")
        return out

    cases = items(args.cases, "cases")
    bad = [c for c in cases if c not in sb.CASES]
    if bad:
        raise ValueError(f"--cases: unknown case {bad[0]!r}; valid: {', '.join(sb.CASES)}")
    methods = items(args.methods, "methods")
    bad = [m for m in methods if m not in sb.METHODS]
    if bad:
        raise ValueError(f"--methods: unknown method {bad[0]!r}; valid: {', '.join(sb.METHODS)}")
    if args.r is None:
        rs = {c: list(sb.DEFAULT_R[c]) for c in cases}
    else:
        vals = []
        for x in items(args.r, "r"):
            if not x.isdigit() or int(x) < 1 or x != str(int(x)):
                raise ValueError(f"--r: each resolution must be a positive integer, got {x!r}")
            vals.append(int(x))
        rs = {c: sorted(set(vals)) for c in cases}
    for c in cases:
        for r in rs[c]:
            get_case(sb.refined_id(c, r))
    for name in ("steps", "rounds", "window", "train_trajectories", "threads"):
        v = getattr(args, name)
        if v < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be an integer >= 1, got {v}")
    for name in ("max_memory_gb", "band_limit_gb", "max_seconds", "stage_timeout"):
        v = getattr(args, name)
        if not (v > 0 and v < float("inf")):
            raise ValueError(f"--{name.replace('_', '-')} must be a positive number, got {v}")
    if not args.memory_wait >= 0:
        raise ValueError(f"--memory-wait must be >= 0, got {args.memory_wait}")
    args.grad_modes = items(args.grad_modes, "grad-modes")
    bad = [m for m in args.grad_modes if m not in sb.GRAD_MODES]
    if bad:
        raise ValueError(f"--grad-modes: unknown gradient mode {bad[0]!r}; valid: "
                         f"{', '.join(sb.GRAD_MODES)}")
    check_preset(args.preset)
    check_device_name(str(args.device))
    from benchmarks.suite.runs import pick_device

    pick_device(args.device)
    refuse_dirty(args.out, args.allow_dirty)
    args.cases, args.methods, args.r = cases, methods, rs
    args.train = not args.no_train
    print(f"meshbench bench scale: {', '.join(f'{c} r = {rs[c]}' for c in cases)}; "
          f"{', '.join(methods)}; {args.steps} intervals, {args.rounds} rounds, preset "
          f"{args.preset}, {args.threads} thread(s), device {args.device}; memory cap "
          f"{args.max_memory_gb:g} GB; out {args.out}", flush=True)
    res = sb.run_scale(args, log=lambda m: print(m, flush=True))
    from benchmarks.cost.scalereport import tables

    for line in tables(res["rows"], res["fit_rows"]):
        print(line)
    print(f"wrote {res['csv']}, {res['fits']}" + (f", {res['figure']}" if res["figure"] else ""))
    print("(timings on a shared machine vary with its load; compare rows of one run)")
    return 0
