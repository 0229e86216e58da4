"""The subdomain suites and their comparison (``benchmarks.suite.subdomain``) on small stand-in
tables: what is compared with what, and clear errors when a table is missing."""

import numpy as np
import pandas as pd
import pytest

from benchmarks.suite import subdomain
from benchmarks.suite.suites import get_suite

STEPS = (1, 25, 50)


def _tables(root, drop=None):
    still = {1: 1e-4, 25: 1e-2, 50: 3e-2}
    rows = {"subdomain": 0.01, "subdomain_whole": 0.02, "subdomain_transfer": 0.07}
    for sub, ratio in rows.items():
        seeds = (0,) if sub == "subdomain_whole" else (0, 1, 2)
        t = pd.DataFrame([{"case": "plate_cantilever_few@r8", "model": "implicit_energy",
                           "seed": s, "step": k, "rmse_mean": ratio * still[k] * (1 + s / 10)}
                          for s in seeds for k in STEPS])
        runs = pd.DataFrame([{"seed": s, "train_wall_time_s": 100.0 + s,
                              "peak_rss_mb": 1000.0} for s in seeds])
        d = root / sub
        if sub == "subdomain_transfer":
            t = pd.concat([t.assign(r=1, no_motion_rmse_mean=np.nan),
                           t.assign(r=8, case="plate_cantilever@r8",
                                    no_motion_rmse_mean=t["step"].map(still))])
            d = d / "transfer"
        if sub == drop:
            continue
        d.mkdir(parents=True)
        t.to_csv(d / "rmse_at_step.csv", index=False)
        runs.to_csv(d / "runs.csv", index=False)


def test_comparison_reads_the_three_suites(tmp_path):
    _tables(tmp_path)
    paths = subdomain.write(tmp_path)
    table = pd.read_csv(paths["csv"])
    assert set(table["training"]) == {"patches", "whole mesh", "paper mesh, transferred"}
    assert (table.groupby("training")["seed"].nunique().to_dict()
            == {"patches": 3, "whole mesh": 1, "paper mesh, transferred": 3})
    s0 = table[(table["seed"] == 0) & (table["training"] == "patches")]
    np.testing.assert_allclose(s0["vs_no_motion"], 0.01)
    assert table.loc[table["training"] == "paper mesh, transferred", "train_wall_time_s"] \
        .isna().all()  # trained on another mesh: its cost is the quick suite's
    md = paths["markdown"].read_text()
    assert "| patches | 3 | 0.011 (0.012) |" in md and paths["figure"].stat().st_size > 0


def test_comparison_names_a_missing_table(tmp_path, capsys):
    _tables(tmp_path, drop="subdomain")
    assert subdomain.main(["--results", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "subdomain/rmse_at_step.csv: no such file" in err and "Traceback" not in err


def test_comparison_without_the_whole_mesh_run(tmp_path):
    _tables(tmp_path, drop="subdomain_whole")
    table = pd.read_csv(subdomain.write(tmp_path)["csv"])
    assert set(table["training"]) == {"patches", "paper mesh, transferred"}


def test_suites_compare_patches_whole_mesh_and_transfer():
    """The patch and whole-mesh runs differ in ``patch_nodes`` alone; the transfer baseline is
    the quick suite's run (the same run id: a trained one is reused) rolled out at r = 8."""
    (p,), (w,) = get_suite("subdomain").specs, get_suite("subdomain_whole").specs
    assert p.case == w.case == "plate_cantilever_few@r8" and p.model == w.model
    assert set(p.overrides) - set(w.overrides) == {"train.patch_nodes=2000"}
    assert set(w.overrides) < set(p.overrides)
    t = get_suite("subdomain_transfer")
    assert t.resolutions == (1, 8) and t.seeds == get_suite("subdomain").seeds == 3
    ids = [r.run_id for r in t.runs()]
    assert ids == [f"plate_cantilever-implicit_energy-quick-s{s}" for s in (0, 1, 2)]
    assert ids[0] in {r.run_id for r in get_suite("quick").runs()}
    with pytest.raises(ValueError, match="matches no run"):
        get_suite("subdomain").runs(only="mgn")
