"""The training engine and the train/rollout/bench commands: overfitting, exact resume,
validation split, clear errors, and an end-to-end run on a tiny generated case."""

import csv
import dataclasses
import json
import time

import numpy as np
import pytest
import torch

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.mesh.data import Mesh, Trajectories, split_indices, stratified_split, validation_split
from meshodenet.training.train import TrainConfig, fit, load_checkpoint, make_optimizer, train_epoch
from tests.conftest import rod_arrays, strip_arrays

torch.set_num_threads(1)  # tiny graphs: threads only add overhead


def _overfit(arrays, max_seconds=60.0):
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), MeshODENetConfig(hidden=32), data)
    cfg = TrainConfig(lr=3e-3, weight_decay=0.0, lr_milestones=(), batch_size=1)
    opt, _ = make_optimizer(model, cfg)
    gen = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    first = train_epoch(model, opt, data, cfg, gen)[0]
    loss = first
    while loss > first / 100 and time.perf_counter() - t0 < max_seconds:
        loss = train_epoch(model, opt, data, cfg, gen)[0]
    return first, loss, time.perf_counter() - t0


def test_overfits_one_short_trajectory_in_under_a_minute():
    first, last, seconds = _overfit(rod_arrays(B=1, T=11))
    assert last < first / 100, (first, last, seconds)


@pytest.mark.slow
def test_overfits_one_short_plate_trajectory():
    first, last, seconds = _overfit(strip_arrays(B=1, T=11), max_seconds=120)
    assert last < first / 100, (first, last, seconds)


def _fit_setup(arrays):
    data = Trajectories.from_arrays(arrays)
    tr, val = split_indices(len(data), 0.25, 0)
    train, valid = data.subset(torch.as_tensor(tr)), data.subset(torch.as_tensor(val))
    cfg = TrainConfig(epochs=3, lr=1e-3, lr_milestones=(2,), batch_size=2, val_fraction=0.25,
                      seed=7)
    mcfg = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, shooting=2, shooting_epochs=2)
    torch.manual_seed(cfg.seed)
    model = MeshODENet(Mesh.from_arrays(arrays), mcfg, train)
    return model, train, valid, cfg


def test_skipped_validations_leave_training_unchanged(tmp_path):
    """``val_every = k`` validates every k-th epoch and the last one, and nothing else changes:
    the weights after each epoch are those of validating every epoch (validation draws no
    random numbers and leaves the model in no other state), and only a validated epoch can be
    the best. This is what lets a preset skip validations its seeds never selected and keep
    its results bit for bit."""
    arrays = rod_arrays(B=4, T=6)
    model, train, valid, cfg = _fit_setup(arrays)
    every = fit(model, train, valid, dataclasses.replace(cfg, epochs=5), tmp_path / "a",
                progress=False)
    model, train, valid, cfg = _fit_setup(arrays)
    sparse = fit(model, train, valid, dataclasses.replace(cfg, epochs=5, val_every=2),
                 tmp_path / "b", progress=False)
    a, b = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(tmp_path / "b" / "last.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert [r["train_loss"] for r in a["history"]] == [r["train_loss"] for r in b["history"]]
    validated = [r["epoch"] for r in b["history"] if not np.isnan(r["val_rmse"])]
    assert validated == [2, 4, 5]
    assert [r["val_rmse"] for r in b["history"] if r["epoch"] in validated] == \
        [r["val_rmse"] for r in a["history"] if r["epoch"] in validated]
    assert sparse.best_epoch in validated
    if every.best_epoch in validated:
        assert sparse.best_epoch == every.best_epoch


def test_a_window_whose_implicit_solve_fails_is_a_skipped_step(monkeypatch):
    """``NewtonError`` in a training window skips that step (counted) and the others train;
    in validation it scores inf, so that epoch is never selected."""
    from meshodenet.integrators.implicit import NewtonError
    from meshodenet.training.train import validate

    model, train, valid, cfg = _fit_setup(rod_arrays(B=4, T=6))
    real, calls = model.training_loss, []

    def flaky(data, idx, gen):
        calls.append(1)
        if len(calls) == 1:
            raise NewtonError("backward_euler: Newton did not converge")
        return real(data, idx, gen)

    monkeypatch.setattr(model, "training_loss", flaky)
    opt, _ = make_optimizer(model, cfg)
    before = [p.detach().clone() for p in model.parameters()]
    loss, skipped = train_epoch(model, opt, train, cfg, torch.Generator().manual_seed(0))
    assert skipped == 1 and len(calls) >= 2 and np.isfinite(loss)
    assert any(not torch.equal(a, p) for a, p in zip(before, model.parameters()))

    def no_root(*a, **k):
        raise NewtonError("no root")

    monkeypatch.setattr(model, "rollout_all", no_root)
    assert validate(model, valid, cfg) == float("inf")


class _Interrupt(Exception):
    pass


def test_interrupt_and_resume_equals_uninterrupted(tmp_path):
    arrays = rod_arrays(B=4, T=6)
    model, train, valid, cfg = _fit_setup(arrays)
    fit(model, train, valid, cfg, tmp_path / "a", progress=False)

    model, train, valid, cfg = _fit_setup(arrays)

    def stop(epoch, row):
        if epoch == 1:
            raise _Interrupt

    with pytest.raises(_Interrupt):
        fit(model, train, valid, cfg, tmp_path / "b", progress=False, on_epoch_end=stop)
    model, train, valid, cfg = _fit_setup(arrays)  # a fresh process would rebuild everything
    fit(model, train, valid, cfg, tmp_path / "b", resume=True, progress=False)

    a, b = load_checkpoint(tmp_path / "a" / "last.pt"), load_checkpoint(tmp_path / "b" / "last.pt")
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert torch.equal(a["generator"], b["generator"])
    assert a["epoch"] == b["epoch"] == 3 and a["best_epoch"] == b["best_epoch"]
    keep = ("epoch", "train_loss", "val_rmse", "best_val_rmse", "lr")
    assert [{k: r[k] for k in keep} for r in a["history"]] == \
        [{k: r[k] for k in keep} for r in b["history"]]
    rows = list(csv.DictReader(open(tmp_path / "b" / "history.csv")))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3]
    assert (tmp_path / "b" / "best.pt").exists()


def test_shooting_horizon_doubles_to_whole_rollouts():
    arrays = rod_arrays(B=3, T=201)
    data = Trajectories.from_arrays(arrays)
    cfg = MeshODENetConfig(hidden=8, shooting=10, shooting_epochs=2)
    model = MeshODENet(Mesh.from_arrays(arrays), cfg)
    plan = []
    for epoch in range(12):
        model.start_epoch(epoch)
        plan.append((model.horizon(200), model.n_training_samples(data)))
    assert plan[::2] == [(10, 60), (20, 30), (40, 15), (80, 6), (160, 3), (200, 3)]
    model.config = dataclasses.replace(cfg, shooting_epochs=0)
    assert model.horizon(200) == 10
    model.config = dataclasses.replace(cfg, shooting=0)
    assert model.horizon(200) == 200 and model.n_training_samples(data) == 3


def test_no_motion_scores_one():
    """The loss is normalised by the no-motion prediction's."""
    arrays = rod_arrays(B=2, T=21)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    model = MeshODENet(Mesh.from_arrays(arrays), MeshODENetConfig(hidden=8), data).double()
    for layer in (model.gnn.decoder[-1],):  # zero acceleration: x(t) = x(0) + v(0) t
        torch.nn.init.zeros_(layer.weight)
        torch.nn.init.zeros_(layer.bias)
    model.stats.acc.mean.zero_()
    still = {**arrays, "vel": np.zeros_like(arrays["vel"])}  # v(0) = 0: nothing moves
    data0 = Trajectories.from_arrays(still, dtype=torch.float64)
    loss = model.training_loss(data0, torch.arange(2), torch.Generator().manual_seed(0))
    assert abs(loss.item() - 1.0) < 1e-12


def test_validation_split_is_fixed_and_disjoint():
    tr, val = split_indices(71, 0.1, 0)
    tr2, val2 = split_indices(71, 0.1, 0)
    assert np.array_equal(val, val2) and len(val) == 7 and len(tr) == 64
    assert not set(tr) & set(val) and sorted(set(tr) | set(val)) == list(range(71))
    assert len(split_indices(2, 0.1, 0)[1]) == 1


def _widest_gap(y, val):
    """The widest gap the validation moduli leave, between each other or to the ends of the
    range of ``y``, and the allowed one: twice the range divided by their number."""
    v = np.sort(y[val])
    return np.diff(np.r_[y.min(), v, y.max()]).max(), 2 * (y.max() - y.min()) / len(v)


def test_stratified_split_spans_the_moduli():
    """Sorted by modulus, cut into strata of equal count, the middle of each: deterministic,
    disjoint, the extremes stay in training, and one stratum apart."""
    y = np.random.default_rng(3).uniform(1.0, 2.0, size=71)
    tr, val = stratified_split(y, 0.1)
    assert np.array_equal(val, stratified_split(y, 0.1)[1]) and len(val) == 7 and len(tr) == 64
    assert not set(tr) & set(val) and sorted(set(tr) | set(val)) == list(range(71))
    assert np.argmin(y) in tr and np.argmax(y) in tr
    ranks = np.argsort(np.argsort(y))[val]
    assert sorted(ranks.tolist()) == [5, 15, 25, 35, 45, 55, 65]
    gap, allowed = _widest_gap(y, val)
    assert gap <= allowed
    # every size: one trajectory at least, never all of them, none with val_fraction 0
    for n in range(2, 40):
        tr, val = stratified_split(np.arange(n, 0, -1.0), 0.1)
        assert len(val) == max(1, round(0.1 * n)) and len(tr) + len(val) == n
    assert len(stratified_split(np.ones(5), 0.0)[1]) == 0
    assert np.array_equal(validation_split(y, 0.1, "random", 4)[1], split_indices(71, 0.1, 4)[1])
    with pytest.raises(ValueError, match="val_split"):
        validation_split(y, 0.1, "kfold")


@pytest.mark.parametrize("case_id", ["rod_falling", "plate_cantilever", "plate_hanging",
                                     "rod_cantilever"])
def test_default_validation_split_leaves_no_gap_in_the_moduli(case_id):
    """The issue's target on every registered case's training moduli (drawn from the case's
    seed, no simulation needed): no gap between the validation moduli, or to the ends of the
    training range, wider than twice the range divided by their number."""
    from benchmarks.suite.registry import get_case

    y = get_case(case_id).sample_youngs("train")
    cfg = TrainConfig()
    assert cfg.val_split == "stratified"
    gap, allowed = _widest_gap(y, validation_split(y, cfg.val_fraction, cfg.val_split)[1])
    assert gap <= allowed


@pytest.mark.parametrize("field,value", [("epochs", 0), ("lr", -1.0), ("val_fraction", 1.0),
                                         ("val_split", "kfold"),
                                         ("lr_milestones", (3, 2)), ("batch_size", 1.5)])
def test_train_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value})


def test_presets_resolve_for_both_mesh_kinds():
    from meshodenet.gnn.meshodenet import meshodenet_presets
    from meshodenet.training.presets import PRESETS

    for kind in ("line", "triangle"):
        for preset in PRESETS:
            meshodenet_presets(preset, kind)
    rod, plate = meshodenet_presets("paper", "line")[0], meshodenet_presets("paper", "triangle")[0]
    assert (rod.epochs, rod.lr_milestones) == (400, (100, 200, 300))
    assert (plate.epochs, plate.lr_milestones) == (600, (200, 400))
    assert rod.lr == 1e-4 and rod.weight_decay == 5e-4
    with pytest.raises(ValueError, match="paper, quick, smoke"):
        meshodenet_presets("fast", "line")


def test_quick_plate_presets_train_without_weight_decay_and_rods_keep_it():
    """The paper's coupled weight decay (5e-4) held MeshODENet on the in-plane plate at
    almost no acceleration: same settings and seed, best validation RMSE 0.183 m with it and
    0.119 m without (no motion 0.1705 m; docs/HISTORY.md, "The in-plane plate"). The plate's
    ``quick`` presets of both models drop it; the rod's keep the paper's weight decay.
    MeshODENet validates its plate every epoch, MGN at epochs 3 and 6 of its 6 (every seed
    selected epoch 6, a validation costs a quarter of an epoch); the learning-curve runs
    validate every epoch whatever the preset."""
    from benchmarks.suite.suites import CURVE_OVERRIDES
    from meshodenet.gnn.meshodenet import meshodenet_presets
    from meshodenet.gnn.mgn import mgn_presets

    for presets in (meshodenet_presets, mgn_presets):
        plate, rod = presets("quick", "triangle")[0], presets("quick", "line")[0]
        assert plate.weight_decay == 0
        assert rod.weight_decay == 5e-4 and rod.val_every == 1
        assert presets("paper", "triangle")[0].weight_decay == 5e-4
    assert meshodenet_presets("quick", "triangle")[0].val_every == 1
    mgn_plate = mgn_presets("quick", "triangle")[0]
    assert (mgn_plate.val_every, mgn_plate.epochs) == (3, 6)
    assert "train.val_every=1" in CURVE_OVERRIDES


def test_quick_plate_preset_rolls_whole_trajectories_and_imex_keeps_its_windows():
    """MeshODENet learns the plate from whole rollouts from rest, one trajectory per
    step, with the release weighted apart (validation and test at the paper's steps:
    docs/HISTORY.md, "MeshODENet's plate from whole rollouts" and "The plate's quick run at a
    third of its cost"); 16-interval windows left it at 0.55-0.9x standing still.
    MeshODENet-IMEX's plate preset keeps the windows its committed results were trained with,
    for the 10 epochs that hold every seed's best (5-7; it diverged from epoch 9-10 on)."""
    from meshodenet.gnn.imex import imex_presets
    from meshodenet.gnn.meshodenet import meshodenet_presets

    tc, mc = meshodenet_presets("quick", "triangle")
    assert (mc.shooting, mc.hidden, mc.release_weight, mc.rest_position) == (0, 48, 0.05, True)
    assert (tc.epochs, tc.lr_milestones, tc.batch_size, tc.max_batches) == (5, (), 1, 24)
    assert meshodenet_presets("quick", "line")[1].release_weight == 0
    itc, imc = imex_presets("quick", "triangle")
    assert (imc.shooting, imc.hidden, imc.release_weight, imc.release_fraction) == (16, 32, 0, 0.05)
    assert (itc.epochs, itc.lr_milestones, itc.batch_size, itc.max_batches) == (10, (), 4, 24)


# --- end to end through the CLI on a tiny generated case ----------------------------------

def _cli(*argv):
    from benchmarks.cli import main

    return main([str(a) for a in argv])


def test_train_rollout_export_resume_end_to_end(tiny_case, tmp_path, capsys, monkeypatch):
    from groundtruth import store

    monkeypatch.chdir(tmp_path)  # meshio's XDMF writer puts its .h5 in the working directory

    case, root = tiny_case
    run = tmp_path / "run"
    common = ("--data-dir", root, "--threads", 1, "--no-progress")
    assert _cli("train", "--case", case.id, "--preset", "smoke", "--out", run, *common) == 0
    for f in ("config.json", "sessions.json", "last.pt", "best.pt", "history.csv",
              "test_metrics.json"):
        assert (run / f).exists(), f
    config = json.loads((run / "config.json").read_text())
    assert config["model"] == "meshodenet" and config["seeds"]["seed"] == 0
    assert sorted(config["split"]["train_idx"] + config["split"]["val_idx"]) == [0, 1, 2, 3]
    assert "torch" in json.loads((run / "sessions.json").read_text())[0]["versions"]

    # starting over in the same directory is refused; resuming with more epochs continues
    assert _cli("train", "--case", case.id, "--preset", "smoke", "--out", run, *common) == 2
    assert "--resume" in capsys.readouterr().err
    assert _cli("train", "--case", case.id, "--preset", "smoke", "--out", run, "--resume",
                "--epochs", 3, *common) == 0
    assert load_checkpoint(run / "last.pt")["epoch"] == 3
    assert _cli("train", "--case", case.id, "--preset", "smoke", "--out", run, "--resume",
                "--set", "model.hidden=8", *common) == 2
    assert "model_config.hidden" in capsys.readouterr().err

    out = tmp_path / "pred.npz"
    assert _cli("rollout", "--run", run, "--split", "test", "--out", out,
                "--data-dir", root, "--device", "cpu") == 0
    printed = capsys.readouterr().out
    metrics = json.loads(printed[:printed.rindex("}") + 1])
    assert metrics["rmse_m"] > 0 and metrics["no_motion_rmse_m"] > 0
    pred = store.load_npz(out)
    truth = store.load_split(case, "test", root)
    assert pred["pos"].shape == truth["pos"].shape and str(pred["model"]) == "meshodenet"
    np.testing.assert_allclose(pred["pos"][:, 0], truth["pos"][:, 0], rtol=0, atol=1e-8)
    assert _cli("export", "--file", out, "--out", tmp_path / "pred.xdmf") == 0


def test_rollout_on_a_file_from_another_rod_case(tiny_case, tmp_path, capsys):
    """A rod of another case (11 nodes, the run's has 21) is a mesh of the run's kind: the
    model rolls out on it (tests/test_transfer.py), and the metrics name both meshes."""
    from groundtruth import store

    case, root = tiny_case
    run = tmp_path / "run"
    assert _cli("train", "--case", case.id, "--preset", "smoke", "--out", run,
                "--data-dir", root, "--threads", 1, "--no-progress", "--epochs", 1) == 0
    other = dataclasses.replace(case, id="rod_other_test", n_nodes=11)
    f = tmp_path / "other.npz"
    q = other.rest_positions()[None, None]
    store.save_npz(f, store.trajectory_arrays(other, [0.0, 0.1], np.repeat(q, 2, 1),
                                              np.zeros((1, 2) + q.shape[2:]), [1e9], "single"))
    assert _cli("rollout", "--run", run, "--file", f, "--out", tmp_path / "x.npz") == 0
    out = capsys.readouterr().out
    assert '"trained_on": "case \'rod_tiny_test\'' in out
    assert '"rolled_out_on": "case \'rod_other_test\'' in out and "11 nodes" in out
    assert store.load_npz(tmp_path / "x.npz")["pos"].shape == (1, 2, 11, 3)


def test_unknown_model_and_preset_are_clear(tiny_case, tmp_path, capsys):
    case, root = tiny_case
    assert _cli("train", "--case", case.id, "--model", "gnn", "--out", tmp_path / "r",
                "--data-dir", root) == 2
    err = capsys.readouterr().err
    assert "unknown model id 'gnn'; valid ids: " in err and "meshodenet, " in err
    assert _cli("train", "--case", case.id, "--preset", "fast", "--out", tmp_path / "r",
                "--data-dir", root) == 2
    assert "paper, quick, smoke" in capsys.readouterr().err


def test_bench_train_prints_the_figures(capsys):
    assert _cli("bench", "train", "--trajectories", 2, "--frames", 4, "--hidden", 8,
                "--max-batches", 1, "--modes", "direct,checkpoint", "--threads", 1) == 0
    out = capsys.readouterr().out
    assert out.count("peak RSS") == 2 and "evals/s" in out and "epoch" in out
