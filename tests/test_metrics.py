import numpy as np
import pandas as pd
import pytest

from benchmarks.suite.metrics import (
    PAPER_TABLES,
    PER_COORDINATE,
    full_rollout_rmse,
    no_motion,
    rmse_at_step_table,
    rmse_per_coordinate,
    rmse_per_step,
    tidy_metrics,
)


def test_rmse_definition_by_hand():
    true = np.zeros((1, 2, 2, 3))
    pred = true.copy()
    pred[0, 1, 0] = [3.0, 4.0, 0.0]          # |err| = 5 at one of two nodes
    r = rmse_per_step(pred, true)
    assert r.shape == (1, 2) and r[0, 0] == 0.0
    assert np.isclose(r[0, 1], np.sqrt(25 / 2))
    assert np.isclose(full_rollout_rmse(pred, true)[0], np.sqrt(25 / 2))


def test_oracle_scores_zero_and_no_motion_is_the_displacement():
    rng = np.random.default_rng(0)
    true = np.cumsum(rng.normal(size=(3, 5, 4, 3)), axis=1)
    assert np.all(rmse_per_step(true.copy(), true) == 0)
    nm = rmse_per_step(no_motion(true), true)
    disp = np.sqrt(np.mean(np.sum((true - true[:, :1]) ** 2, -1), -1))
    np.testing.assert_allclose(nm, disp)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shape"):
        rmse_per_step(np.zeros((1, 2, 3, 3)), np.zeros((1, 2, 4, 3)))


def test_table_mean_std_and_relative_increase():
    t = np.arange(4) * 0.1
    true = np.zeros((2, 4, 1, 3))
    a = true.copy()
    a[0, :, 0, 0], a[1, :, 0, 0] = 1.0, 3.0       # meshodenet: rmse 1 and 3 -> mean 2, std 1
    b = 2 * a                                      # mgn: mean 4 -> +100 %
    df = pd.concat([tidy_metrics(a, true, t, {"case": "c", "model": "meshodenet"}),
                    tidy_metrics(b, true, t, {"case": "c", "model": "mgn"})])
    tab = rmse_at_step_table(df, {"c": (1, 3)})
    assert len(tab) == 4
    r = tab[(tab.model == "mgn") & (tab.step == 3)].iloc[0]
    assert r.rmse_mean == 4 and r.rmse_std == 2 and r.n_trajectories == 2
    assert np.isclose(r.increase_vs_meshodenet_pct, 100.0)
    assert np.allclose(tab[tab.model == "meshodenet"].increase_vs_meshodenet_pct, 0.0)


def test_a_diverged_trajectory_makes_its_step_nan_never_left_out():
    """One trajectory of two NaN from frame 2 on (its rollout diverged): the table's mean and
    std at step 3 are NaN (pandas would average the finite one), step 1 is untouched, and the
    other model's rows keep their values."""
    t = np.arange(4) * 0.1
    true = np.zeros((2, 4, 1, 3))
    a = np.ones_like(true)
    b = a.copy()
    b[1, 2:] = np.nan
    df = pd.concat([tidy_metrics(a, true, t, {"case": "c", "model": "meshodenet"}),
                    tidy_metrics(b, true, t, {"case": "c", "model": "mgn"})])
    tab = rmse_at_step_table(df, {"c": (1, 3)}).set_index(["model", "step"])
    assert np.isnan(tab.loc[("mgn", 3), ["rmse_mean", "rmse_std", "rmse_coord_mean",
                                         "rmse_coord_std"]].to_numpy(float)).all()
    assert tab.loc[("mgn", 3), "n_trajectories"] == 2
    assert tab.loc[("mgn", 1), "rmse_mean"] == pytest.approx(np.sqrt(3))
    assert tab.loc[("meshodenet", 3), "rmse_mean"] == pytest.approx(np.sqrt(3))


def test_per_coordinate_rmse_is_the_authors_formula_and_a_third_of_the_squared_norm():
    """The authors' evaluation: sqrt of the mean over nodes and coordinates of the squared
    error (their evaluation notebook's compute_rmse on (nodes, 3) arrays); by hand on one node,
    and against the Euclidean per-node RMSE / sqrt(3) on random arrays."""
    true = np.zeros((1, 2, 2, 3))
    pred = true.copy()
    pred[0, 1, 0] = [3.0, 4.0, 0.0]          # 25 over 2 nodes x 3 coordinates
    assert rmse_per_coordinate(pred, true)[0, 1] == pytest.approx(np.sqrt(25 / 6))
    rng = np.random.default_rng(1)
    pred, true = rng.normal(size=(3, 4, 5, 3)), rng.normal(size=(3, 4, 5, 3))
    authors = np.array([[np.sqrt(np.mean((pred[b, k] - true[b, k]) ** 2)) for k in range(4)]
                        for b in range(3)])
    np.testing.assert_allclose(rmse_per_coordinate(pred, true), authors, rtol=1e-14)
    np.testing.assert_allclose(rmse_per_step(pred, true) * PER_COORDINATE, authors, rtol=1e-14)


def test_table_reports_the_papers_convention_beside_ours():
    t = np.arange(4) * 0.1
    rng = np.random.default_rng(2)
    true = rng.normal(size=(3, 4, 5, 3))
    pred = true + rng.normal(size=true.shape)
    tab = rmse_at_step_table(tidy_metrics(pred, true, t, {"case": "c", "model": "meshodenet"}),
                             {"c": (1, 2, 3)})
    cols = list(tab.columns)
    assert cols.index("rmse_coord_mean") == cols.index("rmse_std") + 1
    direct = rmse_per_coordinate(pred, true)
    np.testing.assert_allclose(tab["rmse_coord_mean"], direct[:, 1:].mean(0), rtol=1e-12)
    np.testing.assert_allclose(tab["rmse_coord_std"], direct[:, 1:].std(0), rtol=1e-10)
    np.testing.assert_allclose(tab["rmse_coord_mean"] * np.sqrt(3), tab["rmse_mean"], rtol=1e-14)


def test_paper_tables_hold_the_papers_steps_and_numbers():
    from benchmarks.suite.metrics import PAPER_STEPS

    for case, models in PAPER_TABLES.items():
        assert set(models) == {"meshodenet", "mgn"}
        for row in models.values():
            assert tuple(row) == PAPER_STEPS[case]
    # spot values of Tables 1 and 2 (1e-4 m)
    assert PAPER_TABLES["rod_falling"]["meshodenet"][180] == pytest.approx(2.03e-4)
    assert PAPER_TABLES["plate_cantilever"]["mgn"][350] == pytest.approx(354.18e-4)


def test_rmse_is_defined_once_and_keeps_the_arithmetic_of_the_stored_numbers():
    """The suite's per-trajectory RMSEs (metrics.csv) and the pooled ones of training and
    runs.csv all come from ``meshodenet.metrics.rmse``, bit for bit the formulas that wrote the
    committed results (kept here as the oracle)."""
    torch = pytest.importorskip("torch")
    from meshodenet.metrics import position_rmse, rmse_per_frame

    rng = np.random.default_rng(3)
    true = np.cumsum(rng.normal(scale=1e-2, size=(4, 61, 37, 3)), axis=1)
    pred = true + rng.normal(scale=1e-3, size=true.shape)
    same = np.testing.assert_array_equal
    same(rmse_per_step(pred, true), np.sqrt(np.mean(np.sum((pred - true) ** 2, -1), -1)))
    same(full_rollout_rmse(pred, true),
         np.sqrt(np.mean(np.sum((pred - true)[:, 1:] ** 2, -1), axis=(1, 2))))
    for dtype in (torch.float32, torch.float64):
        p, t = torch.tensor(pred, dtype=dtype), torch.tensor(true, dtype=dtype)
        assert torch.equal(rmse_per_frame(p, t),
                           ((p.double() - t.double()) ** 2).sum(-1).mean(dim=(0, 2)).sqrt())
        assert position_rmse(p, t) == float(
            ((p[:, 1:].double() - t[:, 1:].double()) ** 2).sum(-1).mean().sqrt())
