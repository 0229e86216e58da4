"""The ``scale`` suite: the quick runs rolled out on meshes finer than their training mesh
(``benchmarks.suite.transfer``), and ``meshbench generate --split test`` (the test split of a
refined case alone)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from groundtruth import store


def test_the_scale_suite_is_quicks_runs_at_three_resolutions():
    from benchmarks.suite.suites import get_suite

    scale, quick = get_suite("scale"), get_suite("quick")
    assert [r.run_id for r in scale.runs()] == [r.run_id for r in quick.runs(3)]
    assert scale.seeds == 3 and scale.resolutions == (1, 2, 4)
    assert quick.resolutions == () and quick.seeds == 1  # the main job is unchanged
    assert "plate_cantilever-implicit_energy-quick-s2" in {r.run_id for r in scale.runs()}


def test_a_suite_refuses_a_bad_resolution():
    from benchmarks.suite.suites import RunSpec, Suite

    with pytest.raises(ValueError, match="resolutions of 'bad'.*got 0"):
        Suite("bad", "", (RunSpec("rod_falling", "mgn"),), resolutions=(1, 0))


def test_generate_makes_the_test_split_alone_and_keeps_it(tiny_case):
    """``splits=("test",)`` writes test.npz and a meta.json listing it alone; a later full
    generation makes the training split only and keeps the test file byte for byte; the test
    trajectories are those a full generation makes."""
    from benchmarks.suite.generate import generate
    from benchmarks.suite.registry import get_case

    case, root = tiny_case
    fine = get_case(f"{case.id}@r2")
    d = root / fine.id
    rep = generate(fine, root, workers=1, progress=False, splits=("test",))
    assert not rep.reused and rep.n_trajectories == fine.n_test
    assert (d / "test.npz").exists() and not (d / "train.npz").exists()
    meta = store.read_meta(d)
    assert list(meta["splits"]) == ["test"] and meta["case_hash"] == fine.hash()
    assert generate(fine, root, workers=1, progress=False, splits=("test",)).reused
    sha = store.sha256_file(d / "test.npz")
    rep = generate(fine, root, workers=1, progress=False)  # both: the training split is made
    assert not rep.reused and rep.n_trajectories == fine.n_train
    assert store.sha256_file(d / "test.npz") == sha
    assert sorted(store.read_meta(d)["splits"]) == ["test", "train"]
    assert generate(fine, root, workers=1, progress=False).reused
    other = root / "again"
    generate(fine, other, workers=1, progress=False)  # both at once: the same test split
    assert store.sha256_file(other / fine.id / "test.npz") == sha


def test_cli_generate_split(tmp_path, capsys):
    from benchmarks.cli import main

    with pytest.raises(SystemExit) as e:
        main(["generate", "rod_falling@r2", "--split", "val", "--data-dir", str(tmp_path)])
    assert e.value.code == 2 and "invalid choice: 'val'" in capsys.readouterr().err


@pytest.fixture(scope="module")
def transfer(tiny_case, tmp_path_factory):
    """A two-run suite (Implicit-Energy and MGN, smoke preset) on the tiny rod, rolled out at
    r = 1 and 2."""
    from benchmarks.suite.runner import run_suite
    from benchmarks.suite.suites import RunSpec, Suite

    case, root = tiny_case
    suite = Suite("tiny_scale", "the tiny rod at r = 1, 2",
                  (RunSpec(case.id, "implicit_energy", "smoke"), RunSpec(case.id, "mgn", "smoke")),
                  resolutions=(1, 2))
    tmp = tmp_path_factory.mktemp("scale")
    plugin = tmp / "tiny.py"  # the workers' registry: the fixture's case
    plugin.write_text("from benchmarks.suite.registry import register_case\n"
                      "from groundtruth.cases import RodCase\n"
                      "register_case(RodCase(id='rod_tiny_test', n_train=4, n_test=2, "
                      "t_end=0.5), overwrite=True)\n")
    kw = dict(results_dir=tmp / "results", runs_dir=tmp / "runs", data_dir=root,
              progress=False, device="cpu", plugin_files=(str(plugin),))
    res = run_suite(suite, **kw)
    return suite, case, root, tmp, kw, res


def test_transfer_writes_the_tables(transfer):
    suite, case, root, tmp, kw, res = transfer
    out = tmp / "results" / suite.name
    t = out / "transfer"
    assert res["paths"]["rmse_at_step"] == t / "rmse_at_step.csv"
    assert sorted(p.name for p in out.iterdir()) == ["transfer"]  # beside others' files
    table = pd.read_csv(t / "rmse_at_step.csv")
    quick_cols = pd.read_csv(Path(__file__).parents[1] / "results" / "quick" / "rmse_at_step.csv",
                             nrows=1).columns
    assert list(table.columns) == (["case", "r", "nodes"] + [c for c in quick_cols if c != "case"]
                                   + ["no_motion_rmse_mean", "vs_no_motion"])
    assert set(zip(table["case"], table["r"], table["nodes"])) == {
        (case.id, 1, 21), (f"{case.id}@r2", 2, 41)}
    assert set(table["model"]) == {"implicit_energy", "mgn"}
    assert np.allclose(table["vs_no_motion"], table["rmse_mean"] / table["no_motion_rmse_mean"])
    assert (table["no_motion_rmse_mean"] > 0).all() and table["rmse_mean"].notna().all()
    # r = 1 is the run's own test rollout (metrics.csv: 6 significant digits)
    metrics = pd.read_csv(t / "metrics.csv")
    run = "rod_tiny_test-mgn-smoke-s0"
    own = pd.read_csv(tmp / "runs" / run / "test_metrics.csv")
    own = own[own["metric"] == "rmse_at_step"]
    mine = metrics[(metrics["run"] == run) & (metrics["r"] == 1)
                   & (metrics["metric"] == "rmse_at_step")]
    assert np.allclose(mine["rmse"].to_numpy(), own["rmse"].to_numpy(), rtol=1e-5, atol=0)
    runs = pd.read_csv(t / "runs.csv")
    assert len(runs) == 4 and set(runs["r"]) == {1, 2}
    assert {"git_sha", "host", "cpu_model", "version_torch", "rollout_wall_time_s",
            "checkpoint_sha256", "train_git_sha", "train_wall_time_s"} <= set(runs.columns)
    assert (t / "figures" / f"transfer_{case.id}.png").stat().st_size > 0
    md = (t / "rmse_at_step.md").read_text()
    assert "r = 2 (41 nodes)" in md and "implicit_energy" in md
    assert "vs_no_motion" in (t / "README.md").read_text()


def test_transfer_rollouts_are_reused_until_the_checkpoint_changes(transfer):
    from benchmarks.suite.runner import run_suite

    suite, case, root, tmp, kw, res = transfer
    run_dir = tmp / "runs" / "rod_tiny_test-mgn-smoke-s0"
    stored = run_dir / "transfer" / f"{case.id}@r2.json"
    first = json.loads(stored.read_text())
    again = run_suite(suite, **kw)
    runs = pd.read_csv(again["paths"]["runs"])
    assert runs.loc[runs["r"] == 2, "reused"].all()
    assert json.loads(stored.read_text()) == first
    rec = json.loads(stored.read_text())
    stored.write_text(json.dumps({**rec, "checkpoint_sha256": "0" * 64}))  # another checkpoint
    from benchmarks.suite.transfer import transfer_one

    record = json.loads((run_dir / "record.json").read_text())
    row = transfer_one(record, str(run_dir), 2, str(root), 1, kw["plugin_files"], "cpu")
    assert row["reused"] is False and row["checkpoint_sha256"] == first["checkpoint_sha256"]


def test_tables_only_writes_the_stored_rollouts_and_names_the_others(transfer, tmp_path):
    """``meshbench run --tables-only`` of a suite with resolutions: nothing rolled out, the
    rollouts not stored yet left out and named."""
    from benchmarks.suite.transfer import stored_paths, tables_from_stored

    suite, case, root, tmp, kw, res = transfer
    for p in stored_paths(tmp / "runs" / "rod_tiny_test-mgn-smoke-s0", f"{case.id}@r2"):
        p.unlink()
    paths = tables_from_stored(suite, tmp_path, tmp / "runs", data_dir=root, figures=False)
    table = pd.read_csv(paths["rmse_at_step"])
    assert set(zip(table["model"], table["r"])) == {("mgn", 1), ("implicit_energy", 1),
                                                    ("implicit_energy", 2)}
    md = paths["markdown"].read_text()
    assert "**Incomplete**: 1 rollout(s)" in md and "rod_tiny_test-mgn-smoke-s0 at r = 2" in md
    assert not stored_paths(tmp / "runs" / "rod_tiny_test-mgn-smoke-s0", f"{case.id}@r2")[0].exists()
