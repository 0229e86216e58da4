"""Classical cantilever references: Euler–Bernoulli deflection and frequencies, the elastica.

All lengths in m, forces in N, EI in N m^2, q in N/m. The elastica is the inextensible,
shear-rigid large-deflection cantilever under a uniform dead load q (per unit reference length)
acting in -y; with s = arc length / L, theta the downward rotation of the section and
alpha = q L^3 / EI,

    theta'' = -alpha (1 - s) cos(theta),   theta(0) = 0,   theta'(1) = 0,
    x' = cos(theta),  y' = -sin(theta),    x(0) = y(0) = 0,

solved with ``scipy.integrate.solve_bvp`` and continuation in alpha. Small-load limit:
tip deflection alpha/8 (times L).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_bvp

BETA_L = (1.8751040687119611, 4.6940911329741745, 7.8547574382376126)


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


def _rhs(alpha):
    def f(s, y):
        th, k, _, _ = y
        return np.vstack([k, -alpha * (1.0 - s) * np.cos(th), np.cos(th), -np.sin(th)])
    return f


def _bc(ya, yb):
    return np.array([ya[0], yb[1], ya[2], ya[3]])


def elastica_uniform(alpha: float, n_steps: int | None = None, n_mesh: int = 201):
    """Shape of the uniformly loaded elastica for ``alpha = q L^3 / EI``.

    Continuation from the small-load shape in ``n_steps`` geometrically growing load
    increments (default: 8 per decade of alpha, at least 4). Returns ``s, x, y, theta`` on
    ``n_mesh`` points, lengths divided by L (``y`` negative: downward).
    """
    if not (math.isfinite(alpha) and alpha > 0):
        raise ValueError(f"alpha = q L^3 / EI must be positive, got {alpha!r}")
    a0 = min(alpha, 0.5)
    n_steps = n_steps or max(4, int(math.ceil(8 * math.log10(alpha / a0))) + 1)
    s = np.linspace(0.0, 1.0, n_mesh)
    th = a0 * (s - s**2 + s**3 / 3) / 2             # small-load rotation theta(s)
    y = np.vstack([th, np.gradient(th, s), s, np.zeros_like(s)])
    for a in np.geomspace(a0, alpha, n_steps):
        sol = solve_bvp(_rhs(a), _bc, s, y, tol=1e-8, max_nodes=100_000)
        if not sol.success:
            raise RuntimeError(f"elastica: solve_bvp failed at alpha = {a:.4g}: {sol.message}")
        y = sol.sol(s)
    return s, y[2], y[3], y[0]


def elastica_tip(alpha: float) -> tuple[float, float]:
    """Tip displacement ``(dx, dy)/L`` of the uniformly loaded elastica (dy < 0)."""
    _, x, y, _ = elastica_uniform(alpha)
    return float(x[-1] - 1.0), float(y[-1])


def effective_clamp(tip_deflection: float, q: float, EI: float, length: float) -> float:
    """Where a discrete cantilever's clamp acts (m from the fixed end), from its small-load
    static tip deflection under a uniform load q: ``x_c = L - (8 EI delta / q)^(1/4)``."""
    if not (tip_deflection > 0 and q > 0 and EI > 0):
        raise ValueError(f"need a positive deflection, load and EI; got {tip_deflection!r}, "
                         f"{q!r}, {EI!r}")
    return length - (8.0 * EI * tip_deflection / q) ** 0.25
