"""meshbench compare: identical, perturbed and broken files; plugins."""

import textwrap

import numpy as np
import pandas as pd
import pytest

from benchmarks.cli import main


@pytest.fixture
def metrics(tmp_path):
    rng = np.random.default_rng(0)
    rows = [{"case": c, "model": m, "seed": 0, "trajectory": t, "step": s,
             "rmse": rng.uniform(1e-4, 1e-2), "wall_time_s": rng.uniform(1, 9)}
            for c in ("rod_falling", "plate_cantilever") for m in ("meshodenet", "mgn")
            for t in range(3) for s in (1, 30, 60)]
    df = pd.DataFrame(rows)
    path = tmp_path / "base.csv"
    df.to_csv(path, index=False, float_format="%.6e")
    return df, path


def write(df, path):
    df.to_csv(path, index=False, float_format="%.6e")
    return str(path)


def test_identical_files_pass(metrics, tmp_path, capsys):
    df, base = metrics
    other = df.copy()
    other["wall_time_s"] *= 3           # provenance columns are ignored by default
    other = other.sample(frac=1, random_state=1)   # row order does not matter
    assert main(["compare", str(base), write(other, tmp_path / "n.csv")]) == 0
    out = capsys.readouterr().out
    assert "OK" in out and "ignored ['wall_time_s']" in out


def test_perturbed_value_is_a_regression(metrics, tmp_path, capsys):
    df, base = metrics
    new = df.copy()
    new.loc[5, "rmse"] *= 1.02
    assert main(["compare", str(base), write(new, tmp_path / "n.csv"), "--rtol", "0.01"]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION: 1 values" in out and "rmse" in out and "0.02" in out
    assert main(["compare", str(base), str(tmp_path / "n.csv"), "--rtol", "0.05"]) == 0


@pytest.mark.parametrize("breakage,message", [
    (lambda d: d.drop(columns="rmse"), "missing from"),
    (lambda d: pd.concat([d, d.iloc[:1]]), "duplicate keys"),
    (lambda d: d.iloc[1:], "present in one file only"),
])
def test_broken_files_exit_2(metrics, tmp_path, capsys, breakage, message):
    df, base = metrics
    assert main(["compare", str(base), write(breakage(df), tmp_path / "n.csv")]) == 2
    assert message in capsys.readouterr().err


def test_subset_reports_rows_of_a_metric_the_baseline_lacks(metrics, tmp_path, capsys):
    df, _ = metrics
    df = df.assign(metric="rmse_at_step")
    base = write(df, tmp_path / "b.csv")
    added = df[df["step"] == 1].iloc[:4].assign(metric="horizon_shape_rmse", step=900)
    new = write(pd.concat([df, added]), tmp_path / "n.csv")
    assert main(["compare", base, new]) == 2  # without --subset: rows in one file only
    assert main(["compare", base, new, "--subset"]) == 0
    assert "not compared: 4 rows of metrics the baseline has no row of" in capsys.readouterr().out
    # a known metric's extra row is still an error, and the old rows still compared
    extra = df.iloc[:1].assign(step=999)
    assert main(["compare", base, write(pd.concat([df, added, extra]), tmp_path / "x.csv"),
                 "--subset"]) == 2
    moved = df.copy()
    moved.loc[0, "rmse"] *= 2
    assert main(["compare", base, write(pd.concat([moved, added]), tmp_path / "m.csv"),
                 "--subset"]) == 1


def test_unreadable_file_exits_2(metrics, tmp_path, capsys):
    _, base = metrics
    (tmp_path / "bad.csv").write_bytes(b"\xff\xfe\x00garbage")
    assert main(["compare", str(base), str(tmp_path / "bad.csv")]) == 2
    assert main(["compare", str(base), str(tmp_path / "absent.csv")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_plugin_case_registered_from_a_file_generates(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("MESHBENCH_DATA", raising=False)  # the data must land in ./data
    plugin = tmp_path / "mycases.py"
    plugin.write_text(textwrap.dedent("""
        from benchmarks.suite.registry import register_case
        from groundtruth.cases import RodCase
        register_case(RodCase(id="rod_plugin", n_nodes=6, length=0.2, t_end=0.2,
                              n_train=2, n_test=1), overwrite=True)
    """))
    from benchmarks.suite import registry

    monkeypatch.setattr(registry, "CASES", dict(registry.CASES))
    monkeypatch.chdir(tmp_path)
    assert main(["--plugin", str(plugin), "generate", "rod_plugin", "--workers", "2",
                 "--no-progress"]) == 0
    assert (tmp_path / "data" / "rod_plugin" / "meta.json").exists()
    monkeypatch.setenv("MESHBENCH_PLUGINS", str(plugin))
    assert main(["generate", "--list"]) == 0
    assert "rod_plugin" in capsys.readouterr().out


def test_missing_plugin_file_is_a_clear_error(capsys):
    assert main(["--plugin", "nope/absent.py", "generate", "--list"]) == 2
    assert "absent.py" in capsys.readouterr().err
