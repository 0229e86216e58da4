"""The meshbench command line, run in-process and as an installed console script."""

import subprocess
import sys

import numpy as np
import pytest

from benchmarks.cli import main
from groundtruth import store


def test_simulate_and_export_roundtrip(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "elsewhere").mkdir()
    out = tmp_path / "x.npz"
    assert main(["simulate", "rod_falling", "--youngs", "1e9", "--t-end", "1",
                 "--out", str(out), "--no-progress"]) == 0
    d = store.load_npz(out, "rod_falling")
    assert d["pos"].shape == (1, 11, 21, 3) and d["youngs"].tolist() == [1e9]
    assert str(d["split"]) == "single"
    assert "wrote 11 frames" in capsys.readouterr().out
    x = tmp_path / "elsewhere" / "x.xdmf"
    assert main(["export", "--file", str(out), "--out", str(x)]) == 0
    assert (tmp_path / "elsewhere" / "x.h5").exists() and not (tmp_path / "x.h5").exists()
    import meshio

    with meshio.xdmf.TimeSeriesReader(str(x)) as r:
        points, cells = r.read_points_cells()
        assert points.shape == (21, 3) and cells[0].type == "line"
        assert r.num_steps == 11
        t, pd, _ = r.read_data(10)
        np.testing.assert_allclose(pd["displacement"] + points, d["pos"][0, 10])


def test_generate_and_export_split(tmp_path, monkeypatch, capsys):
    from benchmarks.suite import registry
    from groundtruth.cases import RodCase

    monkeypatch.setitem(registry.CASES, "rod_tiny", RodCase(id="rod_tiny", n_nodes=5,
                                                            t_end=0.2, n_train=2, n_test=1))
    args = ["generate", "rod_tiny", "--data-dir", str(tmp_path), "--no-progress", "--workers", "1"]
    assert main(args) == 0
    assert "wrote 3 trajectories" in capsys.readouterr().out
    assert main(args) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(["export", "rod_tiny", "--data-dir", str(tmp_path), "--split", "test",
                 "--index", "0", "--out", str(tmp_path / "t.xdmf")]) == 0
    assert main(["export", "rod_tiny", "--data-dir", str(tmp_path), "--split", "test",
                 "--index", "5", "--out", str(tmp_path / "t.xdmf")]) == 2
    assert "--index must be in [0, 1)" in capsys.readouterr().err


@pytest.mark.parametrize("argv,message", [
    (["simulate", "rod_falling", "--youngs", "-1", "--out", "x.npz"], "youngs must be a positive"),
    (["simulate", "rod_falling", "--youngs", "nan", "--out", "x.npz"], "youngs must be a positive"),
    (["simulate", "nope", "--youngs", "1e9", "--out", "x.npz"], "unknown case id 'nope'"),
    (["simulate", "rod_falling", "--youngs", "1e9", "--static", "--out", "x.npz"], "no clamped"),
    (["simulate", "rod_falling", "--youngs", "1e9", "--out", "x.txt"], "--out must end in .npz"),
    (["generate"], "name at least one CASE"),
    (["generate", "rod_falling", "--workers", "0"], "--workers must be >= 1"),
])
def test_bad_input_exits_2_with_message(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_console_script_and_module_entry_point():
    r = subprocess.run([sys.executable, "-m", "benchmarks.cli", "generate", "--list"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "rod_falling" in r.stdout


def test_import_arrows():
    """groundtruth and the data commands never import torch (STYLE: imports flow one way)."""
    code = ("import sys, groundtruth.cases, groundtruth.store, benchmarks.cli, benchmarks.suite.generate;"
            "benchmarks.cli.build_parser();"
            "bad = [m for m in ('torch', 'meshodenet') if m in sys.modules];"
            "assert not bad, bad")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


def test_every_builtin_suite_is_listed_in_the_help_and_the_docs():
    from pathlib import Path

    from benchmarks.commands import run

    # a fresh interpreter: other tests register suites of their own
    builtin = subprocess.run([sys.executable, "-c", "from benchmarks.suite.suites import SUITES; "
                              "print(' '.join(SUITES))"], capture_output=True, text=True,
                             check=True).stdout.split()
    table = (Path(__file__).resolve().parents[1] / "docs" / "SUITE.md").read_text()
    assert "hanging" in builtin
    for name in builtin:
        assert f" {name}," in run.__doc__ and f"| `{name}`" in table, name
