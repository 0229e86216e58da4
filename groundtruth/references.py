"""Classical references the solvers are measured against: Euler–Bernoulli cantilevers, the
elastica, Stokes flow. Lengths in m, forces in N, EI in N m^2, q in N/m.

The elastica is the inextensible, shear-rigid large-deflection cantilever clamped at s = 0
under a uniform dead load q (per unit reference length) and a tip load P, both acting in -y.
With s = arc length / L, theta the downward rotation of the section, alpha = q L^3 / EI and
beta = P L^2 / EI,

    theta'' = -(alpha (1 - s) + beta) cos(theta),   theta(0) = 0,   theta'(1) = 0,
    x' = cos(theta),  y' = -sin(theta),             x(0) = y(0) = 0,

solved with ``scipy.integrate.solve_bvp`` and geometric continuation in the load. Small-load
limits of the tip deflection: alpha/8 + beta/3 (times L).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_bvp

BETA_L = (1.8751040687119611, 4.6940911329741745, 7.8547574382376126)  # beta_n L


def tip_deflection_uniform(q: float, length: float, EI: float) -> float:
    """Small-load tip deflection ``q L^4 / (8 EI)`` of a cantilever under uniform load (m)."""
    return q * length**4 / (8.0 * EI)


def tip_deflection_point(P: float, length: float, EI: float) -> float:
    """Small-load tip deflection ``P L^3 / (3 EI)`` under a tip load (m)."""
    return P * length**3 / (3.0 * EI)


def cantilever_frequency(EI: float, rho_A: float, length: float, mode: int = 1) -> float:
    """Euler–Bernoulli angular frequency ``(beta_n L)^2 sqrt(EI / (rho A L^4))`` (rad/s)."""
    if mode not in (1, 2, 3):
        raise ValueError(f"mode must be 1, 2 or 3, got {mode!r}")
    return BETA_L[mode - 1] ** 2 * math.sqrt(EI / (rho_A * length**4))


def stokes_terminal_velocity(R: float, rho_s: float, rho_f: float, mu: float, g: float) -> float:
    """Terminal speed of a sphere in Stokes flow: ``2 (rho_s - rho_f) g R^2 / (9 mu)`` (m/s)."""
    return 2.0 * (rho_s - rho_f) * g * R**2 / (9.0 * mu)


def _rhs(alpha, beta):
    def f(s, y):
        th, k, _, _ = y
        return np.vstack([k, -(alpha * (1.0 - s) + beta) * np.cos(th), np.cos(th), -np.sin(th)])
    return f


def _bc(ya, yb):
    return np.array([ya[0], yb[1], ya[2], ya[3]])


def elastica(alpha: float = 0.0, beta: float = 0.0, n_mesh: int = 201,
             n_steps: int | None = None) -> dict:
    """The elastica for ``alpha = q L^3/EI`` and ``beta = P L^2/EI``.

    Continuation from a small load (the linear solution) in ``n_steps`` geometrically growing
    increments (default 8 per decade, at least 4). Returns ``s, x, y, theta`` on ``n_mesh``
    points (lengths over L, ``y`` negative downward), ``tip_v = -y(1)`` and ``tip_u = 1 - x(1)``.
    """
    load = alpha + beta
    if not (math.isfinite(alpha) and math.isfinite(beta) and alpha >= 0 and beta >= 0 and load > 0):
        raise ValueError(f"elastica needs alpha, beta >= 0 with a positive sum, got {alpha!r}, {beta!r}")
    lam0 = min(1.0, 0.5 / load)
    n_steps = n_steps or max(4, int(math.ceil(8 * math.log10(1.0 / lam0))) + 1)
    s = np.linspace(0.0, 1.0, n_mesh)
    a0, b0 = lam0 * alpha, lam0 * beta
    th = a0 * (s - s**2 + s**3 / 3) / 2 + b0 * (s - s**2 / 2)   # linear theta(s)
    y = np.vstack([th, np.gradient(th, s), s, np.zeros_like(s)])
    return _continuation(lambda lam: _rhs(lam * alpha, lam * beta), np.geomspace(lam0, 1.0, n_steps),
                         s, y, lambda lam: f"elastica: solve_bvp failed at alpha = {lam * alpha:.4g}, "
                                           f"beta = {lam * beta:.4g}")


def _continuation(rhs_at, loads, s, y, where):
    """Solve the clamped-free BVP (``_bc``) at each load factor of ``loads`` in turn, each from
    the previous solution; the shape on ``s`` as a dict (``x``, ``y``, ``theta``, tip
    displacements ``tip_v``, ``tip_u``). ``where(lam)`` names the failing load in the error."""
    for lam in loads:
        sol = solve_bvp(rhs_at(lam), _bc, s, y, tol=1e-8, max_nodes=100_000)
        if not sol.success:
            raise RuntimeError(f"{where(lam)}: {sol.message}")
        y = sol.sol(s)
    return {"s": s, "x": y[2], "y": y[3], "theta": y[0], "tip_v": -float(y[3][-1]),
            "tip_u": 1.0 - float(y[2][-1])}


def elastica_uniform(alpha: float, n_steps: int | None = None, n_mesh: int = 201):
    """``(s, x, y, theta)`` of the uniformly loaded elastica (see ``elastica``)."""
    if not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha = q L^3 / EI must be positive, got {alpha!r}")
    e = elastica(alpha, 0.0, n_mesh, n_steps)
    return e["s"], e["x"], e["y"], e["theta"]


def elastica_tip(alpha: float) -> tuple[float, float]:
    """Tip displacement ``(dx, dy)/L`` of the uniformly loaded elastica (dy < 0)."""
    e = elastica(alpha)
    return -e["tip_u"], -e["tip_v"]


def effective_clamp(tip_deflection: float, q: float, EI: float, length: float) -> float:
    """Where a discrete cantilever's clamp acts (m from the fixed end), from its small-load
    static tip deflection under a uniform load q: ``x_c = L - (8 EI delta / q)^(1/4)``."""
    if not (tip_deflection > 0 and q > 0 and EI > 0):
        raise ValueError(f"need a positive deflection, load and EI; got {tip_deflection!r}, "
                         f"{q!r}, {EI!r}")
    return length - (8.0 * EI * tip_deflection / q) ** 0.25


def _rhs_reissner(alpha, ext, shear):
    def f(s, y):
        th, k, _, _ = y
        c, sn = np.cos(th), np.sin(th)
        eps, gam = ext * (1.0 - s) * sn, shear * (1.0 - s) * c
        xp = (1.0 + eps) * c - gam * sn
        return np.vstack([k, -alpha * (1.0 - s) * xp, xp, -(1.0 + eps) * sn - gam * c])
    return f


def elastica_shear(alpha: float, ext: float = 0.0, shear: float = 0.0, n_mesh: int = 201,
                   n_steps: int = 12) -> dict:
    """Reissner's extensible, shearable elastica of a cantilever under a uniform dead load q
    (-y): the Timoshenko correction of ``elastica`` for deep beams. With s = arc length / L,
    theta the downward section rotation, ``alpha = q L^3 / EI``, ``ext = q L / EA`` and
    ``shear = q L / (kappa G A)``, the section force is q L (1 - s) upward on the outer part, with
    tension T = q L (1 - s) sin(theta) and shear V = q L (1 - s) cos(theta), and

        theta' = M / EI,   (M / EI)' = -alpha (1 - s) x',
        x' = (1 + eps) cos(theta) - gam sin(theta),   y' = -(1 + eps) sin(theta) - gam cos(theta),
        eps = ext (1 - s) sin(theta),   gam = shear (1 - s) cos(theta),

    theta(0) = 0, theta'(1) = 0, x(0) = y(0) = 0. ``ext = shear = 0`` is ``elastica``; the small-
    load tip deflection is alpha/8 + shear/2 (times L). Returns ``s, x, y, theta, tip_v, tip_u``
    (lengths over L) like ``elastica``."""
    if not (math.isfinite(alpha) and alpha > 0 and ext >= 0 and shear >= 0):
        raise ValueError(f"elastica_shear needs alpha > 0, ext >= 0, shear >= 0, got "
                         f"{alpha!r}, {ext!r}, {shear!r}")
    s = np.linspace(0.0, 1.0, n_mesh)
    y = np.vstack([np.zeros_like(s), np.zeros_like(s), s, np.zeros_like(s)])
    return _continuation(lambda lam: _rhs_reissner(lam * alpha, lam * ext, lam * shear),
                         np.linspace(1.0 / n_steps, 1.0, n_steps), s, y,
                         lambda lam: f"elastica_shear: solve_bvp failed at alpha = {lam * alpha:.4g}")
