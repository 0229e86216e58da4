"""The in-plane plate (``plate_cantilever``, the paper's case study 2 as its authors ran it):
Delaunay mesh, per-triangle spring calibration, bending calibration, static tip against the
shearable elastica, first frequency, damping against the authors' curve, bad input."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.suite.registry import CASES
from benchmarks.validation import plate_fidelity as pf
from groundtruth.cases import InPlanePlateCase
from groundtruth.mesh import delaunay_mesh, mesh_edges, staggered_strip_points, triangle_areas
from groundtruth.plate import cst_spring_stiffness, edge_strain_map, inplane_stiffness, plane_stress_matrix
from groundtruth.references import elastica, elastica_shear
from groundtruth.stretch import StretchTerm

CASE = CASES["plate_cantilever"]


# --- mesh ----------------------------------------------------------------------------------


def test_mesh_is_a_valid_unstructured_strip_like_the_authors():
    nodes, tri = CASE.rest_positions(), CASE.mesh()[1]
    assert len(nodes) == 182 and CASE.n_rows == 5 and CASE.n_long == 35
    assert np.isclose(triangle_areas(nodes, tri).sum(), CASE.length * CASE.width, rtol=1e-12)
    x = nodes[tri]
    signed = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])[:, 2]
    assert np.all(signed > 0)                                           # counter-clockwise
    # no obtuse angle, none below 29 deg (half cells at the short edges)
    for k in range(3):
        a, b = x[:, (k + 1) % 3] - x[:, k], x[:, (k + 2) % 3] - x[:, k]
        cos = np.sum(a * b, 1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
        assert np.all(cos >= -1e-12) and np.all(cos < math.cos(math.radians(29)))
    fixed = CASE.node_type() == 1
    assert fixed.sum() == 5 and np.all(nodes[fixed, 0] == 0)            # all of x = 0
    assert np.all(nodes[:, 2] == 0) and nodes[:, 1].min() == 0 and nodes[:, 1].max() == CASE.width
    edges = CASE.mesh()[0]
    assert np.max(np.abs(edges[:, 0] - edges[:, 1])) <= 2 * CASE.n_rows  # banded numbering


def test_delaunay_drops_nothing_on_a_staggered_set_and_validates():
    p = staggered_strip_points(1.0, 0.1, 9, 60)
    tri = delaunay_mesh(p)
    assert np.isclose(triangle_areas(p, tri).sum(), 0.1)
    with pytest.raises(ValueError, match="n_rows"):
        staggered_strip_points(1.0, 0.1, 1, 10)


# --- per-triangle spring calibration --------------------------------------------------------


def _equilateral(l0=0.02):
    p = np.array([[0, 0, 0], [l0, 0, 0], [l0 / 2, l0 * math.sqrt(3) / 2, 0]])
    return p, np.array([[0, 1, 2]])


def test_cst_springs_reproduce_the_constant_strain_element_on_equilateral_triangles():
    """nu = 1/3: the three springs store exactly 1/2 A h e^T D e for any small strain."""
    p, tri = _equilateral()
    edges = mesh_edges(tri)
    Y, h = 5e6, 1e-3
    k = cst_spring_stiffness(p, tri, edges, Y, h, 1 / 3)
    l0 = np.linalg.norm(p[edges[:, 1]] - p[edges[:, 0]], axis=1)
    np.testing.assert_allclose(k, math.sqrt(3) / 4 * Y * h * l0, rtol=1e-12)
    rng = np.random.default_rng(0)
    D = plane_stress_matrix(Y, 1 / 3)
    A = triangle_areas(p, tri)[0]
    for _ in range(5):
        e = rng.normal(size=3) * 1e-4
        eps_edges = edge_strain_map(p, tri)[0] @ e
        # edge i of edge_strain_map is (t_i, t_i+1); map to the sorted edges
        order = [list(map(tuple, edges)).index(tuple(sorted((int(tri[0, i]),
                                                              int(tri[0, (i + 1) % 3])))))
                 for i in range(3)]
        springs = 0.5 * np.sum(k[order] * l0[order] * eps_edges**2)
        np.testing.assert_allclose(springs, 0.5 * A * h * e @ D @ e, rtol=1e-10)


@pytest.mark.parametrize("strain", [(1e-4, 0, 0), (0, 1e-4, 0), (0, 0, 1e-4),
                                    (1e-4, -5e-5, 2e-5)])
def test_cst_springs_on_the_case_mesh_pass_the_patch_test(strain):
    """A uniform strain of the default mesh stores the continuum's 1/2 L w h e^T D e within 5 %
    (measured 0.02 %, 3.9 %, 1.0 %, 1.4 %: near-equilateral inside, half cells at the ends)."""
    nodes, tri, edges = CASE.rest_positions(), CASE.mesh()[1], CASE.mesh()[0]
    Y, h = 5e6, 1e-3
    K = inplane_stiffness(nodes, edges, cst_spring_stiffness(nodes, tri, edges, Y, h, 1 / 3))
    exx, eyy, gxy = strain
    u = np.stack([exx * nodes[:, 0] + 0.5 * gxy * nodes[:, 1],
                  eyy * nodes[:, 1] + 0.5 * gxy * nodes[:, 0]], 1).ravel()
    e = np.array(strain)
    continuum = 0.5 * CASE.length * CASE.width * h * e @ plane_stress_matrix(Y, 1 / 3) @ e
    assert 0.5 * u @ K @ u / continuum == pytest.approx(1, abs=0.05)


def test_linear_stiffness_is_the_stretch_hessian_at_rest():
    nodes, edges = CASE.rest_positions(), CASE.mesh()[0]
    k = CASE._springs(5e6)
    K = inplane_stiffness(nodes, edges, k).toarray()
    l0 = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
    term = StretchTerm(edges, l0, k)
    _, _, he = term.evaluate(np.concatenate([nodes[edges[:, 0]], nodes[edges[:, 1]]], 1), 2)
    H = np.zeros((3 * len(nodes),) * 2)
    for d, h in zip(term.dofs, he):
        H[np.ix_(d, d)] += h
    xy = np.flatnonzero(np.arange(3 * len(nodes)) % 3 < 2)
    np.testing.assert_allclose(H[np.ix_(xy, xy)], K, atol=1e-9 * np.abs(K).max())


def test_system_gradient_and_hessian_by_finite_differences():
    """The calibrated springs and the hinges of the case's system, at a random 3-D state."""
    s = CASE.system(5e6)
    rng = np.random.default_rng(3)
    q = CASE.rest_positions().ravel() + 2e-3 * rng.normal(size=3 * len(CASE.rest_positions()))
    g = s.gradient(q)
    H = s.hessian(q)
    free = np.flatnonzero(~s.fixed_dofs)
    eps = 1e-7
    for i in rng.choice(free, 12, replace=False):
        dq = np.zeros_like(q)
        dq[i] = eps
        fd = (s.energy(q + dq) - s.energy(q - dq)) / (2 * eps)
        assert abs(fd - g[i]) < 1e-5 * np.abs(g).max()
        col = (s.gradient(q + dq) - s.gradient(q - dq)) / (2 * eps)
        np.testing.assert_allclose(H[free, i], col[free], atol=1e-5 * np.abs(H).max())


# --- bending calibration and the static tip ---------------------------------------------------


def test_bending_calibration_makes_the_small_load_tip_timoshenkos():
    y = 5e6
    assert 0.8 < CASE.bending_calibration < 0.9                         # measured 0.867
    assert CASE.linear_tip_deflection(y) == pytest.approx(CASE.timoshenko_tip(y), rel=1e-9)
    factors = [pf.refined(CASE, n).bending_calibration for n in (3, 5, 9)]
    assert factors[0] < factors[1] < factors[2] < 1                     # tends to 1
    off = dataclasses.replace(CASE, calibrate_bending=False)
    assert off.bending_calibration == 1.0


def test_shearable_elastica_limits():
    e0, e = elastica(2.0), elastica_shear(2.0)
    assert e["tip_v"] == pytest.approx(e0["tip_v"], rel=1e-6)
    small = elastica_shear(1e-3, 1e-4, 2e-4)
    assert small["tip_v"] == pytest.approx(1e-3 / 8 + 1e-4, rel=1e-3)


@pytest.mark.parametrize("youngs", [2.5e6, 5e6, 7.5e6])
def test_static_tip_matches_the_shearable_elastica(youngs):
    """Within 1 % at both ends and the middle of the modulus range (measured +0.49, +0.21,
    +0.11 %); the bottom corner is the lowest node; the strip stays in z = 0."""
    d = pf.static_tip(CASE, youngs)
    ref = pf.reissner_tip(CASE, youngs)["tip_v"] * CASE.length
    assert d / ref == pytest.approx(1.0, abs=0.01)
    q = CASE.solve_static(youngs)
    assert np.argmin(q[:, 1]) == CASE.corner_node and np.all(q[:, 2] == 0)


def test_first_frequency_matches_beam_theory():
    """Network (lumped mass) vs the plane-stress continuum: within 0.5 % (measured -0.20 %);
    vs Euler-Bernoulli within 1.5 % (measured -0.84 %, shear and rotary inertia)."""
    w = pf.network_frequency(CASE, 5e6)
    assert w / pf.continuum_frequency(CASE, 5e6, 40, 2) == pytest.approx(1, abs=5e-3)
    from groundtruth.references import cantilever_frequency

    w_eb = cantilever_frequency(CASE.bending_rigidity(5e6), 1200 * 1e-4, 1.0)
    assert w / w_eb == pytest.approx(1, abs=0.015)


# --- dynamics and damping ---------------------------------------------------------------------


@pytest.mark.skipif(not pf.REFERENCE_CSV.exists(), reason="authors' digitized curve not present")
def test_damped_sag_follows_the_authors_curve():
    """At the fitted modulus (docs/PLATE.md) and the case's damping rate, the lowest node's drop
    follows the digitized reference within 4 mm everywhere (measured max 1.6 mm, rms 0.6 mm)
    and does not overshoot its final value."""
    t_ref, d_ref = pf.load_reference()
    t, d = pf.lowest_drop(CASE, 8.257e6, 1.2)
    diff = np.interp(t_ref, t, d) - d_ref
    assert np.max(np.abs(diff)) < 4e-3
    assert np.all(np.diff(d) >= -1e-6)                                   # monotone sag


def test_damping_ratio_is_overcritical_over_the_range():
    z = pf.damping_ratios(CASE)
    assert 1.0 < z["7.5e+06"] < z["2.5e+06"] < 3.0


def test_trajectory_stays_planar_and_keeps_shape():
    short = dataclasses.replace(CASE, t_end=0.03)
    sim = short.simulate(5e6)
    assert sim["pos"].shape == (11, 182, 3)
    assert np.all(sim["pos"][..., 2] == 0)
    assert sim["pos"][-1, CASE.corner_node, 1] < -1e-3


@pytest.mark.parametrize("field, value", [("n_rows", 1), ("n_rows", 4), ("n_long", 0), ("poisson", 0.6),
                                          ("damping_rate", -1.0), ("width", 0.0)])
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        InPlanePlateCase(**{field: value})


def test_reference_file_provenance_header():
    if not pf.REFERENCE_CSV.exists():
        pytest.skip("authors' digitized curve not present")
    head = Path(pf.REFERENCE_CSV).read_text().splitlines()[0]
    assert "trajectory_evolution.mp4" in Path(pf.REFERENCE_CSV).read_text() and head.startswith("#")


def test_cli_static_of_the_registered_case(tmp_path):
    """``meshbench simulate plate_cantilever --youngs Y --static --out F.npz``: one frame, the
    case's 182-node mesh, 5 clamped nodes, the static solution."""
    from benchmarks.cli import main
    from groundtruth import store

    out = tmp_path / "static.npz"
    assert main(["simulate", "plate_cantilever", "--youngs", "7.5e6", "--static",
                 "--out", str(out)]) == 0
    data = store.load_npz(out, "plate_cantilever", CASE.hash())
    assert data["pos"].shape == (1, 1, 182, 3) and data["node_type"].sum() == 5
    np.testing.assert_allclose(data["pos"][0, 0], CASE.solve_static(7.5e6))
    assert isinstance(CASE, InPlanePlateCase)


def test_plate_fidelity_command_writes_the_measurement(tmp_path, monkeypatch, capsys):
    from benchmarks.cli import main

    row = {"n_rows": 3, "youngs": 5e6, "omega_network": 1.0, "omega_euler_bernoulli": 1.0,
           "omega_continuum": 1.0, "ratio_euler_bernoulli": 1.0, "ratio_continuum": 1.0}
    monkeypatch.setattr(pf, "frequency", lambda case: [row])
    assert main(["plate-fidelity", "frequency", "--out-dir", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frequency.csv"]
    assert (tmp_path / "frequency.csv").read_text().startswith("n_rows,youngs,omega_network,")
    assert f"wrote {tmp_path}" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["plate-fidelity", "nope"])
    assert e.value.code == 2
