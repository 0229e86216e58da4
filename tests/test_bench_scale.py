"""``meshbench bench scale``: a tiny run's CSV shape, resuming, the exponent fit and the
crossover on synthetic power laws, and the bad-input errors. No timed assertions."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from benchmarks.cli import main
from benchmarks.cost import scalebench as sb
from benchmarks.cost.scalereport import crossover

TINY = ["bench", "scale", "--cases", "rod_falling", "--r", "1,2", "--steps", "1", "--rounds",
        "1", "--methods", "groundtruth,solver_h,meshodenet", "--grad-modes", "direct",
        "--window", "2", "--train-trajectories", "2", "--memory-wait", "0"]


def test_tiny_run_writes_tidy_csv_and_resumes(tmp_path, capsys):
    out = tmp_path / "scale"
    assert main(TINY + ["--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rod_falling@r2 (41 nodes): timing" in text and "wrote" in text
    df = pd.read_csv(out / "scale.csv")
    assert list(df.columns) == sb.COLUMNS + sb.PROVENANCE
    assert set(df["r"]) == {1, 2} and set(df["case"]) == {"rod_falling"}
    assert dict(zip(df["r"], df["nodes"])) == {1: 21, 2: 41}
    # one row per case x r x method x variant x quantity
    key = ["case", "r", "method", "variant", "quantity"]
    assert not df.duplicated(key).any()
    for r in (1, 2):
        sub = df[df["r"] == r]
        got = set(zip(sub["method"], sub["variant"], sub["quantity"]))
        for want in [("groundtruth", "auto", "step_cpu_s"),
                     ("groundtruth", "banded", "step_cpu_s"),
                     ("groundtruth", "auto", "newton_iterations_per_step"),
                     ("groundtruth", "banded", "first_solve_cpu_s"),
                     ("groundtruth", "auto", "cost_per_sim_s"),
                     ("solver_h", "backward_euler", "rollout_interval_s"),
                     ("meshodenet", "quick", "rollout_interval_s"),
                     ("meshodenet", "direct", "train_step_s"),
                     ("meshodenet", "direct", "peak_rss_gb"),
                     ("meshodenet", "direct", "fits_memory_cap")]:
            assert want in got, (r, want)
        step = sub[(sub["method"] == "groundtruth") & (sub["quantity"] == "step_cpu_s")]
        assert (step["value"] > 0).all()
        assert (sub[sub["quantity"] == "peak_rss_gb"]["value"] > 0).all()
    assert (df["threads"] == 1).all() and (df["device"] == "cpu").all()
    assert df["git_sha"].astype(str).str.len().min() >= 7
    fits = pd.read_csv(out / "fits.csv")
    assert {"exponent", "crossover_10x"} <= set(fits["kind"])
    assert (out / "scale.png").stat().st_size > 0
    # --resume: everything is there, nothing is measured again, the rows stay
    assert main(TINY + ["--out", str(out), "--resume"]) == 0
    assert "timing" not in capsys.readouterr().out.split("wrote")[0].replace(
        "meshbench bench scale", "")
    again = pd.read_csv(out / "scale.csv")
    pd.testing.assert_frame_equal(again[sb.COLUMNS], df[sb.COLUMNS])


def test_fit_power_recovers_a_synthetic_power_law():
    n = np.array([182, 643, 2405, 9289, 36497, 103168])
    p, c = sb.fit_power(n, 3e-5 * n ** 1.37)
    assert p == pytest.approx(1.37, abs=1e-12) and c == pytest.approx(3e-5, rel=1e-10)
    noisy = 2.0 * n ** 1.1 * np.exp(0.01 * np.sin(n))
    assert sb.fit_power(n, noisy)[0] == pytest.approx(1.1, abs=0.02)


def test_crossover_measured_and_predicted():
    n = [100, 1000, 10000]
    gt = {k: 1e-4 * k ** 1.5 for k in n}
    # measured: ratio gt/learner = k / 100 crosses 10 at k = 1000 exactly
    learner = {k: 1e-2 * k ** 0.5 for k in n}
    rec = crossover("c", "m", gt, learner)
    assert rec["range"] == "measured" and rec["value"] == pytest.approx(1000)
    # predicted: ratio = k / 1e5 reaches 10 at k = 1e6, beyond the sizes measured
    learner = {k: 10.0 * k ** 0.5 for k in n}
    rec = crossover("c", "m", gt, learner)
    assert rec["range"] == "predicted" and rec["value"] == pytest.approx(1e6, rel=1e-9)
    assert "not reached up to 10000 nodes" in rec["note"]
    # a learner that grows as fast as the ground truth never gets there
    learner = {k: 1.0 * k ** 1.5 for k in n}
    rec = crossover("c", "m", gt, learner)
    assert rec["range"] == "not reached" and math.isnan(rec["value"])
    assert "never" in rec["note"]


@pytest.mark.parametrize("extra, message", [
    (["--r", "0"], "--r: each resolution must be a positive integer, got '0'"),
    (["--r", "2,x"], "--r: each resolution must be a positive integer, got 'x'"),
    (["--cases", "rod_nope"], "--cases: unknown case 'rod_nope'"),
    (["--methods", "meshodenet,gnn"], "--methods: unknown method 'gnn'"),
    (["--steps", "0"], "--steps must be an integer >= 1, got 0"),
    (["--max-memory-gb", "0"], "--max-memory-gb must be a positive number, got 0.0"),
    (["--grad-modes", "backprop"], "--grad-modes: unknown gradient mode 'backprop'"),
    (["--preset", "huge"], "unknown preset 'huge'"),
    (["--device", "tpu"], "tpu"),
])
def test_bad_input_exits_2_naming_the_field(extra, message, tmp_path, capsys):
    assert main(["bench", "scale", "--out", str(tmp_path / "s")] + extra) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s").exists()
