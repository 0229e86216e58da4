"""The solver row (``solver_h``, benchmarks/suite/solver_row.py): its rollout is the case's own
solver stepped once per saved interval by backward Euler, clamped nodes stay put, a Newton
failure is a clear error, and the runner records it without training, reuses it and shows it
in the results tables."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest

from benchmarks.suite import registry

torch = pytest.importorskip("torch")


def _short(case, n_intervals=6):
    """The case with few, short trajectories (same physics, same id)."""
    return dataclasses.replace(case, n_train=2, n_test=2, t_end=n_intervals * case.save_dt)


def _model(case, monkeypatch, **config):
    """``solver_h`` on ``case`` (registered in place of the case of the same id)."""
    from benchmarks.suite.runs import get_model_spec
    from meshodenet.mesh.data import Mesh

    monkeypatch.setattr(registry, "CASES", {**registry.CASES, case.id: case})
    edges, cells, node_type = case.mesh()
    mesh = Mesh(edges, cells, node_type, case.rest_positions(), **case.loads(), case=case.id,
                case_hash=case.hash())
    spec = get_model_spec("solver_h")
    _, cfg = spec.presets("quick", mesh.kind)
    return spec.build(mesh, dataclasses.replace(cfg, **config))


def _rollout(model, case, youngs, t):
    x0, v0 = case.initial_state()
    f64 = lambda a: torch.as_tensor(np.asarray(a, float), dtype=torch.float64)
    pos, vel = model.rollout(f64(x0)[None], f64(v0)[None], f64([youngs]), f64(t))
    return pos[0].numpy(), vel[0].numpy()


@pytest.mark.parametrize("case_id", ["rod_falling", "rod_cantilever", "plate_cantilever"])
def test_rollout_is_the_solver_at_the_sampling_interval(case_id, monkeypatch):
    """Bit for bit the case's own simulation with its internal step set to save_dt; clamped
    nodes never move."""
    case = _short(registry.CASES[case_id])
    model = _model(case, monkeypatch)
    youngs = case.reference_youngs
    pos, vel = _rollout(model, case, youngs, case.t_save())
    ref = dataclasses.replace(case, dt=case.save_dt).simulate(youngs)
    assert ref["stats"]["steps"] == len(ref["t"]) - 1  # one step per interval, no halving
    np.testing.assert_array_equal(pos, ref["pos"])
    np.testing.assert_array_equal(vel, ref["vel"])
    clamped = case.node_type() == 1
    assert np.array_equal(pos[:, clamped], np.broadcast_to(pos[:1, clamped], pos[:, clamped].shape))
    assert case_id == "rod_falling" or clamped.any()
    assert np.abs(pos[-1] - pos[0]).max() > 1e-4  # it did move


def test_any_times_one_backward_euler_step_per_interval(monkeypatch):
    """Uneven intervals: each is one step of its own length, as chaining single steps; a
    single time gives the initial state; float32 in, float32 out."""
    from groundtruth.implicit import NewtonSettings, simulate

    case = _short(registry.CASES["rod_falling"])
    model = _model(case, monkeypatch)
    t = np.array([0.0, 0.1, 0.25, 0.3, 0.5])
    pos, vel = _rollout(model, case, 0.5e9, t)
    system = case.system(0.5e9)
    q, v = (a.ravel() for a in case.initial_state())
    for k in range(len(t) - 1):
        h = t[k + 1] - t[k]
        p, w, stats = simulate(system, q, v, t[k:k + 2], NewtonSettings(dt=h, rtol=case.newton_rtol))
        q, v = p[-1], w[-1]
        assert stats.steps == 1
        np.testing.assert_allclose(pos[k + 1].ravel(), q, rtol=0, atol=1e-12)
    p1, _ = _rollout(model, case, 0.5e9, t[:1])
    assert p1.shape == (1, case.n_nodes, 3)
    x0 = torch.as_tensor(case.initial_state()[0], dtype=torch.float32)[None]
    p32, v32 = model.rollout(x0, torch.zeros_like(x0), torch.tensor([5e8]), torch.tensor(t))
    assert p32.dtype == torch.float32 and p32.shape == (1, len(t), case.n_nodes, 3)
    assert torch.equal(p32[:, 0], x0)
    with pytest.raises(ValueError, match="strictly increasing"):
        model.rollout(x0, x0, torch.tensor([5e8]), torch.tensor([0.0, 0.2, 0.1]))


def test_newton_failure_at_h_is_a_clear_error(monkeypatch):
    from groundtruth.implicit import ConvergenceError

    case = _short(registry.CASES["rod_falling"])
    model = _model(case, monkeypatch, max_iter=1)
    with pytest.raises(ConvergenceError, match=r"solver_h on rod_falling, trajectory 0 .*"
                       r"Newton failed at t = 0 s with dt = 0\.1 s after 0 halvings"):
        _rollout(model, case, 0.5e9, case.t_save())


def test_a_mesh_of_another_case_or_none_is_refused(monkeypatch):
    from meshodenet.mesh.data import DataError

    case = _short(registry.CASES["rod_falling"])
    model = _model(case, monkeypatch)
    with pytest.raises(DataError, match="names none"):
        type(model)(dataclasses.replace(model.mesh, case=""), model.config)
    with pytest.raises(DataError, match="regenerate the data"):
        type(model)(dataclasses.replace(model.mesh, case_hash="0" * 64), model.config)
    with pytest.raises(ValueError, match="nothing to train"):
        from meshodenet.training.train import TrainConfig, fit

        fit(model, None, None, TrainConfig(epochs=1), "unused")


@pytest.fixture()
def small_rod(tmp_path, monkeypatch):
    """A short rod_falling (2 test trajectories of 6 intervals) generated under tmp_path."""
    from benchmarks.suite.generate import generate

    case = _short(registry.CASES["rod_falling"])
    monkeypatch.setattr(registry, "CASES", {**registry.CASES, case.id: case})
    generate(case, tmp_path / "data", workers=1, progress=False)
    return case, tmp_path


def test_runner_records_without_training_reuses_and_tabulates(small_rod):
    from benchmarks.suite import figures
    from benchmarks.suite.runner import execute_run, write_results
    from benchmarks.suite.suites import RunSpec, Suite
    from groundtruth import store

    case, root = small_rod
    data, runs = str(root / "data"), root / "runs"
    threads = torch.get_num_threads()
    try:
        specs = [RunSpec(case.id, "solver_h", "quick", seed=s) for s in (0, 1)]
        recs = [execute_run(s, str(runs / s.run_id), data, 1, (), False) for s in specs]
        again = execute_run(specs[0], str(runs / specs[0].run_id), data, 1, (), False)
    finally:
        torch.set_num_threads(threads)
    rec = recs[0]
    assert not rec["reused"] and again["reused"]
    assert (rec["integrator"], rec["grad_mode"]) == ("backward_euler", "none")
    assert (rec["epochs"], rec["best_epoch"], rec["train_wall_time_s"]) == (0, 0, 0.0)
    assert rec["n_parameters"] == 0 and rec["rollout_wall_time_s"] > 0
    run_dir = runs / specs[0].run_id
    assert pd.read_csv(run_dir / "history.csv").empty  # not one epoch trained
    assert json.loads((run_dir / "sessions.json").read_text())[0]["epochs_run"] == 0
    # the truth is the solver at its internal step (10 per interval): close, not equal
    m = pd.read_csv(run_dir / "test_metrics.csv")
    m = m[~m["metric"].str.startswith("horizon_")]  # the long-horizon rows have other units
    assert 0 < m["rmse"].max() < 1e-4
    # seeds change nothing
    a, b = (pd.read_csv(runs / s.run_id / "test_metrics.csv") for s in specs)
    assert a["rmse"].equals(b["rmse"])

    out = root / "results" / "mine"
    write_results(out, recs, runs, Suite("mine", "the solver row", tuple(specs)), figures=False,
                  data_dir=data)
    table = pd.read_csv(out / "rmse_at_step.csv")
    assert set(table["model"]) == {"solver_h"} and (table["integrator"] == "backward_euler").all()
    md = (out / "rmse_at_step.md").read_text().splitlines()
    md_tables = md[:md.index(next(ln for ln in md if ln.startswith("## Long horizon")))]
    rows = [ln for ln in md_tables if ln.startswith("| solver_h |")]
    # two seeds, in the RMSE table, the increase table and the paper's convention's table
    assert len(rows) == 6
    assert md[md.index(rows[1]) + 1].startswith("| *no motion")  # beside the no-motion row
    runs_rows = [ln for ln in md if ln.startswith(f"| {specs[0].run_id} |")]
    per_traj = rec["rollout_wall_time_s"] / 2
    assert runs_rows == [f"| {specs[0].run_id} | n/a (not trained) | {rec['peak_rss_mb']:.0f} | "
                         f"1 | n/a | {per_traj:.3g} | {1e3 * rec['test_rmse_m']:.3g} | "
                         f"{1e3 * rec['test_no_motion_rmse_m']:.3g} |"]
    assert figures.loss_curves(case.id, recs, runs, root / "loss.png").stat().st_size > 1000
    pred = store.load_npz(run_dir / "test_rollout.npz")
    assert str(pred["model"]) == "solver_h"


def test_reference_rows_come_last_in_the_markdown():
    from benchmarks.suite.runner import render_markdown
    from benchmarks.suite.suites import Suite

    rows = [{"case": "c", "model": m, "preset": "quick", "integrator": i, "grad_mode": g,
             "seed": 0, "step": 1, "rmse_mean": r, "rmse_std": 0.0, "n_trajectories": 1,
             "increase_vs_meshodenet_pct": 0.0}
            for m, i, g, r in (("meshodenet", "rk4", "checkpoint", 2e-3),
                               ("solver_h", "backward_euler", "none", 1e-5),
                               ("zz_model", "rk4", "direct", 1e-3))]
    full = pd.DataFrame(columns=["case", "metric", "model", "preset", "integrator", "grad_mode",
                                 "seed", "rmse"])
    md = render_markdown(pd.DataFrame(rows), full, [], Suite("s", "d", ()),
                         {"c": (np.ones((1, 2)), np.ones(1))})
    lines = [ln.split(" |")[0] for ln in md.splitlines() if ln.startswith("| ")]
    assert lines[1:5] == ["| meshodenet", "| zz_model", "| solver_h", "| *no motion (x = x0)*"]
