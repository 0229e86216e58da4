"""Discrete Elastic Plates: hinge kernel, plate energies, the cantilever case against beam
theory, the elastica and the first natural frequency, convergence, energy, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from groundtruth import implicit
from groundtruth.cases import PlateCase
from groundtruth.hinge import HingeTerm, dihedral_angle, dihedral_derivatives, hinge_energy
from groundtruth.mesh import strip_mesh
from groundtruth.plate import clamp_mask, lumped_mass, plate_terms, spring_stiffness
from groundtruth.references import elastica

CASE = PlateCase()
Y_MID = 5e6


def rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def folded_hinges(n: int, seed: int = 0):
    """``n`` random hinges folded by a known angle phi, |phi| in [0.3, 2.8] rad, both signs,
    with uneven triangles, a small out-of-plane jitter and a random rigid motion."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0.3, 2.8, n) * np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    l = rng.uniform(0.5, 2.0, n)
    a, b = rng.uniform(0.2, 1.5, n), rng.uniform(0.2, 1.5, n)
    t2, t3 = rng.uniform(-0.5, 1.5, n) * l, rng.uniform(-0.5, 1.5, n) * l
    x = np.zeros((n, 4, 3))
    x[:, 1, 1] = l
    x[:, 2] = np.stack([-a, t2, 0 * a], 1)
    x[:, 3] = np.stack([b * np.cos(phi), t3, -b * np.sin(phi)], 1)
    for k in range(n):
        x[k] = x[k] @ rotation(rng).T + rng.normal(size=3)
    return x, phi


def split(x):
    return [x[:, k] for k in range(4)]


class TestDihedralAngle:
    def test_angle_and_sign_convention(self):
        x, phi = folded_hinges(40)
        np.testing.assert_allclose(dihedral_angle(*split(x)), phi, atol=1e-12)
        assert (phi > 0).any() and (phi < 0).any()

    def test_gradient_matches_finite_differences(self):
        x, _ = folded_hinges(40, seed=1)
        x += 0.05 * np.random.default_rng(2).normal(size=x.shape)   # non-planar triangles too
        theta, grad, _ = dihedral_derivatives(*split(x), order=1)
        assert (theta > 0.3).any() and (theta < -0.3).any()
        q, h = x.reshape(-1, 12), 1e-6
        fd = np.empty_like(grad)
        for i in range(12):
            qp, qm = q.copy(), q.copy()
            qp[:, i] += h
            qm[:, i] -= h
            fd[:, i] = (dihedral_angle(*split(qp.reshape(-1, 4, 3)))
                        - dihedral_angle(*split(qm.reshape(-1, 4, 3)))) / (2 * h)
        scale = np.abs(grad).max(axis=1, keepdims=True)
        assert np.max(np.abs(grad - fd) / scale) < 1e-7

    def test_hessian_matches_finite_differences(self):
        x, _ = folded_hinges(40, seed=3)
        x += 0.05 * np.random.default_rng(4).normal(size=x.shape)
        _, grad, hess = dihedral_derivatives(*split(x), order=2)
        np.testing.assert_allclose(hess, hess.transpose(0, 2, 1), atol=1e-12)
        q, h = x.reshape(-1, 12), 1e-6
        fd = np.empty_like(hess)
        for i in range(12):
            qp, qm = q.copy(), q.copy()
            qp[:, i] += h
            qm[:, i] -= h
            gp = dihedral_derivatives(*split(qp.reshape(-1, 4, 3)), order=1)[1]
            gm = dihedral_derivatives(*split(qm.reshape(-1, 4, 3)), order=1)[1]
            fd[:, :, i] = (gp - gm) / (2 * h)
        scale = np.abs(hess).reshape(len(x), -1).max(axis=1)[:, None, None]
        assert np.max(np.abs(hess - fd) / scale) < 1e-6

    def test_classic_gradient_of_the_wing_tips(self):
        """d theta/d x2 = -|e| a/|a|^2, d theta/d x3 = -|e| b/|b|^2 (Bridson et al. 2003)."""
        x, _ = folded_hinges(20, seed=5)
        x0, x1, x2, x3 = split(x)
        e = x1 - x0
        a, b = np.cross(e, x2 - x0), np.cross(x3 - x0, e)
        l = np.linalg.norm(e, axis=1)[:, None]
        grad = dihedral_derivatives(x0, x1, x2, x3, order=1)[1]
        np.testing.assert_allclose(grad[:, 6:9], -l * a / np.sum(a * a, 1)[:, None], rtol=1e-10)
        np.testing.assert_allclose(grad[:, 9:12], -l * b / np.sum(b * b, 1)[:, None], rtol=1e-10)

    def test_invariant_under_rigid_motion(self):
        x, _ = folded_hinges(20, seed=6)
        rng = np.random.default_rng(7)
        R, t = rotation(rng), rng.normal(size=3)
        theta, grad, hess = dihedral_derivatives(*split(x))
        theta2, grad2, _ = dihedral_derivatives(*split(x @ R.T + t))
        np.testing.assert_allclose(theta2, theta, atol=1e-12)
        np.testing.assert_allclose(grad2.reshape(-1, 4, 3), grad.reshape(-1, 4, 3) @ R.T,
                                   atol=1e-10)
        # translations are in the Hessian's null space; for a rotation omega, differentiating
        # grad theta . (omega x x) = 0 gives hess (omega x x) = omega x grad theta per node
        scale = np.abs(hess).max()
        for k in range(3):
            t_mode = np.tile(np.eye(3)[k], 4)
            assert np.abs(hess @ t_mode).max() < 1e-10 * scale
            r_mode = np.cross(np.eye(3)[k], x).reshape(len(x), 12)
            lhs = np.einsum("nij,nj->ni", hess, r_mode)
            rhs = np.cross(np.eye(3)[k], grad.reshape(-1, 4, 3)).reshape(len(x), 12)
            assert np.abs(lhs - rhs).max() < 1e-10 * scale


class TestHingeEnergy:
    def test_energy_gradient_and_hessian(self):
        x, _ = folded_hinges(30, seed=8)
        rng = np.random.default_rng(9)
        theta_bar, k = rng.uniform(-0.5, 0.5, 30), rng.uniform(0.5, 2.0, 30)
        E, g, H = hinge_energy(*split(x), theta_bar, k)
        th = dihedral_angle(*split(x))
        np.testing.assert_allclose(E, 0.5 * k * (th - theta_bar) ** 2)
        q, h = x.reshape(-1, 12), 1e-6
        for i in range(12):
            qp, qm = q.copy(), q.copy()
            qp[:, i] += h
            qm[:, i] -= h
            Ep, gp, _ = hinge_energy(*split(qp.reshape(-1, 4, 3)), theta_bar, k, order=1)
            Em, gm, _ = hinge_energy(*split(qm.reshape(-1, 4, 3)), theta_bar, k, order=1)
            np.testing.assert_allclose((Ep - Em) / (2 * h), g[:, i], rtol=1e-6, atol=1e-8)
            np.testing.assert_allclose((gp - gm) / (2 * h), H[:, :, i], rtol=1e-5, atol=1e-6)

    def test_term_evaluates_on_gathered_dofs(self):
        x, _ = folded_hinges(5, seed=10)
        term = HingeTerm(np.arange(20).reshape(5, 4), 0.1, 2.0)
        E, g, H = term.evaluate(x.reshape(-1)[term.dofs], 2)
        E2, g2, H2 = hinge_energy(*split(x), 0.1, 2.0)
        np.testing.assert_array_equal(E, E2)
        assert term.dofs.shape == (5, 12) and H.shape == (5, 12, 12)


def small_case(**kw) -> PlateCase:
    return dataclasses.replace(CASE, n_length=6, grading=2.0, **kw)


def deformed(case: PlateCase, seed: int, amplitude: float = 0.02) -> np.ndarray:
    q = case.rest_positions()
    x = q[:, 0]
    rng = np.random.default_rng(seed)
    q[:, 2] -= 0.8 * x**2 + amplitude * rng.normal(size=len(q))      # strongly bent, rough
    q[:, :2] += 0.1 * amplitude * rng.normal(size=(len(q), 2))
    return q.ravel()


class TestPlateSystem:
    def test_gradient_and_hessian_of_the_assembled_energy(self):
        case = small_case()
        s = case.system(Y_MID)
        q = deformed(case, 0)
        g, H = s.gradient(q), s.hessian(q)
        h = 1e-7
        for i in range(0, q.size, 5):
            dq = np.zeros(q.size)
            dq[i] = h
            fd_e = (s.energy(q + dq) - s.energy(q - dq)) / (2 * h)
            fd_g = (s.gradient(q + dq) - s.gradient(q - dq)) / (2 * h)
            assert fd_e == pytest.approx(g[i], rel=1e-5, abs=1e-7 * np.abs(g).max())
            np.testing.assert_allclose(fd_g, H[:, i], atol=1e-5 * np.abs(H).max())

    def test_zero_force_under_rigid_motion(self):
        case = small_case()
        s = case.system(Y_MID)
        rest = case.rest_positions()
        rng = np.random.default_rng(1)
        moved = rest @ rotation(rng).T + rng.normal(size=3)
        assert s.energy(moved.ravel()) < 1e-20
        typical = case.line_load * case.length / s.n_nodes        # a node's weight
        free = ~s.fixed_dofs
        assert np.abs(s.gradient(moved.ravel())[free]).max() < 1e-8 * typical
        q = deformed(case, 2)
        R, t = rotation(rng), rng.normal(size=3)
        q2 = (q.reshape(-1, 3) @ R.T + t).ravel()
        assert s.energy(q2) == pytest.approx(s.energy(q), rel=1e-10)
        g, g2 = s.gradient(q).reshape(-1, 3), s.gradient(q2).reshape(-1, 3)
        np.testing.assert_allclose(g2, g @ R.T, atol=1e-9 * np.abs(g).max())

    def test_mass_load_and_clamp(self):
        s = CASE.system(Y_MID)
        nodes, tri = CASE.rest_positions(), CASE.mesh()[1]
        total = CASE.density * CASE.thickness * CASE.width * (np.ptp(nodes[:, 0]))
        assert s.mass.sum() == pytest.approx(total)
        np.testing.assert_allclose(s.force[:, 2], -9.81 * s.mass)
        np.testing.assert_allclose(s.damping, CASE.damping_rate * s.mass)
        fixed = CASE.node_type() == 1
        assert fixed.sum() == 2 * (CASE.n_width + 1)
        # the clamp line x = 0 lies midway between the two clamped rows
        assert set(np.round(nodes[fixed, 0], 9)) == {-CASE.clamp_gap / 2, CASE.clamp_gap / 2}
        assert nodes[:, 0].max() == pytest.approx(CASE.length)
        assert s.energy(nodes.ravel()) == 0.0
        assert len(tri) == 2 * CASE.n_width * (CASE.n_length + CASE.n_clamp_rows - 1)

    def test_registered_with_paper_metadata(self):
        from benchmarks.suite.registry import CASES

        case = CASES["plate_hanging"]
        assert case == PlateCase() and case.id == "plate_hanging"
        assert (case.n_train, case.n_test, case.n_frames) == (30, 6, 501)
        assert case.save_dt == 0.003 and case.dt <= case.save_dt
        lo, hi = case.youngs_train
        assert (lo, hi) == (2.5e6, 7.5e6) and case.youngs_test == (2.5e6, 7.5e6)
        assert case.rest_positions().shape[0] == 150
        y = case.sample_youngs("train")
        assert y.shape == (30,) and y.min() >= lo and y.max() <= hi


def static_tip(case: PlateCase, youngs: float) -> np.ndarray:
    q = case.solve_static(youngs)
    return q[-(case.n_width + 1):].mean(axis=0)


class TestStatics:
    def test_stiff_plate_small_load_matches_euler_bernoulli(self):
        """alpha = q L^3 / EI = 0.1: tip deflection q L^4 / (8 EI) within 2 % (EI = Y w h^3/12
        of the free length; measured +0.2 %)."""
        alpha = 0.1
        g = alpha * CASE.bending_rigidity(Y_MID) / (CASE.line_load / CASE.gravity * CASE.length**3)
        case = dataclasses.replace(CASE, gravity=g, newton_rtol=1e-3)
        tip = static_tip(case, Y_MID)
        beam = case.line_load * case.length**4 / (8 * case.bending_rigidity(Y_MID))
        assert -tip[2] == pytest.approx(beam, rel=0.02)
        assert -tip[2] == pytest.approx(beam, rel=0.005)       # what it actually achieves

    @pytest.mark.parametrize("youngs", [5e9, 5e8, 5e6])
    def test_static_shape_matches_the_elastica(self, youngs):
        """Centre line against the inextensible uniform-load elastica at the same arc length:
        alpha = 28, 283 and 2.8e4 (the dataset's middle modulus); within 2 % of L (measured
        0.03 %, 0.02 % and 0.15 %, the last being mostly the physical stretch q L^2 / 2 EA)."""
        case = CASE
        el = elastica(case.load_parameter(youngs), n_mesh=4001)
        q = case.solve_static(youngs)
        rest = case.rest_positions()
        mid = (case.node_type() == 0) & (np.abs(rest[:, 1]) < 1e-12)
        s = rest[mid, 0] / case.length
        x_el, v_el = np.interp(s, el["s"], el["x"]), -np.interp(s, el["s"], el["y"])
        err = np.hypot(q[mid, 0] / case.length - x_el, -q[mid, 2] / case.length - v_el)
        assert err.max() < 0.02
        assert err.max() < 0.004
        assert -q[mid][-1, 2] / case.length == pytest.approx(v_el[-1], rel=0.02)

    def test_mirror_symmetry_is_kept(self):
        q = CASE.solve_static(Y_MID)
        rest = CASE.rest_positions()
        order = np.lexsort((np.round(-rest[:, 1], 9), np.round(rest[:, 0], 9)))
        mirror = q[order] * [1, -1, 1]
        back = np.lexsort((np.round(rest[:, 1], 9), np.round(rest[:, 0], 9)))
        np.testing.assert_allclose(mirror, q[back], atol=1e-9)


class TestStaticConvergence:
    """Tip of the static cantilever at alpha = 283 under refinement of the rows (n_length
    12 -> 96 at fixed grading map): successive differences shrink at second order (measured
    1.7-2.0), and the tip approaches the elastica (0.06 % of L at the default 48 rows,
    0.02 % at 96)."""

    expected_rate = 2.0
    youngs = 5e8

    def test_rate(self):
        tips = np.array([static_tip(dataclasses.replace(CASE, n_length=n), self.youngs)
                         for n in (12, 24, 48, 96)])
        diffs = np.linalg.norm(np.diff(tips[:, [0, 2]], axis=0), axis=1)
        rate = -np.polyfit(np.log2([1, 2, 4]), np.log2(diffs), 1)[0]
        assert rate == pytest.approx(self.expected_rate, abs=0.3)
        el = elastica(CASE.load_parameter(self.youngs), n_mesh=4001)
        err = np.hypot(tips[:, 0] - (1 - el["tip_u"]), -tips[:, 2] - el["tip_v"])
        assert err[2] < 1e-3 and err[3] < 3e-4 and np.all(np.diff(err) < 0)


class TestDynamics:
    def test_first_natural_frequency(self):
        """Free vibration (no gravity, no damping) from a slightly bent static shape: the
        period of the tip matches omega_1 = 1.875^2 sqrt(EI / (rho w h L^4)) within 3 %
        (measured -0.1 %)."""
        case = dataclasses.replace(CASE, damping_rate=0.0)
        EI, mu = case.bending_rigidity(Y_MID), case.density * case.width * case.thickness
        omega = 1.875104**2 * np.sqrt(EI / (mu * case.length**4))
        period = 2 * np.pi / omega
        bent = dataclasses.replace(case, gravity=0.2 * EI / (mu * case.length**3),
                                   newton_rtol=1e-3)
        q0 = bent.solve_static(Y_MID).ravel()
        system = bent.system(Y_MID)
        system.force[:] = 0.0
        t = np.arange(401) * period / 200
        pos, _, _ = implicit.simulate(system, q0, np.zeros_like(q0), t,
                                      implicit.NewtonSettings(dt=period / 200, rtol=1e-3))
        z = pos.reshape(len(t), -1, 3)[:, -(case.n_width + 1):, 2].mean(axis=1)
        i = np.flatnonzero(np.sign(z[:-1]) * np.sign(z[1:]) < 0)
        crossings = t[i] - z[i] * (t[i + 1] - t[i]) / (z[i + 1] - z[i])
        assert len(crossings) >= 3
        measured = 2 * np.mean(np.diff(crossings))
        assert measured == pytest.approx(period, rel=0.03)
        assert measured == pytest.approx(period, rel=0.005)

    def test_energy_never_grows_without_damping(self):
        case = dataclasses.replace(CASE, damping_rate=0.0)
        res = case.simulate(Y_MID, t_end=0.15)
        s = case.system(Y_MID)
        E = np.array([s.total_energy(p.ravel(), v.ravel())
                      for p, v in zip(res["pos"], res["vel"], strict=True)])
        scale = case.line_load * case.length**2
        assert np.all(np.diff(E) <= 1e-9 * scale)
        assert E[-1] < E[0] and -np.min(res["pos"][-1][:, 2]) > 0.05   # it fell and dissipated

    def test_plate_swings_with_mild_damping(self):
        """The default damping leaves a swing: the tip passes under the clamp to x < 0."""
        res = CASE.simulate(Y_MID, t_end=0.75)
        tip_x = res["pos"][:, -(CASE.n_width + 1):, 0].mean(axis=1)
        assert tip_x.min() < -0.3
        assert res["stats"]["halvings"] == 0


@pytest.mark.slow
class TestDynamicConvergence:
    """Tip trajectory over the first fall and swing (0.75 s, Y = 2.5 MPa, the most flexible)."""

    youngs = 2.5e6
    t_end = 0.75

    def tip(self, **kw):
        case = dataclasses.replace(CASE, **kw)
        res = case.simulate(self.youngs, t_end=self.t_end)
        return res["pos"][:, -(case.n_width + 1):].mean(axis=1)

    def test_time_step(self):
        """Backward Euler is first order: the distance to a dt = 0.00025 s run halves with dt."""
        ref = self.tip(dt=0.00025)
        err = [np.sqrt(np.mean(np.sum((self.tip(dt=dt) - ref) ** 2, axis=1)))
               for dt in (0.003, 0.0015)]
        assert err[1] < 0.7 * err[0]
        assert err[0] < 0.05

    def test_mesh(self):
        tips = [self.tip(n_length=n, n_width=w) for n, w in ((24, 2), (48, 2), (96, 2))]
        d = [np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1)))
             for a, b in zip(tips[:-1], tips[1:], strict=True)]
        assert d[1] < 0.6 * d[0]
        assert d[1] < 0.01


class TestBadInput:
    @pytest.mark.parametrize("field, value", [
        ("thickness", 0.0), ("thickness", -1e-3), ("width", 0.0), ("density", -1.0),
        ("grading", 0.0), ("clamp_gap", 0.0), ("damping_rate", -0.1), ("n_length", 0),
        ("n_width", 1.5), ("pattern", "spiral"), ("spring_weights", "x"),
    ])
    def test_case_fields(self, field, value):
        with pytest.raises(ValueError, match=f"PlateCase.{field}"):
            PlateCase(**{field: value})

    def test_clamp_needs_two_rows(self):
        with pytest.raises(ValueError, match="n_clamp_rows must be an int >= 2"):
            PlateCase(n_clamp_rows=1)

    def test_clamp_gap_must_fit_before_the_first_row(self):
        with pytest.raises(ValueError, match="clamp_gap"):
            PlateCase(clamp_gap=0.5)

    def test_clamp_that_fixes_no_node(self):
        nodes, _ = strip_mesh(np.linspace(0, 1, 5), 0.1, 2)
        with pytest.raises(ValueError, match="fixes no node"):
            clamp_mask(nodes, -0.1)
        with pytest.raises(ValueError, match="fixes 1 row"):
            clamp_mask(nodes, 0.0)
        assert clamp_mask(nodes, 0.25).sum() == 6

    @pytest.mark.parametrize("thickness", [0.0, -1e-3, np.nan])
    def test_terms_reject_bad_thickness(self, thickness):
        nodes, tri = strip_mesh(np.linspace(0, 1, 5), 0.1, 2)
        with pytest.raises(ValueError, match="thickness"):
            plate_terms(nodes, tri, 5e6, thickness)
        with pytest.raises(ValueError, match="thickness"):
            lumped_mass(nodes, tri, 1200.0, thickness)

    def test_terms_reject_degenerate_triangle(self):
        nodes, tri = strip_mesh(np.linspace(0, 1, 5), 0.1, 2)
        nodes[tri[4, 2]] = nodes[tri[4, 0]]
        with pytest.raises(ValueError, match="degenerate triangle"):
            plate_terms(nodes, tri, 5e6, 1e-3)

    def test_bad_youngs(self):
        with pytest.raises(ValueError, match="youngs"):
            CASE.system(-1.0)


def test_spring_calibration():
    """Equilateral interior edges keep the DEP constant; short edges of skinny cells are
    stiffened so that the strip's tensile stiffness is Y h w."""
    l0 = np.array([1.0])
    dep = spring_stiffness(5e6, 1e-3, l0)
    assert spring_stiffness(5e6, 1e-3, l0, np.array([np.sqrt(3) / 2]))[0] == pytest.approx(dep[0])
    s = CASE.system(Y_MID)
    stretch = s.terms[0]
    x = CASE.rest_positions()
    d = x[stretch.edges[:, 1]] - x[stretch.edges[:, 0]]
    along_x = np.abs(d[:, 1]) < 1e-12
    # the springs along x between two rows act in parallel: EA = sum of k_s (k_s eps is a force)
    for row in (3, 10):
        between = np.isclose(x[stretch.edges[:, 0], 0], x[row * (CASE.n_width + 1), 0]) & along_x
        assert between.sum() == CASE.n_width + 1
        EA = stretch.k[between].sum()
        assert EA == pytest.approx(Y_MID * CASE.thickness * CASE.width, rel=1e-9)


def test_cli_static_writes_one_frame(tmp_path):
    """``meshbench simulate plate_hanging --youngs Y --static --out F.npz``."""
    from benchmarks.cli import main
    from groundtruth import store

    out = tmp_path / "static.npz"
    assert main(["simulate", "plate_hanging", "--youngs", "5e6", "--static",
                 "--out", str(out)]) == 0
    data = store.load_npz(out, "plate_hanging", CASE.hash())
    assert data["pos"].shape == (1, 1, 150, 3) and data["t"].tolist() == [0.0]
    assert data["cells"].shape == (2 * 2 * 49, 3) and data["node_type"].sum() == 6
    np.testing.assert_allclose(data["pos"][0, 0], CASE.solve_static(5e6))
    assert data["pos"][0, 0, :, 2].min() < -0.99          # a soft plate hangs down
