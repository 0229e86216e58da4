"""Every committed results CSV is plain: bare ``pandas.read_csv`` loads it, no comment lines;
``meshbench compare`` still reads the old commented files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd

from benchmarks.suite.compare import read_csv
from benchmarks.suite.runner import strip_comments, write_csv, write_readme

ROOT = Path(__file__).resolve().parents[1]


def test_every_committed_results_csv_is_plain():
    files = sorted((ROOT / "results").rglob("*.csv"))
    assert len(files) >= 10
    for f in files:
        text = f.read_text()
        assert not any(line.startswith("#") for line in text.splitlines()), f
        df = pd.read_csv(f)
        assert len(df) and len(df.columns) > 1 and not any(
            str(c).startswith(("#", "Unnamed")) for c in df.columns), f
    for suite in ("quick", "integrators"):  # the sidecar describes them
        readme = (ROOT / "results" / suite / "README.md").read_text()
        assert "`rmse_at_step.csv`" in readme and "squared Euclidean position error" in readme


def test_write_csv_plain_with_sidecar_and_old_files_still_compare(tmp_path):
    df = pd.DataFrame({"case": ["a", "a"], "step": [1, 2], "rmse_mean": [0.1, 0.2]})
    write_csv(tmp_path / "rmse_at_step.csv", df, "rmse_at_step")
    assert pd.read_csv(tmp_path / "rmse_at_step.csv").equals(df)
    assert "`rmse_at_step.csv`" in (tmp_path / "README.md").read_text()
    old = tmp_path / "old" / "rmse_at_step.csv"
    old.parent.mkdir()
    old.write_text("# rmse_at_step.csv: a comment\n# more\n" + df.to_csv(index=False))
    assert read_csv(old).equals(df)  # the old commented format is still accepted
    r = subprocess.run([sys.executable, "-m", "benchmarks.cli", "compare", str(old),
                        str(tmp_path / "rmse_at_step.csv")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert strip_comments(old) == ["rmse_at_step.csv: a comment", "more"]
    assert pd.read_csv(old).equals(df)
    write_readme(old.parent)
    assert (old.parent / "README.md").exists()
