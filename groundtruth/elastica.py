"""Reference solutions of the inextensible planar elastica of a clamped cantilever.

With arc length s in units of the free length L, theta(s) the angle of the tangent below the
horizontal, a uniform dead load q per length (alpha = q L^3 / EI) or a tip load P
(beta = P L^2 / EI):

    theta'' = -alpha (1 - s) cos theta     or     theta'' = -beta cos theta,
    theta(0) = 0,  theta'(1) = 0,
    x(s) = int_0^s cos theta,  deflection v(s) = int_0^s sin theta   (in units of L).

Small-load limits: v(1) = alpha / 8 and beta / 3. Large loads are reached by continuation in
the load (each solve starts from the previous one) with ``scipy.integrate.solve_bvp``; the
clamp boundary layer has width about 1 / sqrt(alpha), which the adaptive mesh resolves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_bvp


@dataclass
class Elastica:
    """A solved elastica: ``s (n,)`` nodes and the callables of ``s`` in units of L."""

    load: float
    s: np.ndarray
    theta: np.ndarray
    x: np.ndarray
    v: np.ndarray

    def at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``theta, x, v`` interpolated at arc lengths ``s`` (units of L)."""
        s = np.asarray(s, float)
        return (np.interp(s, self.s, self.theta), np.interp(s, self.s, self.x),
                np.interp(s, self.s, self.v))

    @property
    def tip(self) -> tuple[float, float]:
        """``(x, v)`` of the tip, units of L."""
        return float(self.x[-1]), float(self.v[-1])


def cantilever_elastica(load: float, kind: str = "uniform", n_steps: int | None = None,
                        tol: float = 1e-8) -> Elastica:
    """Solve the clamped elastica under ``load`` = alpha (``kind='uniform'``) or beta
    (``kind='tip'``), continuing from a small load in geometric steps."""
    if kind not in ("uniform", "tip"):
        raise ValueError(f"kind must be 'uniform' or 'tip', got {kind!r}")
    if not (np.isfinite(load) and load > 0):
        raise ValueError(f"load must be a positive number, got {load!r}")
    w = (lambda s: 1.0 - s) if kind == "uniform" else (lambda s: np.ones_like(s))

    def rhs(s, y, p):
        th, dth, x, v = y
        return np.vstack([dth, -p[0] * w(s) * np.cos(th), np.cos(th), np.sin(th)])

    def bc(ya, yb, p):
        return np.array([ya[0], yb[1], ya[2], ya[3]])

    def solve(lam, s, y):
        r = solve_bvp(lambda s, y: rhs(s, y, [lam]), lambda a, b: bc(a, b, [lam]), s, y,
                      tol=tol, max_nodes=200_000)
        if not r.success:
            raise RuntimeError(f"elastica continuation failed at load {lam:.4g}: {r.message}")
        return r.sol, r.x

    start = min(load, 0.1)
    n = n_steps or max(1, int(np.ceil(np.log(load / start) / np.log(1.5))))
    s = np.linspace(0.0, 1.0, 201)
    y = np.zeros((4, s.size))
    y[2] = s
    sol = None
    for lam in np.geomspace(start, load, n + 1):
        sol, s = solve(lam, s, sol(s) if sol is not None else y)
        s = np.union1d(s, np.linspace(0, 1, 201))
    fine = np.union1d(s, np.linspace(0.0, 1.0, 4001))
    th, _, x, v = sol(fine)
    return Elastica(float(load), fine, th, x, v)
