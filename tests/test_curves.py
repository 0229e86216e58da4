"""Learning curves: budget checkpoints in CPU seconds (a fake clock decides the crossings),
their survival through resume, training unchanged without budgets, TensorBoard events,
`meshbench curves` end to end and resumable, and the `curves` suite's settings."""

from __future__ import annotations

import csv
import dataclasses
import json

import pandas as pd
import pytest
import torch

from meshodenet.training import train as T
from meshodenet.training.train import TrainConfig, budget_checkpoint, fit, load_checkpoint
from tests.conftest import rod_arrays
from tests.test_meshodenet_train import _fit_setup

torch.set_num_threads(1)


class FakeClock:
    """CPU seconds from a list (one value per call), then steps of ``step`` seconds."""

    def __init__(self, values=(), start=0.0, step=1.0):
        self.values, self.now, self.step = list(values), start - step, step

    def __call__(self):
        self.now = self.values.pop(0) if self.values else self.now + self.step
        return self.now


def _setup(**changes):
    model, train, valid, cfg = _fit_setup(rod_arrays(B=4, T=6))
    return model, train, valid, dataclasses.replace(cfg, **changes)


def _budget_rows(run_dir, wall=True):
    rows = list(csv.DictReader(open(run_dir / T.BUDGETS_FILE)))
    return rows if wall else [{k: v for k, v in r.items() if k not in ("wall_s", "load_1m")}
                              for r in rows]


def _same_training(a, b):
    """Same tensors (model, optimizer, RNGs) and the same history up to timings."""
    for name in ("best.pt", "last.pt"):
        x, y = load_checkpoint(a / name), load_checkpoint(b / name)
        for k in x["model"]:
            assert torch.equal(x["model"][k], y["model"][k]), (name, k)
        for k in ("generator", "torch_rng"):
            assert torch.equal(x[k], y[k]), (name, k)
        for i, st in x["optimizer"]["state"].items():
            for k, v in st.items():
                assert torch.equal(torch.as_tensor(v), torch.as_tensor(y["optimizer"]["state"][i][k]))
        keep = ("epoch", "train_loss", "val_rmse", "best_val_rmse", "lr", "skipped_steps")
        assert [{k: r[k] for k in keep} for r in x["history"]] == \
            [{k: r[k] for k in keep} for r in y["history"]]


def test_budgets_are_written_at_the_epoch_that_crosses_them(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup(epochs=6, budgets_s=(2, 3, 10))
    best_at = {}
    clock = FakeClock([0.0, 1.5, 2.5, 5.0, 5.5, 12.0, 13.0])
    fit(model, train, valid, cfg, tmp_path, progress=False, clock=clock,
        on_epoch_end=lambda e, row: best_at.update({e: row["best_val_rmse"]}))
    rows = _budget_rows(tmp_path)
    assert [int(r["budget_s"]) for r in rows] == [2, 3, 10]
    assert [int(r["epoch"]) for r in rows] == [2, 3, 5]
    assert [float(r["cpu_s"]) for r in rows] == [2.5, 5.0, 12.0]
    assert all(float(r["load_1m"]) >= 0 for r in rows)
    for r in rows:
        ck = load_checkpoint(budget_checkpoint(tmp_path, int(r["budget_s"])))  # weights only
        assert ck["epoch"] == int(r["best_epoch"]) <= int(r["epoch"])
        assert float(r["best_val_rmse"]) == pytest.approx(best_at[int(r["epoch"])], rel=1e-5)
        assert ck["best_val_rmse"] == pytest.approx(float(r["best_val_rmse"]), rel=1e-5)
    assert load_checkpoint(tmp_path / "last.pt")["cpu_time_s"] == 13.0


def test_max_cpu_s_ends_training_and_is_the_last_budget(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup(epochs=50, budgets_s=(2,), max_cpu_s=4)
    result = fit(model, train, valid, cfg, tmp_path, progress=False,
                 clock=FakeClock(step=1.5))
    assert result.epochs_run == 3  # 1.5, 3.0, 4.5 CPU s
    assert [(int(r["budget_s"]), int(r["epoch"])) for r in _budget_rows(tmp_path)] == [(2, 2),
                                                                                      (4, 3)]
    # resuming a run whose CPU budget is spent trains nothing more
    again = fit(model, train, valid, cfg, tmp_path, resume=True, progress=False,
                clock=FakeClock(step=1.5))
    assert again.epochs_run == 0 and len(_budget_rows(tmp_path)) == 2


def test_resume_carries_cpu_time_and_budgets(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup(epochs=4, budgets_s=(2, 4))
    fit(model, train, valid, cfg, tmp_path / "a", progress=False, clock=FakeClock())

    class Stop(Exception):
        pass

    def stop(epoch, row):
        if epoch == 2:
            raise Stop

    model, train, valid, cfg = _setup(epochs=4, budgets_s=(2, 4))
    with pytest.raises(Stop):
        fit(model, train, valid, cfg, tmp_path / "b", progress=False, clock=FakeClock(),
            on_epoch_end=stop)
    assert len(_budget_rows(tmp_path / "b")) == 1
    model, train, valid, cfg = _setup(epochs=4, budgets_s=(2, 4))
    # a new process: its CPU clock starts elsewhere; the 2 s already spent carry over
    fit(model, train, valid, cfg, tmp_path / "b", resume=True, progress=False,
        clock=FakeClock(start=100.0))
    assert _budget_rows(tmp_path / "a", False) == _budget_rows(tmp_path / "b", False)
    assert [int(r["epoch"]) for r in _budget_rows(tmp_path / "b")] == [2, 4]
    assert load_checkpoint(tmp_path / "b" / "last.pt")["cpu_time_s"] == 4.0
    _same_training(tmp_path / "a", tmp_path / "b")
    for b in (2, 4):
        x = load_checkpoint(budget_checkpoint(tmp_path / "a", b))["model"]
        y = load_checkpoint(budget_checkpoint(tmp_path / "b", b))["model"]
        assert all(torch.equal(x[k], y[k]) for k in x)


def test_budgets_and_tensorboard_leave_training_unchanged(tmp_path, monkeypatch):
    """Without budgets nothing new is written; budgets, a clock and TensorBoard change no
    tensor and no history value (the same run without any of them is the reference)."""
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup()
    fit(model, train, valid, cfg, tmp_path / "plain", progress=False)
    assert sorted(p.name for p in (tmp_path / "plain").iterdir()) == ["best.pt", "history.csv",
                                                                      "last.pt"]
    monkeypatch.delenv("MESHBENCH_TENSORBOARD")
    model, train, valid, cfg = _setup(budgets_s=(1, 2), max_cpu_s=100)
    fit(model, train, valid, cfg, tmp_path / "budgets", progress=False, clock=FakeClock())
    _same_training(tmp_path / "plain", tmp_path / "budgets")
    assert len(_budget_rows(tmp_path / "budgets")) == 2


def test_a_short_run_is_the_start_of_a_long_one(tmp_path, monkeypatch):
    """Epochs and budgets only extend a run: the best-so-far checkpoint of a long run at the
    end of epoch 2 is the best model of the same run trained for 2 epochs (why the quick runs
    are the short end of the curves)."""
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup(epochs=2)
    fit(model, train, valid, cfg, tmp_path / "short", progress=False)
    model, train, valid, cfg = _setup(epochs=1000, budgets_s=(2,), max_cpu_s=4)
    fit(model, train, valid, cfg, tmp_path / "long", progress=False, clock=FakeClock())
    short = load_checkpoint(tmp_path / "short" / "best.pt")
    at_2 = load_checkpoint(budget_checkpoint(tmp_path / "long", 2))
    assert short["epoch"] == at_2["epoch"]
    assert all(torch.equal(short["model"][k], at_2["model"][k]) for k in short["model"])
    assert load_checkpoint(tmp_path / "long" / "last.pt")["epoch"] == 4


def test_old_checkpoint_without_cpu_time_resumes(tmp_path, monkeypatch):
    """A ``last.pt`` written before budgets existed resumes with no CPU time spent."""
    monkeypatch.setenv("MESHBENCH_TENSORBOARD", "0")
    model, train, valid, cfg = _setup(epochs=2)
    fit(model, train, valid, cfg, tmp_path, progress=False)
    ck = load_checkpoint(tmp_path / "last.pt")
    for k in ("cpu_time_s", "budgets"):
        ck.pop(k)
    T.save_checkpoint(tmp_path / "last.pt", ck)
    model, train, valid, cfg = _setup(epochs=3, budgets_s=(1,))
    fit(model, train, valid, cfg, tmp_path, resume=True, progress=False, clock=FakeClock())
    assert [int(r["epoch"]) for r in _budget_rows(tmp_path)] == [3]


def test_tensorboard_events_beside_the_history(tmp_path, monkeypatch):
    pytest.importorskip("tensorboard", reason="the optional `tensorboard` extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    monkeypatch.delenv("MESHBENCH_TENSORBOARD", raising=False)
    model, train, valid, cfg = _setup()
    fit(model, train, valid, cfg, tmp_path, progress=False)
    assert list(tmp_path.glob("events.out.tfevents.*"))
    acc = EventAccumulator(str(tmp_path)).Reload()
    tags = set(acc.Tags()["scalars"])
    assert {"train/loss", "val/rmse_m", "val/best_rmse_m", "train/lr", "time/epoch_s"} <= tags
    hist = list(csv.DictReader(open(tmp_path / "history.csv")))
    assert [e.step for e in acc.Scalars("train/loss")] == [1, 2, 3]
    assert [e.value for e in acc.Scalars("train/lr")] == pytest.approx(
        [float(r["lr"]) for r in hist])


def test_progress_line_shows_best_and_time_left():
    cfg = TrainConfig(epochs=10)
    state = {"epoch": 2, "wall_time_s": 20.0, "cpu_time_s": 16.0, "best_val_rmse": 1e-3}
    assert T.time_left(cfg, state) == 80.0  # 8 epochs of 10 s
    capped = dataclasses.replace(cfg, max_cpu_s=40)  # 24 CPU s left at 8 per epoch: 3 epochs
    assert T.time_left(capped, state) == 30.0
    row = {"epoch": 2, "train_loss": 0.5, "val_rmse": 2e-3}
    text = T.progress_text(row, state, cfg)
    assert "epoch 2" in text and "best 0.001 m" in text and "left 1m20s" in text


@pytest.mark.parametrize("field,value", [("budgets_s", (3, 2)), ("budgets_s", (0,)),
                                         ("budgets_s", (1.5,)), ("max_cpu_s", -1),
                                         ("max_cpu_s", 2.5)])
def test_budget_settings_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_curves_suite_settings_reach_the_train_config():
    """One run per learned (case, model) of quick (not the solver row, which learns nothing),
    seed 0, tagged apart from the quick runs, with the quick preset's model and learning-rate
    milestones and the long budget."""
    from benchmarks.suite.runs import apply_overrides, trainable, with_defaults
    from benchmarks.suite.suites import CURVE_BUDGETS_S, CURVE_MAX_CPU_S, get_suite
    from meshodenet.registry import get_model_spec

    quick = [r for r in get_suite("quick").runs() if trainable(r.model)]
    curves = get_suite("curves").runs()
    assert len(quick) < len(get_suite("quick").runs())  # the solver rows are left out
    assert [(r.case, r.model, r.seed) for r in curves] == [(r.case, r.model, 0) for r in quick]
    assert all(r.run_id.endswith("-quick-curves-s0") for r in curves)
    for q, r in zip(quick, curves):
        kind = "triangle" if r.case.startswith("plate") else "line"
        base = get_model_spec(q.model).presets("quick", kind)
        t, m = apply_overrides(*base, r.all_overrides())
        assert m == base[1] and t.lr_milestones == base[0].lr_milestones
        assert t.budgets_s == CURVE_BUDGETS_S and t.max_cpu_s == CURVE_MAX_CPU_S >= 7200
        assert t.epochs > 1000 * base[0].epochs
    # a configuration stored before the budget fields existed reads as their defaults
    new = json.loads(json.dumps({"model": "mgn", "train": dataclasses.asdict(TrainConfig())}))
    old = {**new, "train": {k: v for k, v in new["train"].items()
                            if k not in ("budgets_s", "max_cpu_s")}}
    assert with_defaults(old) == new


# --- meshbench curves -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def curve_runs(tiny_case, tmp_path_factory):
    """Two smoke runs (MeshODENet, MGN) of the tiny case with budgets 1 and 2 CPU s and an end
    at 3, trained in this process under a fake CPU clock of 1 s per call."""
    from benchmarks.suite.runner import execute_run
    from benchmarks.suite.suites import SUITES, RunSpec, Suite, register_suite

    case, data = tiny_case
    root = tmp_path_factory.mktemp("curves")
    over = ("train.epochs=20", "train.budgets_s=1,2", "train.max_cpu_s=3")
    suite = register_suite(Suite("curves_test", "test", tuple(
        RunSpec(case.id, m, "smoke", overrides=over, tag="curves") for m in ("meshodenet",
                                                                             "mgn"))),
        overwrite=True)
    mp = pytest.MonkeyPatch()
    mp.setattr(T, "CPU_CLOCK", FakeClock())
    mp.setenv("MESHBENCH_TENSORBOARD", "0")
    threads = torch.get_num_threads()
    try:
        for spec in suite.runs():
            execute_run(spec, str(root / "runs" / spec.run_id), str(data), 1, (), False)
    finally:
        mp.undo()
        torch.set_num_threads(threads)
    args = ["curves", "--suite", "curves_test", "--results", str(root / "results"),
            "--runs-dir", str(root / "runs"), "--data-dir", str(data)]
    yield root, args
    SUITES.pop("curves_test", None)


def test_meshbench_curves_writes_the_table_and_figures(curve_runs, capsys):
    from benchmarks.cli import main
    from benchmarks.suite.curves import COLUMNS

    root, args = curve_runs
    assert main(args) == 0
    out = root / "results" / "curves_test"
    df = pd.read_csv(out / "curves.csv")
    assert tuple(df.columns) == COLUMNS
    assert sorted(df["model"].unique()) == ["meshodenet", "mgn"]
    assert sorted(df["budget_s"].unique()) == [1, 2, 3]
    assert set(df["split"]) == {"val", "test"}
    steps = set(df["step"])
    assert -1 in steps and len(steps) > 2 and (df["rmse"] > 0).all()
    assert (df.groupby(["model", "budget_s"])["cpu_s"].nunique() == 1).all()
    assert df.equals(df.sort_values(["case", "model", "seed", "run", "budget_s", "split",
                                     "step"]).reset_index(drop=True))
    assert (out / "figures" / "curves_rod_tiny_test.png").stat().st_size > 0
    assert "curves.csv" in (out / "README.md").read_text()
    err = capsys.readouterr().err
    assert "6 checkpoint(s) evaluated, 0 unchanged" in err


def test_meshbench_curves_resumes_without_recomputing(curve_runs, capsys):
    from benchmarks.cli import main

    root, args = curve_runs
    assert main(args) == 0
    csv_path = root / "results" / "curves_test" / "curves.csv"
    before = csv_path.read_bytes()
    capsys.readouterr()
    assert main(args) == 0
    assert "0 checkpoint(s) evaluated, 6 unchanged" in capsys.readouterr().err
    assert csv_path.read_bytes() == before
    # a changed checkpoint is evaluated again, alone
    run = root / "runs" / "rod_tiny_test-mgn-smoke-curves-s0"
    budget_checkpoint(run, 1).write_bytes(budget_checkpoint(run, 3).read_bytes())
    assert main(args) == 0
    assert "1 checkpoint(s) evaluated, 5 unchanged" in capsys.readouterr().err
    df = pd.read_csv(csv_path)
    mgn = df[df["model"] == "mgn"].set_index(["budget_s", "split", "step"])["rmse"]
    assert mgn.loc[1].equals(mgn.loc[3])


def test_meshbench_curves_bad_input_exits_2(curve_runs, tmp_path, capsys):
    from benchmarks.cli import main

    root, args = curve_runs
    assert main(["curves", "--suite", "nope", "--runs-dir", str(root / "runs")]) == 2
    assert "'nope'" in capsys.readouterr().err
    assert main(["curves", "--suite", "curves_test", "--runs-dir", str(tmp_path),
                 "--results", str(tmp_path / "r")]) == 2
    assert "no budget checkpoints" in capsys.readouterr().err
    run = tmp_path / "runs" / "rod_tiny_test-mgn-smoke-curves-s0"
    run.mkdir(parents=True)
    (run / "budgets.csv").write_text("a,b\n1,2\n")
    assert main(["curves", "--suite", "curves_test", "--runs-dir", str(tmp_path / "runs"),
                 "--results", str(tmp_path / "r")]) == 2
    assert "budgets.csv: not a budgets file" in capsys.readouterr().err


def test_meshbench_curves_keeps_provenance_and_other_sessions_rows(curve_runs, tmp_path,
                                                                   capsys):
    """Each run's provenance lands beside the table; a later session that has only some of
    the run directories (another machine) adds to the table without dropping the others."""
    import shutil

    from benchmarks.cli import main

    root, args = curve_runs
    assert main(args) == 0
    out = root / "results" / "curves_test"
    mgn, ode = "rod_tiny_test-mgn-smoke-curves-s0", "rod_tiny_test-meshodenet-smoke-curves-s0"
    for run in (mgn, ode):
        prov = out / "runs" / run
        for name in ("config.json", "budgets.csv", "history.csv", "sessions.json",
                     "record.json"):
            assert (prov / name).read_bytes() == (root / "runs" / run / name).read_bytes()
        assert "torch" in json.loads((prov / "evaluation.json").read_text())["versions"]
    # the next session: the committed results, and only MGN's run directory
    results, runs = tmp_path / "results", tmp_path / "runs"
    shutil.copytree(root / "results", results)
    shutil.copytree(root / "runs" / mgn, runs / mgn)
    before = pd.read_csv(results / "curves_test" / "curves.csv")
    capsys.readouterr()
    assert main(args[:3] + ["--results", str(results), "--runs-dir", str(runs)]
                + args[7:]) == 0
    err = capsys.readouterr().err
    assert f"{ode}: no budget checkpoints yet" in err and "0 checkpoint(s) evaluated" in err
    after = pd.read_csv(results / "curves_test" / "curves.csv")
    assert after.equals(before) and set(after["model"]) == {"meshodenet", "mgn"}
    assert (results / "curves_test" / "runs" / ode / "config.json").exists()


def test_quick_points_are_the_short_end_of_the_curves(tmp_path):
    """``quick_points``: per run the mean over test trajectories, then mean and std over
    seeds, at the seeds' median training wall time; the solver row (no training) left out."""
    from benchmarks.suite.curves import ALL_STEPS, curve_figure, quick_points

    assert quick_points(tmp_path).empty  # no quick results: nothing to draw
    runs = pd.DataFrame({"run": ["a0", "a1", "a2", "s0"], "case": ["c"] * 4,
                         "model": ["m", "m", "m", "solver_h"], "seed": [0, 1, 2, 0],
                         "train_wall_time_s": [100.0, 300.0, 200.0, 0.0]})
    rows = []
    for run, base in (("a0", 1.0), ("a1", 2.0), ("a2", 3.0), ("s0", 9.0)):
        for traj, extra in ((0, 0.0), (1, 2.0)):  # per-run mean over trajectories: base + 1
            rows += [{"run": run, "metric": "rmse_at_step", "trajectory": traj, "step": 5,
                      "rmse": base + extra},
                     {"run": run, "metric": "full_rollout_rmse", "trajectory": traj,
                      "step": 10, "rmse": 10 * (base + extra)},
                     {"run": run, "metric": "horizon_shape_rmse", "trajectory": traj,
                      "step": 50, "rmse": 1e9}]
    runs.to_csv(tmp_path / "runs.csv", index=False)
    pd.DataFrame(rows).to_csv(tmp_path / "metrics.csv", index=False)
    q = quick_points(tmp_path).set_index("step")
    assert list(q["model"]) == ["m", "m"] and sorted(q.index) == [ALL_STEPS, 5]
    assert q.loc[5, "x_s"] == 200.0 and q.loc[5, "n_seeds"] == 3
    assert q.loc[5, "rmse_mean"] == pytest.approx(3.0) and q.loc[5, "rmse_std"] == 1.0
    assert q.loc[ALL_STEPS, "rmse_mean"] == pytest.approx(30.0)
    curve = pd.DataFrame({"run": "r", "case": "c", "model": "m", "seed": 0,
                          "budget_s": [120, 300] * 2, "cpu_s": [130.0, 310.0] * 2,
                          "split": "test", "step": [5, 5, ALL_STEPS, ALL_STEPS],
                          "rmse": [2.0, 1.0, 20.0, 10.0]})
    path = curve_figure(curve, "c", {5: 4.0, ALL_STEPS: 40.0}, tmp_path / "f.png",
                        quick_points(tmp_path))
    assert path.stat().st_size > 0


def test_budget_ticks_name_seconds_and_minutes_or_hours():
    from benchmarks.suite.curves import _budget_label

    assert _budget_label(120) == "120 s\n2 min"
    assert _budget_label(2700) == "2700 s\n45 min"
    assert _budget_label(7200) == "7200 s\n2 h"
