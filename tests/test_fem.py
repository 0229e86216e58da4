"""The scikit-fem total-Lagrangian SVK model: kernel, statics, dynamics, plate strip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize

from groundtruth import fem
from groundtruth import references as br
from groundtruth.implicit import NewtonSettings

R0, L, RHO = 1e-3, 0.1, 7000.0
HEIGHT, THICK = fem.rod_section(R0)
AREA, INERTIA = math.pi * R0**2, math.pi * R0**4 / 4
STATIC = NewtonSettings(rtol=1e-8, max_iter=40)


def rod_model(youngs=1e9, poisson=0.0, nx=20, ny=1, gravity=9.81, **kw):
    return fem.cantilever(L, HEIGHT, fem.Material(youngs, poisson, RHO, THICK), nx, ny,
                          gravity=gravity, **kw)


def tip(model, u):
    return model.probe_matrix(fem.tip_point(model)) @ u


# --- material and section --------------------------------------------------------------------


def test_rod_section_has_the_rods_area_and_inertia():
    assert HEIGHT * THICK == pytest.approx(AREA, rel=1e-14)
    assert THICK * HEIGHT**3 / 12 == pytest.approx(INERTIA, rel=1e-14)


def test_lame_constants_are_computed_here():
    E, nu = 2.0e9, 0.3
    lam, mu = fem.lame_plane_stress(E, nu)
    assert lam == pytest.approx(E * nu / (1 - nu**2)) and mu == pytest.approx(E / 2.6)
    lam, mu = fem.lame_plane_strain(E, nu)
    assert lam == pytest.approx(E * nu / (1.3 * 0.4)) and mu == pytest.approx(E / 2.6)
    assert fem.Material(E, nu, 1.0, 1.0).plane_modulus == pytest.approx(E)
    assert fem.Material(E, nu, 1.0, 1.0, "plane_strain").plane_modulus == \
        pytest.approx(E / (1 - nu**2))


@pytest.mark.parametrize("kw, field", [({"poisson": 0.5}, "poisson"),
                                       ({"youngs": -1.0}, "youngs"),
                                       ({"model": "axisymmetric"}, "model")])
def test_bad_material_is_named(kw, field):
    args = {"youngs": 1e9, "poisson": 0.3, "density": 1.0, "thickness": 1.0, **kw}
    with pytest.raises(ValueError, match=f"Material.{field}"):
        fem.Material(**args)


def test_bad_integrator_lists_the_valid_ones():
    with pytest.raises(ValueError, match="backward_euler, newmark"):
        fem.get_integrator("rk4")


def test_bad_mesh_sizes_are_rejected():
    with pytest.raises(ValueError, match="nx|length"):
        rod_model(nx=0)
    with pytest.raises(ValueError, match="ny"):
        rod_model(ny=0)


# --- the kernel --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small():
    return rod_model(nx=4, ny=2, poisson=0.3)


def test_kernel_matches_scikit_fem_forms(small):
    from skfem import asm

    rng = np.random.default_rng(0)
    u = rng.normal(size=small.ndof) * 2e-4
    res, tan = fem.reference_forms(small.material)
    w = small.basis.interpolate(u)
    f_ref = asm(res, small.basis, u=w)
    K_ref = asm(tan, small.basis, u=w).toarray()[np.ix_(small.free, small.free)]
    _, f, K = small.evaluate(u)
    assert np.allclose(f, f_ref, rtol=0, atol=1e-12 * np.abs(f_ref).max())
    assert np.allclose(K.toarray(), K_ref, rtol=0, atol=1e-12 * np.abs(K_ref).max())


def test_force_and_tangent_by_finite_differences(small):
    rng = np.random.default_rng(1)
    u = rng.normal(size=small.ndof) * 3e-4
    d = rng.normal(size=small.ndof) * 1e-7
    d[small.fixed] = 0.0
    e_p, f_p, _ = small.evaluate(u + d, 1)
    e_m, f_m, _ = small.evaluate(u - d, 1)
    _, f, K = small.evaluate(u)
    assert (e_p - e_m) / 2 == pytest.approx(f @ d, rel=1e-6)
    Kd = K @ d[small.free]
    assert np.allclose((f_p - f_m)[small.free] / 2, Kd, rtol=0, atol=1e-6 * np.abs(Kd).max())
    assert abs(K - K.T).max() < 1e-10 * abs(K).max()


def test_rigid_motion_gives_no_force(small):
    X = small.basis.doflocs                                   # (2, ndof): location of each dof
    c, s = math.cos(1.1), math.sin(1.1)
    comp = np.arange(small.ndof) % 2                           # interleaved (x, y)
    rx, ry = c * X[0] - s * X[1] + 0.3, s * X[0] + c * X[1] - 0.2
    u = np.where(comp == 0, rx - X[0], ry - X[1])
    e, f, _ = small.evaluate(u, 1)
    stretch = np.where(comp == 0, 1e-6 * X[0], 0.0)             # strain 1e-6
    scale = np.abs(small.evaluate(stretch, 1)[1]).max() * 1e6     # force at unit strain, N
    assert abs(e) < 1e-20 and np.abs(f).max() < 1e-10 * scale


def test_probes_interleave_components(small):
    P = small.probe_matrix(np.array([[0.05, L], [0.0, 0.0]]))
    u = np.where(np.arange(small.ndof) % 2 == 0, 1.0, 2.0)
    assert np.allclose(P @ u, [1.0, 1.0, 2.0, 2.0])


def test_mass_and_gravity_are_consistent(small):
    m_total = RHO * AREA * L
    one_y = (np.arange(small.ndof) % 2 == 1).astype(float)
    assert one_y @ small.M @ one_y == pytest.approx(m_total, rel=1e-12)
    assert small.F.sum() == pytest.approx(-m_total * 9.81, rel=1e-12)


# --- statics -------------------------------------------------------------------------------


@pytest.mark.parametrize("poisson", [0.0, 0.3])
def test_static_cantilever_matches_beam_theory(poisson):
    """q L^4 / (8 EI) within 0.5 % (measured: -0.02 % at nu = 0, -0.23 % at nu = 0.3)."""
    g = 9.81e-4                                                   # small load: linear regime
    m = rod_model(poisson=poisson, nx=20, gravity=g)
    u = fem.solve_static(m, STATIC, 1)
    ref = br.tip_deflection_uniform(RHO * AREA * g, L, 1e9 * INERTIA)
    assert -tip(m, u)[1] == pytest.approx(ref, rel=5e-3)


def test_tip_point_load_through_probes():
    """A point weight at the tip (probes): P L^3 / (3 EI) within 0.5 %."""
    P = 1e-4
    pts = fem.PointLoads(np.array([[L], [0.0]]), [0.0], [0.0], [P])
    m = rod_model(nx=20, gravity=0.0, points=pts)
    u = fem.solve_static(m, STATIC, 1)
    assert -tip(m, u)[1] == pytest.approx(br.tip_deflection_point(P, L, 1e9 * INERTIA), rel=5e-3)


@pytest.mark.parametrize("alpha", [4.0, 10.0])
def test_static_cantilever_matches_the_elastica(alpha):
    """Large deflection (alpha = q L^3/EI >= 4): tip within 1 % of the elastica
    (measured with nx = 40: +0.02 % / +0.04 % at alpha = 4, +0.03 % / +0.05 % at 10)."""
    q = RHO * AREA * 9.81
    m = rod_model(youngs=q * L**3 / (alpha * INERTIA), nx=40)
    u = fem.solve_static(m, STATIC, 5)
    dx, dy = br.elastica_tip(alpha)
    got = tip(m, u) / L
    assert got[1] == pytest.approx(dy, rel=1e-2)
    assert got[0] == pytest.approx(dx, rel=1e-2)


def test_elastica_reference_limits():
    assert br.elastica_tip(1e-3)[1] == pytest.approx(-1e-3 / 8, rel=1e-4)
    assert br.elastica_tip(1.0)[1] == pytest.approx(-0.12347, abs=2e-5)   # tabulated


# --- dynamics ------------------------------------------------------------------------------


@pytest.mark.parametrize("poisson", [0.0, 0.3])
def test_first_frequency_matches_beam_theory(poisson):
    """(beta_1 L)^2 sqrt(EI/(rho A L^4)) within 1 % (measured: +0.005 %, +0.11 % at nx = 20)."""
    w = rod_model(poisson=poisson).natural_frequencies(2)
    ref = br.cantilever_frequency(1e9 * INERTIA, RHO * AREA, L)
    assert w[0] == pytest.approx(ref, rel=1e-2)
    assert w[1] == pytest.approx(br.cantilever_frequency(1e9 * INERTIA, RHO * AREA, L, 2),
                                 rel=1e-2)


def test_tip_mass_frequency_through_probes():
    """Tip point mass mu = m_tip / (rho A L): 1 + cos b cosh b + mu b (cos b sinh b -
    sin b cosh b) = 0 for b = beta L."""
    mu = 0.5
    pts = fem.PointLoads(np.array([[L], [0.0]]), [mu * RHO * AREA * L], [0.0], [0.0])
    w = rod_model(points=pts).natural_frequencies(1)[0]
    f = lambda b: 1 + math.cos(b) * math.cosh(b) + mu * b * (math.cos(b) * math.sinh(b)
                                                              - math.sin(b) * math.cosh(b))
    b = scipy.optimize.brentq(f, 0.5, 1.875)
    ref = b**2 * math.sqrt(1e9 * INERTIA / (RHO * AREA * L**4))
    assert w == pytest.approx(ref, rel=1e-2)


def _mode_one_release(amplitude=1e-4, damping=0.0):
    """Model without gravity and an initial state along its first mode (tip = amplitude)."""
    m = rod_model(youngs=1e8, nx=8, gravity=0.0, damping=damping)
    w, phi = m.modes(1)
    P = m.probe_matrix(fem.tip_point(m))
    return m, P, phi[0] * (amplitude / (P @ phi[0])[1]), 2 * math.pi / w[0]


class TestIntegratorOrder:
    """Observed order from three step sizes (dt, dt/2, dt/4) of a first-mode free vibration:
    log2(|u_dt - u_dt/2| / |u_dt/2 - u_dt/4|), max over the saved frames."""

    expected = {"backward_euler": 1.0, "newmark": 2.0}
    # (t_end / T, saved frames, steps per T): every save interval holds whole steps
    windows = {"backward_euler": (0.1, 2, 100), "newmark": (1.0, 5, 48)}

    @pytest.mark.parametrize("integrator", ["backward_euler", "newmark"])
    def test_order(self, integrator):
        m, P, u0, T = _mode_one_release()
        frac, frames, n = self.windows[integrator]
        t = np.linspace(0.0, frac * T, frames)
        runs = [(P @ fem.simulate(m, t, NewtonSettings(dt=T / k, rtol=1e-10), integrator,
                                  u0=u0)[0].T)[1] for k in (n, 2 * n, 4 * n)]
        rate = math.log2(np.abs(runs[0] - runs[1]).max() / np.abs(runs[1] - runs[2]).max())
        assert rate == pytest.approx(self.expected[integrator], abs=0.25)


def test_free_vibration_period_and_mass_proportional_damping():
    """Newmark free vibration along mode 1 with C = c M returns to the tip amplitude
    exp(-c t / 2) after each damped period 2 pi / sqrt(omega^2 - c^2/4)."""
    m0, P, u0, T = _mode_one_release()
    c = 0.1 * 2 * math.pi / T                                      # 1.6 % of critical
    m = rod_model(youngs=1e8, nx=8, gravity=0.0, damping=c)
    Td = 2 * math.pi / math.sqrt((2 * math.pi / T) ** 2 - c**2 / 4)
    t = np.array([0.0, Td, 2 * Td])
    u, _, _ = fem.simulate(m, t, NewtonSettings(dt=T / 200, rtol=1e-10), "newmark", u0=u0)
    tip_y = (P @ u.T)[1]
    assert tip_y[1:] / tip_y[0] == pytest.approx(np.exp(-c * t[1:] / 2), rel=2e-3)


def test_newmark_conserves_energy_and_backward_euler_dissipates():
    """Released from straight under gravity (large deflection): Newmark's total energy stays
    within 0.2 % of the work of gravity, backward Euler's decreases monotonically."""
    m = rod_model(youngs=1e8, nx=8)
    t = np.linspace(0.0, 0.3, 7)
    energies = {}
    for name in fem.INTEGRATORS:
        u, v, _ = fem.simulate(m, t, NewtonSettings(dt=1e-3, rtol=1e-10), name)
        energies[name] = np.array([m.total_energy(a, b) for a, b in zip(u, v, strict=True)])
    scale = abs(m.F @ u[1])                                       # work of gravity, J
    assert np.abs(energies["newmark"]).max() < 2e-3 * scale
    assert np.all(np.diff(energies["backward_euler"]) < 0)


# --- the plate strip -----------------------------------------------------------------------


def test_plate_strip_model_matches_dep_rigidity():
    mat = fem.plate_strip_material(5e6)
    assert mat.model == "plane_strain" and mat.poisson == pytest.approx(1 / 3)
    assert mat.plane_modulus == pytest.approx(5e6, rel=1e-12)     # EI = Y w h^3/12, EA = Y w h


def test_plate_strip_static_small_load_matches_beam_theory():
    """Stiff strip under small load: q L^4/(8 EI), EI = Y w h^3/12, within 0.5 %
    (measured -0.07 % with 100 elements graded 4:1)."""
    Y, g, h, w = 5e6, 9.81e-6, 1e-3, 0.1
    m = fem.plate_strip(Y, nx=100, gravity=g)
    u = fem.solve_static(m, STATIC, 1)
    ref = br.tip_deflection_uniform(1200 * h * w * g, 1.0, Y * w * h**3 / 12)
    assert -tip(m, u)[1] == pytest.approx(ref, rel=5e-3)


def test_plate_strip_static_heavy_chain_matches_the_elastica():
    """The plate case's own load, q L^3/EI = 2.8e4: the tip within 2 mm of the inextensible
    elastica (measured: dx 1.1 mm, dy -0.4 mm with 100 elements; gravity stretches the strip
    by about 1.2 mm, which the elastica ignores)."""
    Y, h, w = 5e6, 1e-3, 0.1
    m = fem.plate_strip(Y, nx=100)
    u = fem.solve_static(m, NewtonSettings(rtol=1e-8, max_iter=50), 20)
    alpha = 1200 * h * w * 9.81 / (Y * w * h**3 / 12)
    dx, dy = br.elastica_tip(alpha)
    got = tip(m, u)
    assert abs(got[0] - dx) < 2e-3 and abs(got[1] - dy) < 2e-3


def test_plate_strip_tip_first_falls_freely():
    """Released from straight, the strip's tip does not feel the clamp for a while: over the
    first 30 backward-Euler steps of the plate case's 3 ms it follows the discrete free fall
    u_n = -g dt^2 n (n + 1) / 2 within 2 %."""
    dt, n = 0.003, np.array([10, 20, 30])
    out = fem.fem_plate_strip(5e6, np.arange(31) * dt, 0.0, dt=dt, nx=50)
    assert out["stats"]["halvings"] == 0
    free_fall = -9.81 * dt**2 * n * (n + 1) / 2
    assert out["tip"][n, 1] == pytest.approx(free_fall, rel=2e-2)
