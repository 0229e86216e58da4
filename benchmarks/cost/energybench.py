"""Implicit-Energy's cost against the solver it stands in for (``meshbench bench``, section
``energy``): per paper case, one training step of the ``quick`` preset, the cost of one
interval of a rollout (one backward-Euler step: Newton on the learned energy), of a whole test
trajectory alone, batched by ``n_traj`` and the whole test split batched, against the case's
own solver stepped once per interval (``solver_h``) and at its own time step (the ground
truth). Every rollout is timed with each of ``ImplicitEnergy``'s solvers (``batched``, the
default, and ``reference``, the first solver, kept as a reference), interleaved in ``rounds`` rounds with
the solvers, the best round kept; the largest difference of their positions on the test split
is reported against Newton's tolerance. Needs the case's generated data (the model's statistics
and initial stiffness come from its training split); prints, never asserts."""

from __future__ import annotations

import time

#: ``ImplicitEnergy.solver`` values timed, the new one first
ENERGY_SOLVERS = ("batched", "reference")


def energy_bench(case_id: str, n_traj: int = 2, device="cpu", log=print, data_dir=None,
                 rounds: int = 2) -> dict:
    """Seconds per training step, per rollout interval and per trajectory of
    ``implicit_energy`` (untrained: statistics and least-squares stiffness of the training
    split) per solver (``ENERGY_SOLVERS``; the top-level keys are the default solver's,
    ``"reference"`` holds the old solver's), and per trajectory of ``solver_h`` and of the
    ground-truth solver, on the first ``n_traj`` test trajectories of ``case_id`` (the whole
    test split for ``split_per_trajectory_s``); the best of ``rounds`` interleaved rounds.
    ``{"skipped": why}`` without data."""
    import torch

    from benchmarks.suite.registry import get_case
    from benchmarks.suite.solver_row import SolverRow, SolverRowConfig
    from groundtruth import store
    from meshodenet.energy.model import ImplicitEnergy, energy_presets
    from meshodenet.mesh.data import Mesh, Trajectories

    if rounds < 1 or n_traj < 1:
        raise ValueError(f"energy_bench: rounds and n_traj must be >= 1, got {rounds}, {n_traj}")
    case = get_case(case_id)
    try:
        train, test = (store.load_split(case, s, data_dir) for s in ("train", "test"))
    except store.StoreError as e:
        return {"skipped": f"no generated data ({e}); run `meshbench generate {case_id}`"}
    mesh = Mesh.from_arrays(train)
    tr = Trajectories.from_arrays(train, device=device)
    # float64 in and out (the model computes in float64): the solvers' difference unrounded
    split = Trajectories.from_arrays(test, device=device, dtype=torch.float64)
    te = split.subset(slice(0, n_traj))
    tc, mc = energy_presets("quick", mesh.kind)
    torch.manual_seed(0)
    model = ImplicitEnergy(mesh, mc, tr).to(device)
    samples = torch.randint(0, model.n_training_samples(tr), (tc.batch_size,),
                            generator=torch.Generator().manual_seed(0))
    t0 = time.perf_counter()
    model.training_loss(tr, samples).backward()
    step_s = time.perf_counter() - t0
    first = (te.pos[:1, 0], te.vel[:1, 0], te.youngs[:1], te.t)
    batch = (te.pos[:, 0], te.vel[:, 0], te.youngs, te.t)
    whole = (split.pos[:, 0], split.vel[:, 0], split.youngs, split.t)
    best, pos = {}, {}

    def timed(key, fn, per):
        t0 = time.perf_counter()
        out = fn()
        best[key] = min(best.get(key, float("inf")), (time.perf_counter() - t0) / per)
        return out

    for _ in range(rounds):
        with torch.no_grad():
            for s in ENERGY_SOLVERS:
                model.solver = s
                timed((s, "single"), lambda: model.rollout(*first), 1)
                timed((s, "batched"), lambda: model.rollout(*batch), len(te))
                pos[s] = timed((s, "split"), lambda: model.rollout(*whole)[0], len(split))
            timed("solver_h", lambda: SolverRow(mesh, SolverRowConfig()).rollout(*batch), len(te))
        timed("solver", lambda: [case.simulate(float(y)) for y in test["youngs"][:n_traj]],
              len(te))
    model.solver = ENERGY_SOLVERS[0]
    intervals = len(te.t) - 1
    out = {"batch_size": tc.batch_size, "train_step_s": step_s, "trajectories": len(te),
           "split_trajectories": len(split), "intervals": intervals, "rounds": rounds,
           "solver_h_per_trajectory_s": best["solver_h"],
           "solver_per_trajectory_s": best["solver"],
           "max_abs_diff_m": float((pos["batched"] - pos["reference"]).abs().max()),
           "newton_tol_m": model.config.newton_rtol * model.length}
    for s in ENERGY_SOLVERS:
        r = {"single_per_trajectory_s": best[(s, "single")],
             "batched_per_trajectory_s": best[(s, "batched")],
             "split_per_trajectory_s": best[(s, "split")],
             "single_per_interval_ms": 1e3 * best[(s, "single")] / intervals}
        r["interval_over_solver_h"] = r["single_per_trajectory_s"] / best["solver_h"]
        r["solver_over_split"] = best["solver"] / r["split_per_trajectory_s"]
        if s == ENERGY_SOLVERS[0]:
            out.update(r)
        else:
            out[s] = r
    log(energy_line(case_id, out))
    return out


def _solver_line(r: dict) -> str:
    return (f"rollout {r['single_per_interval_ms']:.2f} ms per interval "
            f"({r['interval_over_solver_h']:.2f}x the solver at h), "
            f"{r['single_per_trajectory_s']:.3f} s per trajectory alone, "
            f"{r['batched_per_trajectory_s']:.3f} s batched by B, "
            f"{r['split_per_trajectory_s']:.3f} s batched over the test split "
            f"({r['solver_over_split']:.1f}x faster than the ground truth)")


def energy_line(case_id: str, r: dict) -> str:
    if "skipped" in r:
        return f"implicit_energy {case_id}: skipped: {r['skipped']}"
    if "reference" not in r:  # a result saved before the batched solver: one solver
        return (f"implicit_energy {case_id}: training step {r['train_step_s']:.2f} s (batch "
                f"{r['batch_size']}); rollout {r['single_per_interval_ms']:.1f} ms per interval, "
                f"{r['single_per_trajectory_s']:.2f} s per trajectory alone, "
                f"{r['batched_per_trajectory_s']:.2f} s batched by {r['trajectories']}; solver "
                f"at h {r['solver_h_per_trajectory_s']:.2f} s, ground-truth solver "
                f"{r['solver_per_trajectory_s']:.2f} s per trajectory")
    head = (f"implicit_energy {case_id}: training step {r['train_step_s']:.2f} s (batch "
            f"{r['batch_size']}); solver at h {r['solver_h_per_trajectory_s']:.3f} s "
            f"({1e3 * r['solver_h_per_trajectory_s'] / r['intervals']:.2f} ms per interval), "
            f"ground-truth solver {r['solver_per_trajectory_s']:.3f} s per trajectory; best of "
            f"{r['rounds']} interleaved rounds, B = {r['trajectories']}, test split "
            f"{r['split_trajectories']}")
    rows = [f"  {s:9s} " + _solver_line(r if s == ENERGY_SOLVERS[0] else r[s])
            .replace("by B", f"by {r['trajectories']}") for s in ENERGY_SOLVERS]
    return "\n".join([head, *rows, f"  positions batched - reference on the test split: max "
                      f"{r['max_abs_diff_m']:.2e} m (Newton's tolerance {r['newton_tol_m']:.2e} m)"])
