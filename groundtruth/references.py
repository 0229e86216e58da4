"""Classical references the solvers are measured against (beam theory, elastica, Stokes).

Lengths in m, forces in N, stiffness EI in N m^2. The elastica is the inextensible
Euler–Bernoulli cantilever at large deflection, clamped at s = 0 and free at s = 1
(arc length scaled by L), with theta the slope angle below the horizontal.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import cumulative_trapezoid, solve_bvp

BETA_L = (1.8751040687, 4.6940911330, 7.8547574382)  # cantilever eigenvalues beta_n L


def cantilever_uniform_tip(q: float, L: float, EI: float) -> float:
    """Small-deflection tip deflection of a cantilever under uniform load: q L^4 / (8 EI)."""
    return q * L**4 / (8.0 * EI)


def cantilever_point_tip(P: float, L: float, EI: float) -> float:
    """Small-deflection tip deflection under a tip load: P L^3 / (3 EI)."""
    return P * L**3 / (3.0 * EI)


def cantilever_frequency(n: int, EI: float, mass_per_length: float, L: float) -> float:
    """Angular frequency (rad/s) of mode n (1-based): (beta_n L)^2 sqrt(EI / (rho A L^4))."""
    return BETA_L[n - 1] ** 2 * np.sqrt(EI / (mass_per_length * L**4))


def stokes_terminal_velocity(R: float, rho_s: float, rho_f: float, mu: float, g: float) -> float:
    """Terminal speed of a sphere in Stokes flow: 2 (rho_s - rho_f) g R^2 / (9 mu)."""
    return 2.0 * (rho_s - rho_f) * g * R**2 / (9.0 * mu)


def elastica(alpha: float = 0.0, beta: float = 0.0, n: int = 401, steps: int = 20) -> dict:
    """Large-deflection cantilever under a uniform dead load (alpha = q L^3/EI) and/or a tip
    load (beta = P L^2/EI):

        theta'' = -(alpha (1 - s) + beta) cos(theta),  theta(0) = 0,  theta'(1) = 0,

    solved with ``solve_bvp`` by continuation from zero load. Returns ``s``, ``theta`` and the
    scaled shape ``x/L = int cos``, ``y/L = -int sin`` (downward negative), plus the tip
    values ``tip_v = int_0^1 sin theta`` and ``tip_u = 1 - int_0^1 cos theta``. Small-load
    limits: ``tip_v -> alpha/8 + beta/3``.
    """
    s = np.linspace(0.0, 1.0, n)
    y = np.zeros((2, n))
    for lam in np.linspace(0.0, 1.0, steps + 1)[1:]:
        a, b = lam * alpha, lam * beta

        def rhs(s_, u, a=a, b=b):
            return np.vstack([u[1], -(a * (1.0 - s_) + b) * np.cos(u[0])])

        def bc(u0, u1):
            return np.array([u0[0], u1[1]])

        sol = solve_bvp(rhs, bc, s, y, tol=1e-10, max_nodes=100_000)
        if not sol.success:
            raise RuntimeError(f"elastica: solve_bvp failed at alpha={a}, beta={b}: {sol.message}")
        y = sol.sol(s)
    theta = y[0]
    x = cumulative_trapezoid(np.cos(theta), s, initial=0.0)
    yv = -cumulative_trapezoid(np.sin(theta), s, initial=0.0)
    return {"s": s, "theta": theta, "x": x, "y": yv, "tip_v": -yv[-1], "tip_u": 1.0 - x[-1]}
