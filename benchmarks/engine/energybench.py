"""Implicit-Energy's cost against the solver it stands in for (``meshbench bench``, section
``energy``): per paper case, one training step of the ``quick`` preset, the cost of one
interval of a rollout (one backward-Euler step: Newton on the learned energy) and of a whole
test trajectory, against the case's own solver stepped once per interval (``solver_h``) and at
its own time step (the ground truth). Needs the case's generated data (the model's statistics
and initial stiffness come from its training split); prints, never asserts."""

from __future__ import annotations

import time


def energy_bench(case_id: str, n_traj: int = 2, device="cpu", log=print, data_dir=None) -> dict:
    """Seconds per training step, per rollout interval and per trajectory of
    ``implicit_energy`` (untrained: statistics and least-squares stiffness of the training
    split), and per trajectory of ``solver_h`` and of the ground-truth solver, on the first
    ``n_traj`` test trajectories of ``case_id``. ``{"skipped": why}`` without data."""
    import torch

    from benchmarks.suite.registry import get_case
    from benchmarks.suite.solver_row import SolverRow, SolverRowConfig
    from groundtruth import store
    from meshodenet.data import Mesh, Trajectories
    from meshodenet.models.energy import ImplicitEnergy, energy_presets

    case = get_case(case_id)
    try:
        train, test = (store.load_split(case, s, data_dir) for s in ("train", "test"))
    except store.StoreError as e:
        return {"skipped": f"no generated data ({e}); run `meshbench generate {case_id}`"}
    mesh = Mesh.from_arrays(train)
    tr = Trajectories.from_arrays(train, device=device)
    te = Trajectories.from_arrays(test, device=device).subset(slice(0, n_traj))
    tc, mc = energy_presets("quick", mesh.kind)
    torch.manual_seed(0)
    model = ImplicitEnergy(mesh, mc, tr).to(device)
    samples = torch.randint(0, model.n_training_samples(tr), (tc.batch_size,),
                            generator=torch.Generator().manual_seed(0))
    t0 = time.perf_counter()
    model.training_loss(tr, samples).backward()
    step_s = time.perf_counter() - t0
    args = (te.pos[:, 0], te.vel[:, 0], te.youngs, te.t)
    out = {"batch_size": tc.batch_size, "train_step_s": step_s, "trajectories": len(te),
           "intervals": len(te.t) - 1}
    with torch.no_grad():
        t0 = time.perf_counter()
        model.rollout(*(a[:1] for a in args[:3]), args[3])
        out["single_per_trajectory_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        model.rollout(*args)
        out["batched_per_trajectory_s"] = (time.perf_counter() - t0) / len(te)
        t0 = time.perf_counter()
        SolverRow(mesh, SolverRowConfig()).rollout(*args)
        out["solver_h_per_trajectory_s"] = (time.perf_counter() - t0) / len(te)
    t0 = time.perf_counter()
    for y in test["youngs"][:n_traj]:
        case.simulate(float(y))
    out["solver_per_trajectory_s"] = (time.perf_counter() - t0) / len(te)
    out["single_per_interval_ms"] = 1e3 * out["single_per_trajectory_s"] / out["intervals"]
    log(energy_line(case_id, out))
    return out


def energy_line(case_id: str, r: dict) -> str:
    if "skipped" in r:
        return f"implicit_energy {case_id}: skipped: {r['skipped']}"
    return (f"implicit_energy {case_id}: training step {r['train_step_s']:.2f} s (batch "
            f"{r['batch_size']}); rollout {r['single_per_interval_ms']:.1f} ms per interval, "
            f"{r['single_per_trajectory_s']:.2f} s per trajectory alone, "
            f"{r['batched_per_trajectory_s']:.2f} s batched by {r['trajectories']}; solver at h "
            f"{r['solver_h_per_trajectory_s']:.2f} s, ground-truth solver "
            f"{r['solver_per_trajectory_s']:.2f} s per trajectory")
