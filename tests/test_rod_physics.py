"""The DER solver against beam theory, the elastica, Stokes flow and its own convergence."""

import dataclasses

import numpy as np
import pytest

from groundtruth import implicit
from groundtruth.cases import RodCase
from groundtruth.implicit import NewtonSettings
from groundtruth.references import elastica, stokes_terminal_velocity, tip_deflection_uniform
from groundtruth.system import MechanicalSystem

# A rod cantilever: the rod's own section and mass, gravity only, nodes 0 and 1 clamped.
CANTILEVER = RodCase(id="rod_cantilever_test", lumping="line", mid_radius=None, rho_fluid=0.0,
                     viscosity=0.0, clamped_nodes=(0, 1), t_end=1.0, save_dt=0.01, dt=0.01)


def free_length(case):
    """Clamping nodes 0 and 1 fixes the tangent of edge 0: the effective clamp is the middle
    of that edge, so the free length is L - dL/2 (measured: error O(dL^2), below)."""
    return case.length - case.dL / 2


def static_tip(n_nodes, alpha=None, youngs=1e11):
    case = dataclasses.replace(CANTILEVER, n_nodes=n_nodes)
    q = case.rho_metal * case.area * case.gravity
    Le = free_length(case)
    if alpha is not None:
        youngs = q * Le**3 / alpha / case.inertia
    x = case.solve_static(youngs)
    return case, x, q, Le, youngs


def test_static_cantilever_small_load_matches_beam_theory_and_converges():
    errors = []
    for n in (11, 21, 41):
        case, x, q, Le, Y = static_tip(n)
        ref = tip_deflection_uniform(q, Le, Y * case.inertia)
        errors.append(abs(-x[-1, 1] / ref - 1))
    assert errors[1] < 0.01, errors                      # 21 nodes within 1 % (measured 0.13 %)
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(rates > 1.8), (errors, rates)          # second order in dL


@pytest.mark.parametrize("alpha", [5.0, 10.0])
def test_large_deflection_matches_elastica(alpha):
    ref = elastica(alpha)
    errs = []
    for n in (21, 41):
        case, x, q, Le, Y = static_tip(n, alpha=alpha)
        v = -x[-1, 1] / Le
        u = (case.length - x[-1, 0]) / Le
        errs.append((abs(v / ref["tip_v"] - 1), abs(u / ref["tip_u"] - 1)))
    assert max(errs[0]) < 0.01, errs                     # measured 0.28 % / 0.40 % at alpha = 5
    assert max(errs[1]) < max(errs[0]) / 3, errs         # and converging
    assert ref["tip_v"] > 0.4                            # really a large deflection


def test_elastica_reference_small_load_limit():
    assert np.isclose(elastica(0.01)["tip_v"], 0.01 / 8, rtol=1e-3)
    assert np.isclose(elastica(0.0, beta=0.01)["tip_v"], 0.01 / 3, rtol=1e-3)


def test_single_stokes_sphere_reaches_terminal_velocity():
    R, rho_s, rho_f, mu, g = 1e-3, 7000.0, 1000.0, 1.0, 9.81
    m = 4 / 3 * np.pi * R**3 * rho_s
    w = -4 / 3 * np.pi * R**3 * (rho_s - rho_f) * g
    sphere = MechanicalSystem([], np.array([m]), np.array([6 * np.pi * mu * R]),
                              np.array([[0.0, w, 0.0]]), np.array([False]), force_scale=abs(w))
    tau = m / (6 * np.pi * mu * R)
    t = np.linspace(0, 20 * tau, 41)
    pos, vel, _ = implicit.simulate(sphere, np.zeros(3), np.zeros(3), t,
                                    NewtonSettings(dt=tau / 20, rtol=1e-10))
    vT = stokes_terminal_velocity(R, rho_s, rho_f, mu, g)
    assert np.isclose(-vel[-1, 1], vT, rtol=1e-6)
    # the transient follows v = vT (1 - exp(-t/tau)) to first order in dt
    assert np.allclose(-vel[:, 1], vT * (1 - np.exp(-t / tau)), atol=0.03 * vT)


def test_falling_rod_reaches_exact_terminal_speed():
    case = RodCase()
    out = case.simulate(1e9)
    v = out["vel"][-1]
    vT = case.terminal_velocity()
    assert np.isclose(vT, 5.8402e-3, rtol=1e-4)
    np.testing.assert_allclose(v[:, 1], -vT, rtol=1e-5)       # every node, rigid translation
    assert np.abs(v[:, [0, 2]]).max() < 1e-8
    assert np.abs(out["pos"][:, :, 2]).max() == 0.0           # stays in the x-y plane
    x = out["pos"][-1]
    assert np.allclose(x[:, 0], x[::-1, 0].max() - x[::-1, 0] + x[:, 0].min(), atol=1e-9)


def test_backward_euler_is_first_order_in_dt():
    case = dataclasses.replace(RodCase(), t_end=2.0)
    ref = dataclasses.replace(case, dt=0.1 / 64).simulate(1.5e9)["pos"]
    dts = [0.05, 0.025, 0.0125]
    err = [np.abs(dataclasses.replace(case, dt=dt).simulate(1.5e9)["pos"] - ref).max()
           for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(err), 1)[0]
    assert 0.85 < slope < 1.2, (err, slope)


# Halving the internal step (0.01 s -> 0.005 s) moves no saved node by more than this
# (measured 8.6e-6 m at Y = 0.1 and 1.5 GPa, i.e. < 1e-4 L and 30x below the paper's
# smallest reported RMSE of 2.6e-4 m).
DT_HALVING_TOL = 2e-5


@pytest.mark.parametrize("youngs", [pytest.param(1e8, marks=pytest.mark.slow), 1.5e9])
def test_halving_dt_changes_saved_frames_less_than_tolerance(youngs):
    case = RodCase()
    a = case.simulate(youngs)["pos"]
    b = dataclasses.replace(case, dt=case.dt / 2).simulate(youngs)["pos"]
    assert np.linalg.norm(a - b, axis=-1).max() < DT_HALVING_TOL


def test_no_energy_gain_without_drag():
    case = dataclasses.replace(CANTILEVER, t_end=0.5, save_dt=0.002, dt=0.002)
    Y = 2e8
    s = case.system(Y)
    out = case.simulate(Y)
    E = np.array([s.total_energy(q.ravel(), v.ravel()) for q, v in zip(out["pos"], out["vel"])])
    assert np.all(np.diff(E) <= 1e-12 * np.abs(E).max()), np.diff(E).max()
    assert -out["pos"][:, -1, 1].min() > 1e-3               # it really swung


def test_newton_failure_reports_time_and_residual():
    case = dataclasses.replace(RodCase(), t_end=0.2)
    s = case.system(1e9)
    q0, v0 = case.initial_state()
    with pytest.raises(implicit.ConvergenceError, match=r"t = .* residual .* tolerance"):
        implicit.simulate(s, q0.ravel(), v0.ravel(), case.t_save(),
                          NewtonSettings(dt=0.01, rtol=1e-30, max_iter=1, max_halvings=1))
