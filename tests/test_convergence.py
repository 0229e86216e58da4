"""Mesh convergence study (benchmarks.validation.convergence, `meshbench convergence`)."""

import numpy as np
import pandas as pd
import pytest

from benchmarks.cli import main
from benchmarks.suite.registry import get_case
from benchmarks.validation import convergence as cv


def test_probe_is_the_same_material_point_at_every_r():
    for base, r in (("rod_falling", 2), ("plate_cantilever", 2), ("plate_hanging", 2)):
        c1, cr = get_case(base), get_case(f"{base}@r{r}")
        x1 = np.asarray(c1.initial_state()[0], float)
        xr = np.asarray(cr.initial_state()[0], float)
        p = x1[cv.probe_node(c1)]
        assert p[0] == pytest.approx(x1[:, 0].max())
        node = cv.node_at(xr, p, 1.0)
        assert np.allclose(xr[node], p, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="no node at rest position"):
        cv.node_at(np.zeros((3, 3)), np.ones(3), 1.0)


def test_rod_study_compares_neighbouring_resolutions(tmp_path):
    summary, frames = cv.convergence("rod_falling", [2, 1], t_end=0.3, cache=tmp_path)
    assert [r["r"] for r in summary] == [1, 2] and [r["nodes"] for r in summary] == [21, 41]
    assert summary[0]["next_r"] == 2 and summary[1]["rel_diff"] is None
    assert summary[0]["relative_to"] == "mass_centre"   # the rod falls freely
    assert 0 < summary[0]["rel_diff"] < 0.1
    df = pd.DataFrame(frames)
    u1 = df[df.r == 1][["ux_m", "uy_m", "uz_m"]].to_numpy()
    u2 = df[df.r == 2][["ux_m", "uy_m", "uz_m"]].to_numpy()
    assert u1.shape == u2.shape == (4, 3) and np.all(u1[0] == 0)
    expect = np.linalg.norm(u1 - u2, axis=1).max() / np.linalg.norm(u2, axis=1).max()
    assert summary[0]["rel_diff"] == pytest.approx(expect, rel=1e-12)
    # the cache holds both trajectories: a second study simulates nothing
    assert len(list(tmp_path.glob("*.npz"))) == 2
    again, _ = cv.convergence("rod_falling", [1, 2], t_end=0.3, cache=tmp_path)
    assert again[0]["rel_diff"] == summary[0]["rel_diff"]


def test_cli_writes_summary_and_frames(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["convergence", "rod_falling", "--r", "1,2", "--t-end", "0.2", "--out-dir", str(out),
            "--cache", str(tmp_path / "cache"), "--allow-dirty", "--no-progress"]
    assert main(args) == 0
    s = pd.read_csv(out / "convergence_summary.csv")
    assert list(s.r) == [1, 2] and s.loc[0, "next_r"] == 2
    assert (out / "convergence_rod_falling.png").stat().st_size > 0
    f = pd.read_csv(out / "convergence_rod_falling.csv")
    assert set(f.r) == {1, 2}
    assert main(args) == 0                       # again: rows replaced, not duplicated
    assert len(pd.read_csv(out / "convergence_summary.csv")) == 2


@pytest.mark.parametrize("extra, field", [(["--r", "0,1"], "--r"), (["--r", "x"], "--r"),
                                          (["--t-end", "-1"], "--t-end"),
                                          (["--youngs", "-5"], "youngs")])
def test_bad_input_exits_2(tmp_path, capsys, extra, field):
    rc = main(["convergence", "rod_falling", "--out-dir", str(tmp_path), "--allow-dirty"] + extra)
    assert rc == 2
    assert field in capsys.readouterr().err


def test_refined_id_is_refused(tmp_path, capsys):
    assert main(["convergence", "rod_falling@r2", "--out-dir", str(tmp_path),
                 "--allow-dirty"]) == 2
    assert "without '@rN'" in capsys.readouterr().err
