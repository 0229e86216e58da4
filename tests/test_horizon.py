"""Long-horizon stability metrics (benchmarks/suite/horizon.py): known answers on synthetic
rollouts, the solver's cached references, and the runner adding the rows to a finished run."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pandas as pd
import pytest

from benchmarks.suite import horizon as H
from benchmarks.suite import registry
from groundtruth import store
from groundtruth.cases import RodCase

#: A clamped rod small enough to simulate in milliseconds (the cache and runner tests).
TINY = RodCase(id="rod_tiny", n_nodes=5, lumping="line", mid_radius=None, rho_fluid=0.0,
               viscosity=0.0, clamped_nodes=(0, 1), t_end=0.1, save_dt=0.02, dt=0.005,
               youngs_train=(0.1e9, 0.3e9), youngs_test=(0.12e9, 0.28e9), n_train=1, n_test=2,
               seed_train=1, seed_test=2)
#: A free falling rod that settles within a few chunks of its t_end.
FALLING = RodCase(id="rod_fall_tiny", n_nodes=5, t_end=5.0, n_train=1, n_test=1)


def _square():
    """Two counter-clockwise triangles of the unit square in z = 0, clamped on x = 0, loaded
    in -y (a plate that deforms in its plane)."""
    rest = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    force = np.zeros((4, 3))
    force[:, 1] = -1.0
    return {"rest_pos": rest, "cells": np.array([[0, 1, 2], [0, 2, 3]]), "force": force,
            "node_type": np.array([1, 0, 0, 1]), "t": np.array([0.0, 0.1]),
            "youngs": np.array([1.0])}


def test_an_inverted_triangle_is_counted():
    a = _square()
    rest, cells = a["rest_pos"], a["cells"]
    normals = H.rest_normals(rest, cells)
    assert (H.signed_areas(rest, cells, normals) == pytest.approx([0.5, 0.5]))
    flipped = rest.copy()
    flipped[1, 1] = 2.0  # node 1 crosses the diagonal 0-2: triangle 0 turns clockwise
    frames = np.stack([rest, flipped, flipped, rest])
    assert H.signed_areas(flipped, cells, normals)[0] < 0
    assert H.inverted_counts(frames, cells, normals) == (1, 2)
    degenerate = rest.copy()
    degenerate[1] = [0.5, 0.5, 0.0]  # on the diagonal: zero area counts as inverted
    assert H.inverted_counts(degenerate[None], cells, normals) == (1, 1)
    assert H.deforms_in_plane(a) and H.metric_names(registry.get_case("plate_cantilever"), a) \
        == ["horizon_equilibrium_rmse", "horizon_tip_rel_error", "horizon_inverted_triangles",
            "horizon_inverted_triangle_frames"]
    a["force"] = np.tile([0.0, 0.0, -1.0], (4, 1))  # loaded through its thickness: no count
    assert not H.deforms_in_plane(a)


def test_clamped_metrics_have_known_answers():
    a = _square()
    eq = a["rest_pos"] + [0.0, -0.2, 0.0]
    pred = np.stack([a["rest_pos"], a["rest_pos"], eq])[None]
    case = types.SimpleNamespace(id="square")  # no tip_node of its own
    assert H.tip_node(case, a["rest_pos"]) == 1  # free edge x = 1, nearest y = 0.5 (first)
    v = H.clamped_values(case, pred, a, [eq])
    assert v["horizon_equilibrium_rmse"][0] == pytest.approx(0.0, abs=1e-15)
    assert v["horizon_tip_rel_error"][0] == pytest.approx(0.0, abs=1e-12)
    assert (v["horizon_inverted_triangles"][0], v["horizon_inverted_triangle_frames"][0]) == (0, 0)
    short = pred.copy()
    short[0, -1] = a["rest_pos"] + [0.0, -0.15, 0.0]  # three quarters of the sag
    v = H.clamped_values(case, short, a, [eq])
    assert v["horizon_equilibrium_rmse"][0] == pytest.approx(0.05)
    assert v["horizon_tip_rel_error"][0] == pytest.approx(0.25)
    plate = registry.get_case("plate_cantilever")  # the case's own tip when it defines one
    assert H.tip_node(plate, plate.rest_positions()) == plate.tip_node
    assert H.tip_node(TINY, TINY.rest_positions()) == TINY.n_nodes - 1


def test_rigid_translation_gives_zero_shape_error_and_exact_terminal_speed():
    case = registry.get_case("rod_falling")
    rng = np.random.default_rng(0)
    steady = H.comoving(case.rest_positions() + 1e-3 * rng.standard_normal((21, 3)))
    h, v_t = 0.1, case.terminal_velocity()
    t = h * np.arange(11)
    offset = np.array([0.3, -0.2, 0.1])
    pred = steady[None] + offset + (-v_t * t)[:, None, None] * np.array([0.0, 1.0, 0.0])
    v = H.falling_values(case, pred[None], h, [{"shape": steady}])
    assert v["horizon_shape_rmse"][0] == pytest.approx(0.0, abs=1e-12)
    assert v["horizon_terminal_speed_rel_error"][0] == pytest.approx(0.0, abs=1e-9)
    slow = pred.copy()
    slow[-1] = slow[-2] + (pred[-1] - pred[-2]) * 0.9  # the last interval 10 % slower
    v = H.falling_values(case, slow[None], h, [{"shape": steady}])
    assert v["horizon_terminal_speed_rel_error"][0] == pytest.approx(0.1)


def _tiny_arrays() -> dict:
    """``TINY``'s test split, simulated."""
    ys = TINY.sample_youngs("test")
    sims = [TINY.simulate(y) for y in ys]
    return store.trajectory_arrays(TINY, sims[0]["t"], np.stack([s["pos"] for s in sims]),
                                   np.stack([s["vel"] for s in sims]), ys, "test")


def test_a_diverged_rollout_is_nan_in_every_metric(tmp_path):
    a = _tiny_arrays()
    pred = np.repeat(a["pos"][:, :1], 4, axis=1)
    pred[1, 2, 3] = np.nan
    v = H.horizon_values(TINY, pred, a, tmp_path)
    assert set(v) == {"horizon_equilibrium_rmse", "horizon_tip_rel_error"}
    for name, x in v.items():
        assert np.isfinite(x[0]) and np.isnan(x[1]), name
    rows = H.horizon_frame(v, a, {"run": "r", "case": TINY.id, "model": "m"})
    assert len(rows) == 4 and (rows["step"] == H.FACTOR * (a["pos"].shape[1] - 1)).all()
    md = H.markdown_lines(rows, ["model"])
    assert "### rod_tiny" in md[4] and md[-2].count("(1 diverged)") == 2


def test_the_static_reference_is_cached_and_reused(tmp_path):
    calls = []

    def compute(case, y):
        calls.append(y)
        return {"pos": case.solve_static(y)}

    y = 0.2e9
    first = H.cached(TINY, "static", y, compute, tmp_path)
    path = H.cache_path(TINY, "static", y, tmp_path)
    assert path.exists() and path.parent == tmp_path / "rod_tiny" / "horizon"
    again = H.cached(TINY, "static", y, compute, tmp_path)
    assert calls == [y] and np.array_equal(first["pos"], again["pos"])
    assert np.array_equal(H.static_equilibrium(TINY, y, tmp_path), first["pos"])
    assert first["pos"][-1, 1] < 0  # it sags
    path.write_bytes(b"not an npz")  # a corrupt file is recomputed, atomically replaced
    H.cached(TINY, "static", y, compute, tmp_path)
    assert calls == [y, y] and np.load(path)["pos"].shape == (5, 3)
    other = dataclasses.replace(TINY, r0=2e-3)  # another case hash: another file
    assert H.cache_path(other, "static", y, tmp_path) != path
    assert not list(path.parent.glob(".*.tmp"))


def test_the_steady_fall_is_steady_and_falls_at_the_exact_speed(tmp_path):
    ref = H.steady_fall(FALLING, 0.5e9, tmp_path)
    assert float(ref["speed"]) == pytest.approx(FALLING.terminal_velocity(), rel=1e-6)
    deflection = H.node_rmse(ref["shape"], H.comoving(FALLING.rest_positions()))
    assert 0 < float(ref["change_m"]) <= H.STEADY_RTOL * deflection
    assert H.cache_path(FALLING, "steady", 0.5e9, tmp_path).exists()


class _Standing:
    """A model that holds every node still (x = x0) and counts its rollouts."""

    def __init__(self):
        import torch

        self.device = torch.device("cpu")
        self.calls = 0

    def rollout(self, x0, v0, youngs, t):
        self.calls += 1
        pos = x0[:, None].expand(-1, len(t), -1, -1)
        return pos, 0 * pos


def _tiny_run(tmp_path, monkeypatch):
    """A data directory with ``TINY``'s test split, a finished run's RMSE rows, and the
    runner's loaders patched to reuse it with a standing model."""
    from benchmarks.suite import runner, runs

    monkeypatch.setitem(registry.CASES, TINY.id, TINY)
    arrays = _tiny_arrays()
    store.save_npz(tmp_path / "data" / TINY.id / "test.npz", arrays)
    run_dir = tmp_path / "runs" / "r"
    run_dir.mkdir(parents=True)
    ids = {"run": "r", "case": TINY.id, "model": "meshodenet", "preset": "smoke",
           "integrator": "rk4", "grad_mode": "checkpoint", "seed": 0}
    df = runner.per_run_metrics(arrays["pos"] * 1.01, arrays["pos"], arrays["t"], ids)
    (run_dir / runner.METRICS_FILE).write_text(
        df.to_csv(index=False, float_format="%.9g", lineterminator="\n"))
    model = _Standing()
    monkeypatch.setattr(runs, "resolve_run", lambda *a, **k: {"config": {}})
    monkeypatch.setattr(runs, "decide_run", lambda *a, **k: runs.RunDecision(
        "reuse", stored={"run": "r"}))
    monkeypatch.setattr(runs, "_load_run", lambda *a, **k: ({}, model, {}))
    monkeypatch.setattr(runs, "train_resolved", lambda *a, **k: pytest.fail("retrained"))
    return run_dir, model, arrays


def test_the_runner_adds_the_rows_to_a_finished_run_once(tmp_path, monkeypatch, capsys):
    from benchmarks.suite import runner
    from benchmarks.suite.suites import RunSpec

    run_dir, model, arrays = _tiny_run(tmp_path, monkeypatch)
    path = run_dir / runner.METRICS_FILE
    before = path.read_text()
    spec = RunSpec(TINY.id, "meshodenet", "smoke")
    rec = runner._execute(spec, run_dir, str(tmp_path / "data"), False, "cpu")
    assert rec["reused"] and model.calls == 1
    after = path.read_text()
    assert after.startswith(before)  # the RMSE rows byte for byte
    m = pd.read_csv(path)
    hz = m[m["metric"].str.startswith("horizon_")]
    assert sorted(set(hz["metric"])) == ["horizon_equilibrium_rmse", "horizon_tip_rel_error"]
    T = arrays["pos"].shape[1]
    assert len(hz) == 2 * 2 and (hz["step"] == H.FACTOR * (T - 1)).all()
    assert (hz[["run", "model", "seed"]] == ["r", "meshodenet", 0]).all().all()
    # standing still: the equilibrium distance is the static sag's, the tip error 100 %
    eq = [H.static_equilibrium(TINY, y, tmp_path / "data") for y in arrays["youngs"]]
    sag = H.node_rmse(np.stack(eq), arrays["pos"][:, 0])
    got = hz[hz["metric"] == "horizon_equilibrium_rmse"]["rmse"].to_numpy()
    assert got == pytest.approx(sag, rel=1e-6)  # the rollout is float32
    assert hz[hz["metric"] == "horizon_tip_rel_error"]["rmse"].to_numpy() == pytest.approx(1.0)
    assert "long horizon" in capsys.readouterr().err
    runner._execute(spec, run_dir, str(tmp_path / "data"), False, "cpu")
    assert model.calls == 1 and path.read_text() == after  # present: not added again


def test_a_suite_without_horizon_adds_no_rows(tmp_path, monkeypatch):
    """``Suite.horizon = False`` (the subdomain suites, where 5 times the test trajectories of
    the r = 8 plate cost more than the suite): the run's rows stay its own, nothing is rolled
    out; the runner passes the suite's setting to every run."""
    from benchmarks.suite import runner
    from benchmarks.suite.suites import RunSpec, get_suite

    run_dir, model, _ = _tiny_run(tmp_path, monkeypatch)
    path = run_dir / runner.METRICS_FILE
    before = path.read_text()
    rec = runner._execute(RunSpec(TINY.id, "meshodenet", "smoke"), run_dir,
                          str(tmp_path / "data"), False, "cpu", horizon=False)
    assert rec["reused"] and model.calls == 0 and path.read_text() == before
    assert not get_suite("subdomain").horizon and get_suite("quick").horizon


def test_a_reference_that_fails_keeps_the_run(tmp_path, monkeypatch, capsys):
    from benchmarks.suite import runner
    from benchmarks.suite.suites import RunSpec

    def fail(*a, **k):
        raise H.HorizonError("rod_tiny at Y = 1 Pa: the solver's fall is not steady")

    monkeypatch.setattr(H, "add_to_run", fail)
    runner._add_horizon(RunSpec(TINY.id, "mgn", "smoke"), tmp_path, tmp_path, "cpu")
    err = capsys.readouterr().err
    assert "long horizon: not computed (HorizonError: rod_tiny" in err and "retries" in err
