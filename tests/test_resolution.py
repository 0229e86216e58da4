"""Cases by resolution (docs/SCALE.md): ``CASE@rN`` is ``CASE.refined(N)``, a mesh N times finer
with the same physics (loads, masses, drag, time step, clamp), its own hash and data directory;
``CASE@r1`` is ``CASE`` itself, hash and parameters unchanged."""

import dataclasses

import numpy as np
import pytest

from benchmarks.cli import main
from benchmarks.suite import registry
from benchmarks.suite.metrics import table_steps
from benchmarks.suite.registry import CASES, RegistryError, get_case, register_case, safe_id
from benchmarks.suite.suites import RunSpec
from groundtruth import store
from groundtruth.cases import RodCase, resolution_id, split_resolution_id
from groundtruth.cases.rod import refined_clamp

REFINABLE = ("rod_falling", "rod_cantilever", "plate_cantilever", "plate_hanging")

#: Nodes at r = 1, 2, 4: the rod 20 r + 1; the in-plane plate 4 r + 1 rows across the 35 r
#: intervals along (staggered rows); plate_hanging (2 r + 1) nodes across (48 r + 2) rows.
NODES = {"rod_falling": (21, 41, 81), "rod_cantilever": (21, 41, 81),
         "plate_cantilever": (182, 643, 2405), "plate_hanging": (150, 490, 1746)}

#: ``CaseBase.hash()`` of the registered cases computed by the code before resolutions existed
#: (commit e0d8fe7): the committed data and results record them, so r = 1 must not move them.
HASHES = {
    "rod_falling": "d8b889aff7b0fc9b3fec52200ae622def55e5483a1162455f9671b013538e349",
    "rod_cantilever": "05b85b294da40f1d92565bbd4d117182b8d462b937c55d8a52cfc3c4055b51d7",
    "plate_cantilever": "f713629a93d15780dd6eb0c034b28bc51fff2c6d6ad6d2522401e0b0789b29c1",
    "plate_hanging": "76609fdedd8d17acdf33e32c17498b96c724f78bfb27ac78fab7dfb8198f4e53",
}

TINY = RodCase(id="rod_tiny_res", n_nodes=7, t_end=0.2, n_train=2, n_test=1)


def test_every_registered_case_is_refinable():
    assert sorted(c for c in CASES if callable(getattr(CASES[c], "refined", None))) == \
        sorted(REFINABLE + ("plate_cantilever_few",))


def test_the_subdomain_plate_is_the_paper_plate_with_fewer_training_trajectories():
    """plate_cantilever_few (the subdomain suite's) differs from plate_cantilever in its
    training split only: at r = 8 the same mesh and the same test moduli, so that a model
    trained on the paper's mesh is rolled out on the same test trajectories."""
    few, paper = get_case("plate_cantilever_few@r8"), get_case("plate_cantilever@r8")
    a, b = few.to_dict(), paper.to_dict()
    assert {k for k in a if a[k] != b[k]} == {"id", "n_train", "seed_train"}
    assert few.n_train == 6 and len(few.rest_positions()) == 9289
    np.testing.assert_array_equal(few.sample_youngs("test"), paper.sample_youngs("test"))
    y = np.sort(few.sample_youngs("train"))  # the seed's draws span the modulus range
    assert y[0] <= 3.0e6 and y[-1] >= 7.0e6
    assert np.diff(np.r_[2.5e6, y, 7.5e6]).max() <= 1.5e6


@pytest.mark.parametrize("case_id", REFINABLE)
def test_node_counts_per_resolution(case_id):
    counts = tuple(len(get_case(f"{case_id}@r{r}").rest_positions()) for r in (1, 2, 4))
    assert counts == NODES[case_id]
    c = get_case(f"{case_id}@r2")
    if case_id.startswith("rod"):
        assert c.n_nodes == 41 and c.dL == pytest.approx(CASES[case_id].dL / 2)
    elif case_id == "plate_cantilever":
        assert (c.n_rows, c.n_long) == (9, 70)
    else:
        assert (c.n_length, c.n_width, c.grading, c.grading_layer) == (96, 4, 16.0, 0.03)


def _totals(case):
    s = case.system(case.reference_youngs)
    x = case.rest_positions()[:, 0]
    return {"mass": s.mass.sum(), "force": s.force.sum(axis=0), "damping": s.damping.sum(),
            "mass_centre_x": (s.mass * x).sum() / s.mass.sum()}


@pytest.mark.parametrize("case_id", REFINABLE)
def test_same_physics_at_every_resolution(case_id):
    """Total mass, gravity load and drag, where the mass sits, the time step and everything
    but the mesh are those of r = 1 at r = 2 and 4."""
    base = CASES[case_id]
    want = _totals(base)
    # plate_hanging's mesh reaches clamp_gap / 2 behind the clamp line, a sliver of sheet that
    # never moves and shrinks with the clamp rows (docs/SCALE.md): 5e-4 of the mass at r = 1
    rtol = 1e-3 if case_id == "plate_hanging" else 1e-12
    for r in (2, 4):
        c = get_case(f"{case_id}@r{r}")
        got = _totals(c)
        for k in ("mass", "damping"):
            assert got[k] == pytest.approx(want[k], rel=rtol, abs=0), (r, k)
        np.testing.assert_allclose(got["force"], want["force"], rtol=rtol, atol=0)
        assert got["mass_centre_x"] == pytest.approx(want["mass_centre_x"], abs=1e-3)
        assert (c.dt, c.save_dt, c.t_end, c.newton_rtol) == \
            (base.dt, base.save_dt, base.t_end, base.newton_rtol)
        assert np.array_equal(c.t_save(), base.t_save())
        for split in ("train", "test"):
            assert np.array_equal(c.sample_youngs(split), base.sample_youngs(split))
        mesh = {"n_nodes", "clamped_nodes", "n_rows", "n_long", "n_length", "n_width",
                "clamp_gap", "id", "resolution"}
        same = {f.name for f in dataclasses.fields(base)} - mesh
        assert {k: getattr(c, k) for k in same} == {k: getattr(base, k) for k in same}
    if case_id == "plate_hanging":
        for r in (1, 2, 4):
            c = get_case(f"{case_id}@r{r}")
            strip = c.density * c.thickness * c.width * (c.length + c.clamp_gap / 2)
            assert _totals(c)["mass"] == pytest.approx(strip, rel=1e-12)


def test_rod_falling_spheres_keep_mass_and_drag_per_length():
    """The middle sphere is unchanged at the centre; the small ones are r times as many, each
    with 1/r of the volume and drag of one at r = 1."""
    base, c = CASES["rod_falling"], get_case("rod_falling@r2")
    sb, s = base.system(1e9), c.system(1e9)
    mid_b, mid = 10, 20
    assert c.rest_positions()[mid, 0] == pytest.approx(base.length / 2)
    assert (s.mass[mid], s.damping[mid]) == (sb.mass[mid_b], sb.damping[mid_b])
    small_b, small = np.delete(sb.mass, mid_b), np.delete(s.mass, mid)
    np.testing.assert_allclose(small, small_b[0] / 2, rtol=1e-12)
    np.testing.assert_allclose(np.delete(s.damping, mid), sb.damping[0] / 2, rtol=1e-12)
    assert c.terminal_velocity() == pytest.approx(base.terminal_velocity(), rel=1e-12)


def test_hash_and_parameters_unchanged_at_r1_and_different_above():
    for case_id, h in HASHES.items():
        assert get_case(case_id).hash() == h
        assert get_case(f"{case_id}@r1") is get_case(case_id)
        assert get_case(f"{case_id}@r1").hash() == h
        assert "resolution" not in get_case(case_id).to_dict()
        assert CASES[case_id].refined(1) is CASES[case_id]
        fine = get_case(f"{case_id}@r2")
        assert fine.hash() != h and fine.hash() != get_case(f"{case_id}@r4").hash()
        assert fine.to_dict()["resolution"] == 2 and fine.to_dict()["id"] == f"{case_id}@r2"


@pytest.mark.parametrize("case_id", REFINABLE)
def test_derived_ids_round_trip(case_id):
    for r in (1, 2, 8):
        cid = resolution_id(case_id, r)
        assert cid == (case_id if r == 1 else f"{case_id}@r{r}")
        assert split_resolution_id(cid) == (case_id, r)
        assert safe_id(cid, "case id") == cid
    c = get_case(f"{case_id}@r8")
    assert c.id == f"{case_id}@r8" and c.resolution == 8
    assert get_case(c.id) is c                      # built once, cached
    assert c == CASES[case_id].refined(8)
    assert table_steps(c.id, c.n_frames) == table_steps(case_id, c.n_frames)
    assert RunSpec(c.id, "mgn", "quick").run_id == f"{case_id}@r8-mgn-quick-s0"


@pytest.mark.parametrize("bad, text", [
    ("plate_cantilever@r0", "'0'"), ("plate_cantilever@rx", "'x'"),
    ("plate_cantilever@r-1", "'-1'"), ("plate_cantilever@r", "''"),
    ("plate_cantilever@8", "'8'"), ("plate_cantilever@r2@r2", "'2@r2'"),
    ("plate_cantilever@r1.5", "'1.5'")])
def test_bad_resolutions_are_refused_naming_the_value(bad, text):
    with pytest.raises(ValueError, match=f"case id '{bad}': the resolution after '@r' must be a "
                                         f"positive integer .*got {text}"):
        get_case(bad)


def test_other_bad_refinements_are_refused():
    with pytest.raises(ValueError, match="without leading zeros, 'rod_falling@r2'"):
        get_case("rod_falling@r02")
    with pytest.raises(RegistryError, match="unknown case id 'nope'; valid ids: "):
        get_case("nope@r2")
    for r in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match=f"RodCase.refined: the resolution r must be an int "
                                             f">= 1 .*got {r!r}"):
            CASES["rod_falling"].refined(r)
    with pytest.raises(ValueError, match="'rod_falling@r2' is already refined .* 'rod_falling@r4'"):
        get_case("rod_falling@r2").refined(2)
    with pytest.raises(ValueError, match="does not match resolution=1"):
        RodCase(id="rod_x@r2")
    with pytest.raises(ValueError, match="does not match resolution=2"):
        RodCase(id="rod_x", resolution=2)
    with pytest.raises(ValueError, match="RodCase.resolution must be an int >= 1, got 0"):
        RodCase(resolution=0)
    with pytest.raises(ValueError, match="'@' marks a derived id"):
        register_case(dataclasses.replace(TINY, id="rod_tiny_res@r2", resolution=2))
    # a middle sphere off the centre would move: refused rather than moved
    with pytest.raises(ValueError, match="'rod_even' cannot be refined to resolution 2"):
        RodCase(id="rod_even", n_nodes=20).refined(2)


def test_a_case_without_refined_refuses_resolutions(monkeypatch):
    @dataclasses.dataclass(frozen=True)
    class Fixed:
        id: str = "fixed_mesh"

    monkeypatch.setitem(CASES, "fixed_mesh", Fixed())
    assert get_case("fixed_mesh@r1") is CASES["fixed_mesh"]
    with pytest.raises(ValueError, match=r"case 'fixed_mesh' cannot be refined \('fixed_mesh@r3' "
                                         r"asks for resolution 3\): its class Fixed defines no "
                                         r"refined\(r\) method"):
        get_case("fixed_mesh@r3")


def test_the_same_clamp_at_every_resolution():
    # the rod: the same clamped length (one segment at r = 1)
    assert refined_clamp((0, 1), 4) == (0, 1, 2, 3, 4)
    assert refined_clamp((0, 5), 2) == (0, 10)           # separate nodes stay points
    assert refined_clamp((), 3) == ()
    for r in (1, 2, 4):
        c = get_case(f"rod_cantilever@r{r}")
        x = c.rest_positions()[c.node_type() == 1, 0]
        assert x.max() == pytest.approx(CASES["rod_cantilever"].dL) and len(x) == r + 1
        # the in-plane strip: every node on x = 0
        p = get_case(f"plate_cantilever@r{r}")
        xp = p.rest_positions()[:, 0]
        assert np.array_equal(p.node_type() == 1, np.abs(xp) < 1e-12)
        # plate_hanging: two rows straddling x = 0, clamp_gap / r apart
        h = get_case(f"plate_hanging@r{r}")
        xh = h.rest_positions()[h.node_type() == 1, 0]
        assert sorted(set(np.round(xh, 12))) == pytest.approx([-5e-4 / r, 5e-4 / r])
        assert len(xh) == 2 * (2 * r + 1)


def test_rod_falling_at_r2_falls_like_r1():
    """Physics smoke: 30 steps (0.3 s) at the stiff end; the mass centre's fall at r = 2 is
    finite and within 3 % of r = 1 (measured: 0.9 %)."""
    fall = {}
    for r in (1, 2):
        c = get_case(f"rod_falling@r{r}")
        res = c.simulate(1.0e9, t_end=0.3)
        assert np.all(np.isfinite(res["pos"])) and res["stats"]["halvings"] == 0
        m = c.loads()["mass"]
        y = (res["pos"][:, :, 1] * m).sum(axis=1) / m.sum()
        fall[r] = y[0] - y[-1]
    assert fall[1] > 1e-3
    assert fall[2] == pytest.approx(fall[1], rel=0.03)


def test_cli_simulates_a_refined_case(tmp_path, capsys):
    out = tmp_path / "r2.npz"
    assert main(["simulate", "rod_falling@r2", "--youngs", "1e9", "--t-end", "0.2",
                 "--out", str(out), "--no-progress"]) == 0
    with np.load(out) as z:
        assert z["pos"].shape == (1, 3, 41, 3) and str(z["case"]) == "rod_falling@r2"
        assert str(z["case_hash"]) == get_case("rod_falling@r2").hash()
    for bad, needle in (("rod_falling@r0", "got '0'"), ("rod_falling@rx", "got 'x'"),
                        ("nope@r2", "unknown case id 'nope'")):
        assert main(["simulate", bad, "--youngs", "1e9", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and needle in err.strip().splitlines()[-1]


def test_cli_generates_a_refined_case_into_its_own_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(CASES, TINY.id, TINY)
    monkeypatch.setattr(registry, "_REFINED", {})
    assert main(["generate", f"{TINY.id}@r2", "--data-dir", str(tmp_path), "--workers", "1",
                 "--no-progress"]) == 0
    assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == \
        [f"{TINY.id}@r2"]
    fine = get_case(f"{TINY.id}@r2")
    data = store.load_split(fine, "train", tmp_path)
    assert data["pos"].shape == (2, 3, 13, 3) and str(data["case"]) == fine.id
    assert str(data["case_hash"]) == fine.hash() != TINY.hash()
