"""The benchmark suite: `meshbench run` end to end (smoke suite), reuse / retrain / resume of
runs, a plugin case and suite from a separate file, and every registered case x model through
generate, the smoke preset and a test rollout."""

from __future__ import annotations

import dataclasses
import json
import textwrap
import time

import numpy as np
import pandas as pd
import pytest

from benchmarks.cli import main
from benchmarks.suite import registry
from benchmarks.suite.compare import compare, read_csv

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """One run of the smoke suite shared by the tests below (about 30 s)."""
    root = tmp_path_factory.mktemp("smoke")
    args = ["run", "--suite", "smoke", "--results", str(root / "results"), "--runs-dir",
            str(root / "runs"), "--data-dir", str(root / "data"), "--no-progress"]
    assert main(args) == 0
    return root, args


def test_smoke_suite_writes_every_result(smoke):
    root, _ = smoke
    out = root / "results" / "smoke"
    runs = read_csv(out / "runs.csv")
    assert list(runs["run"]) == ["rod_cantilever-meshodenet-smoke-s0",
                                 "rod_cantilever-mgn-smoke-s0"]
    for col in ("case", "model", "integrator", "grad_mode", "seed", "preset", "hidden", "epochs",
                "train_wall_time_s", "rollout_wall_time_s", "peak_rss_mb", "device", "threads",
                "git_sha", "timestamp", "version_torch", "version_numpy"):
        assert col in runs, col
    assert (runs["peak_rss_mb"] > 50).all() and (runs["threads"] == 1).all()
    assert list(runs["integrator"]) == ["rk4", "autoregressive"]

    m = read_csv(out / "metrics.csv")
    assert set(m["metric"]) == {"rmse_at_step", "full_rollout_rmse", "horizon_equilibrium_rmse",
                                "horizon_tip_rel_error"}  # the clamped rod's long horizon
    hz = m[m["metric"].str.startswith("horizon_")]
    assert len(hz) == 2 * 2 * 2 and (hz["step"] == 5 * 100).all()
    assert (hz["rmse"].dropna() > 0).all() and "## Long horizon" in (out / "rmse_at_step.md").read_text()
    steps = m[m["metric"] == "rmse_at_step"]
    # 2 runs x 2 test trajectories x 101 frames, frame 0 exact up to float32
    assert len(steps) == 2 * 2 * 101
    assert (steps.loc[steps["step"] == 0, "rmse"] < 1e-7).all()  # float32 round-off
    full = m[m["metric"] == "full_rollout_rmse"]
    assert len(full) == 4 and (full["rmse"] > 0).all()
    # the full-rollout RMSE is the RMS over frames 1.. of the per-step RMSEs
    s = steps[(steps["run"] == runs["run"][1]) & (steps["trajectory"] == 0) & (steps["step"] > 0)]
    f = full[(full["run"] == runs["run"][1]) & (full["trajectory"] == 0)]["rmse"].item()
    assert f == pytest.approx(((s["rmse"] ** 2).mean()) ** 0.5, rel=1e-5)  # CSV keeps 6 digits

    table = read_csv(out / "rmse_at_step.csv")
    assert sorted(table["step"].unique()) == [1, 20, 40, 60, 80, 100]
    ref = table[table["model"] == "meshodenet"]
    assert (ref["increase_vs_meshodenet_pct"] == 0).all()
    mgn = table[table["model"] == "mgn"].set_index("step")
    ode = ref.set_index("step")
    expect = 100 * (mgn["rmse_mean"] / ode["rmse_mean"] - 1)
    assert mgn["increase_vs_meshodenet_pct"].to_numpy() == pytest.approx(expect.to_numpy(),
                                                                          rel=1e-4)
    assert (table["n_trajectories"] == 2).all()
    md = (out / "rmse_at_step.md").read_text()
    assert "## rod_cantilever" in md and "step 100" in md
    for name in ("rmse_vs_step", "snapshots", "loss_curves"):
        png = out / "figures" / f"{name}_rod_cantilever.png"
        assert png.stat().st_size > 5000, png
    from PIL import Image

    for model in ("meshodenet", "mgn"):  # one animated test rollout per case and model
        gif = out / "figures" / f"rollout_rod_cantilever_{model}.gif"
        with Image.open(gif) as im:
            assert im.n_frames == 60 and gif.stat().st_size < 500_000, gif
    # plain CSVs; the sidecar documents every file and the RMSE definition
    for name in ("runs", "metrics", "rmse_at_step"):
        assert not (out / f"{name}.csv").read_text().startswith("#")
        assert pd.read_csv(out / f"{name}.csv").shape[0] > 0
    readme = (out / "README.md").read_text()
    assert "sqrt(mean over ALL nodes" in readme and "`runs.csv`" in readme
    assert "host" in pd.read_csv(out / "runs.csv").columns


def test_tables_only_rewrites_the_tables_from_the_committed_csvs(smoke, tmp_path, capsys):
    """``--tables-only`` rebuilds rmse_at_step.csv and .md from metrics.csv and runs.csv alone
    (no runs directory): the same rows up to the 6 digits metrics.csv stores; a baseline
    written before the paper-convention columns existed still compares clean."""
    import shutil

    root, args = smoke
    res = tmp_path / "res"
    shutil.copytree(root / "results" / "smoke", res / "smoke")
    old = pd.read_csv(res / "smoke/rmse_at_step.csv")
    (res / "smoke/rmse_at_step.md").unlink()
    metrics_before = (res / "smoke/metrics.csv").read_bytes()
    capsys.readouterr()
    assert main(["run", "--suite", "smoke", "--results", str(res), "--tables-only",
                 "--data-dir", str(root / "data"), "--runs-dir", str(tmp_path / "no-runs")]) == 0
    new = pd.read_csv(res / "smoke/rmse_at_step.csv")
    assert (res / "smoke/metrics.csv").read_bytes() == metrics_before
    assert "## rod_cantilever" in (res / "smoke/rmse_at_step.md").read_text()
    np.testing.assert_allclose(new["rmse_mean"], old["rmse_mean"], rtol=1e-5)
    legacy = old.drop(columns=["rmse_coord_mean", "rmse_coord_std"])
    res = compare(legacy, new, rtol=1e-5, ignore=["rmse_std"])  # a difference of 6-digit values
    assert res.ok, res.moved.to_string()
    assert main(["run", "--suite", "smoke", "--results", str(tmp_path / "empty"),
                 "--tables-only"]) == 2
    assert "metrics.csv: no such file" in capsys.readouterr().err


def test_rerun_reuses_finished_runs_and_compares_clean(smoke, capsys):
    root, args = smoke
    capsys.readouterr()
    again = [a if a != str(root / "results") else str(root / "again") for a in args]
    assert main(again + ["--compare-with", str(root / "results")]) == 0
    cap = capsys.readouterr()
    assert cap.err.count(": reused;") == 2
    assert "OK: every value within" in cap.out
    # the runs.csv rows agree too, provenance aside
    res = compare(read_csv(root / "results/smoke/runs.csv"), read_csv(root / "again/smoke/runs.csv"))
    assert res.ok, res.moved


def test_compare_with_detects_a_regression(smoke, capsys):
    root, args = smoke
    base = root / "baseline"
    (base / "smoke").mkdir(parents=True)
    t = pd.read_csv(root / "results/smoke/rmse_at_step.csv")
    t.loc[3, "rmse_mean"] *= 0.5  # the baseline was twice as good there
    t.to_csv(base / "smoke/rmse_at_step.csv", index=False)
    again = [a if a != str(root / "results") else str(root / "again2") for a in args]
    assert main(again + ["--compare-with", str(base), "--no-figures"]) == 1
    assert "REGRESSION" in capsys.readouterr().out
    assert main(args + ["--compare-with", str(root / "results")]) == 2
    assert "compared with themselves" in capsys.readouterr().err


def test_bad_suite_and_pattern_are_clear_errors(smoke, capsys):
    root, args = smoke
    assert main(["run", "--suite", "nope"]) == 2
    err = capsys.readouterr().err
    assert "'nope'" in err and "smoke" in err and "quick" in err
    assert main(args + ["--only", "plate_zzz"]) == 2
    assert "matches no run" in capsys.readouterr().err
    assert main(args + ["--seeds", "0"]) == 2
    assert "--seeds" in capsys.readouterr().err


def test_changed_configuration_retrains_and_interrupted_run_resumes(smoke):
    import torch

    from benchmarks.suite.runner import execute_run
    from benchmarks.suite.runs import train_run
    from benchmarks.suite.suites import RunSpec

    root, _ = smoke
    data = str(root / "data")
    run_dir = root / "runs" / "rod_cantilever-mgn-smoke-s0"
    threads = torch.get_num_threads()
    try:
        changed = RunSpec("rod_cantilever", "mgn", "smoke", overrides=("train.lr=0.002",))
        rec = execute_run(changed, str(run_dir), data, 1, (), False)
        assert not rec["reused"] and rec["config"]["train"]["lr"] == 0.002
        assert execute_run(changed, str(run_dir), data, 1, (), False)["reused"]
        # a run held by a live process is waited for; a lock left by a dead one is taken over
        import threading

        from benchmarks.suite.procs import DirLock

        held = DirLock(run_dir).acquire()
        threading.Timer(1.0, held.release).start()
        t0 = time.monotonic()
        assert execute_run(changed, str(run_dir), data, 1, (), False)["reused"]
        assert time.monotonic() - t0 >= 0.9
        (run_dir / ".lock").write_text("999999999")
        assert execute_run(changed, str(run_dir), data, 1, (), False)["reused"]

        # an interrupted run: stop after epoch 1 of 2, then the runner resumes it
        spec = RunSpec("rod_cantilever", "mgn", "smoke", seed=3)
        d = root / "runs" / spec.run_id

        def stop(epoch, *a, **k):
            raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            train_run(spec.case, spec.model, spec.preset, d, data_dir=data,
                      overrides=spec.all_overrides(), progress=False, on_epoch_end=stop)
        assert (d / "last.pt").exists() and not (d / "record.json").exists()
        rec = execute_run(spec, str(d), data, 1, (), False)
        assert rec["resumed"] and not rec["reused"]
        hist = pd.read_csv(d / "history.csv")
        assert list(hist["epoch"]) == [1, 2]
        assert [s["resumed"] for s in json.loads((d / "sessions.json").read_text())] == [False, True]
    finally:
        torch.set_num_threads(threads)


def test_plugin_case_and_suite_run_end_to_end(tmp_path, monkeypatch, capsys):
    """The README's recipe: a new rod case and a suite over it, from a separate file."""
    monkeypatch.delenv("MESHBENCH_DATA", raising=False)  # the data must land in ./data
    plugin = tmp_path / "mycases.py"
    plugin.write_text(textwrap.dedent("""
        from benchmarks.suite.registry import register_case
        from benchmarks.suite.suites import RunSpec, Suite, register_suite
        from groundtruth.cases import RodCase

        register_case(RodCase(id="rod_short", n_nodes=8, length=0.05, t_end=0.5,
                              n_train=3, n_test=2), overwrite=True)
        register_suite(Suite("mine", "rod_short on both models",
                             (RunSpec("rod_short", "meshodenet", "smoke"),
                              RunSpec("rod_short", "mgn", "smoke"))), overwrite=True)
    """))
    from benchmarks.suite import suites

    monkeypatch.setattr(registry, "CASES", dict(registry.CASES))
    monkeypatch.setattr(suites, "SUITES", dict(suites.SUITES))
    monkeypatch.chdir(tmp_path)
    assert main(["--plugin", str(plugin), "run", "--suite", "mine", "--no-progress",
                 "--jobs", "2"]) == 0
    table = read_csv(tmp_path / "results/mine/rmse_at_step.csv")
    assert set(table["case"]) == {"rod_short"} and set(table["model"]) == {"meshodenet", "mgn"}
    assert sorted(table["step"].unique()) == [1, 2, 3, 4, 5]
    assert (tmp_path / "data/rod_short/meta.json").exists()


def _small(case):
    """The case with few, short trajectories (same physics, same id)."""
    return dataclasses.replace(case, n_train=3, n_test=1, t_end=8 * case.save_dt)


@pytest.mark.parametrize("case_id", sorted(registry.CASES))
@pytest.mark.parametrize("model_id", ["meshodenet", "mgn"])
def test_every_case_and_model_smoke(case_id, model_id, tmp_path, monkeypatch):
    import numpy as np
    import torch

    from benchmarks.suite.generate import generate
    from benchmarks.suite.runs import rollout_arrays, train_run
    from meshodenet.registry import MODELS

    assert set(MODELS) >= {"meshodenet", "mgn"}
    small = _small(registry.CASES[case_id])
    monkeypatch.setattr(registry, "CASES", {**registry.CASES, case_id: small})
    generate(small, tmp_path, workers=1, progress=False)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        s = train_run(case_id, model_id, "smoke", tmp_path / "run", data_dir=tmp_path,
                      progress=False)
        pred, m = rollout_arrays(tmp_path / "run", "test", tmp_path)
    finally:
        torch.set_num_threads(threads)
    assert s["best_epoch"] >= 1 and np.isfinite(s["test_rmse_m"])
    assert pred["pos"].shape == (1, 9, small.rest_positions().shape[0], 3)
    assert m["case"] == case_id and np.isfinite(m["rmse_m"])


def test_every_registered_suite_resolves():
    """Each run of each suite names registered ids and a valid configuration (e.g. the
    integrators suite's dopri5 + direct and rk4 + adjoint), without training anything."""
    from benchmarks.suite.runs import apply_overrides, get_model_spec
    from benchmarks.suite.suites import SUITES

    assert {"smoke", "quick", "paper", "integrators"} <= set(SUITES)
    for suite in SUITES.values():
        runs = suite.runs()
        assert runs and len({r.run_id for r in runs}) == len(runs)
        for r in runs:
            kind = "triangle" if len(registry.get_case(r.case).mesh()[1]) else "line"
            train, model = apply_overrides(*get_model_spec(r.model).presets(r.preset, kind),
                                           r.all_overrides())
            if r.integrator:
                assert model.integrator == r.integrator and model.grad_mode == r.grad_mode
    ids = [r.run_id for r in SUITES["integrators"].runs(seeds=2)]
    assert "rod_falling-meshodenet-quick-dopri5-direct-s1" in ids and len(ids) == 16
    assert "rod_falling-meshodenet-quick-sdirk2-direct-s1" in ids
    assert [r.run_id for r in SUITES["quick"].runs(only="*-mgn-*")] == [
        "rod_falling-mgn-quick-s0", "plate_cantilever-mgn-quick-s0"]


def test_runs_stored_before_a_setting_existed_are_reused_with_its_default(smoke, tmp_path):
    """A setting added to a config class after a run was stored: the stored run ran with the
    setting's default, so it is reused (and resumable) while the preset keeps the default,
    and retrained when the preset sets another value."""
    import shutil

    import torch

    from benchmarks.suite.runner import execute_run
    from benchmarks.suite.runs import with_defaults
    from benchmarks.suite.suites import RunSpec

    root, _ = smoke
    data = str(root / "data")
    src = root / "runs" / "rod_cantilever-mgn-smoke-s0"
    run_dir = tmp_path / "old"
    threads = torch.get_num_threads()
    spec = RunSpec("rod_cantilever", "mgn", "smoke", overrides=("train.lr=0.002",))
    try:
        execute_run(spec, str(src), data, 1, (), False)
        shutil.copytree(src, run_dir, ignore=shutil.ignore_patterns(".lock"))

        def strip(name, value=None):
            for f, get in (("record.json", lambda d: d["config"]), ("config.json", lambda d: d)):
                d = json.loads((run_dir / f).read_text())
                mc = get(d)["model_config"]
                mc.pop(name) if value is None else mc.__setitem__(name, value)
                (run_dir / f).write_text(json.dumps(d))

        strip("acc_norm")  # as written before acc_norm existed
        stored = json.loads((run_dir / "config.json").read_text())
        assert "acc_norm" not in stored["model_config"]
        assert with_defaults(stored)["model_config"]["acc_norm"] == "component"
        assert execute_run(spec, str(run_dir), data, 1, (), False)["reused"]
        # the same stored run against a preset that sets another value: retrained
        other = RunSpec("rod_cantilever", "mgn", "smoke",
                        overrides=("train.lr=0.002", "model.acc_norm=vector"))
        rec = execute_run(other, str(run_dir), data, 1, (), False)
        assert not rec["reused"] and rec["config"]["model_config"]["acc_norm"] == "vector"
    finally:
        torch.set_num_threads(threads)
    assert with_defaults({"model": "not-registered", "train": {}}) == {"model": "not-registered",
                                                                      "train": {}}


def test_runs_stored_before_val_split_read_as_random_splits():
    """``train.val_split`` was introduced with a new default (stratified); a config stored
    before it ran with the seeded random draw, and reads back so: it differs from today's
    default and equals a configuration that asks for ``random``."""
    from benchmarks.suite.runs import apply_overrides, with_defaults
    from meshodenet.training.train import TrainConfig

    old = {"model": "mgn", "train": {"val_fraction": 0.1, "split_seed": 0}, "model_config": {}}
    assert with_defaults(old)["train"]["val_split"] == "random"
    assert with_defaults({**old, "train": {**old["train"], "val_split": "stratified"}})[
        "train"]["val_split"] == "stratified"
    tc, _ = apply_overrides(TrainConfig(), TrainConfig(), ["train.val_split=random"])
    assert tc.val_split == "random" and TrainConfig().val_split == "stratified"
    with pytest.raises(ValueError, match="val_split"):
        apply_overrides(TrainConfig(), TrainConfig(), ["train.val_split=kfold"])


def test_runs_start_longest_recorded_first(tmp_path):
    """``longest_first``: runs a baseline ``runs.csv`` records start longest training first,
    unrecorded ones before them in the suite's order; a missing or unreadable file changes
    nothing."""
    from benchmarks.suite.procs import longest_first

    ids = ["rod-a-s0", "rod-b-s0", "plate-a-s0", "plate-new-s0", "plate-b-s0"]
    costs = tmp_path / "runs.csv"
    costs.write_text("run,train_wall_time_s,other\nrod-a-s0,150,x\nrod-b-s0,185,x\n"
                     "plate-a-s0,1900,x\nplate-b-s0,nan-ish,x\n")
    assert longest_first(ids, costs) == ["plate-new-s0", "plate-b-s0", "plate-a-s0",
                                         "rod-b-s0", "rod-a-s0"]
    assert longest_first(ids, None) == ids
    assert longest_first(ids, tmp_path / "missing.csv") == ids
    (tmp_path / "bad.csv").write_bytes(b"\xff\xfe\x00garbage")
    assert longest_first(ids, tmp_path / "bad.csv") == ids
