"""Backward Euler with Newton–Raphson, and a static solve with load stepping.

One backward-Euler step from ``(q_n, v_n)`` solves for ``q`` the residual

    f(q) = M [(q - q_n)/dt - v_n]/dt + grad E(q) + C (q - q_n)/dt - F = 0,

with tangent ``M/dt^2 + hess E(q) + C/dt``; then ``v_{n+1} = (q - q_n)/dt``. Newton starts from
``q_n + dt v_n`` (``predictor="velocity"``) or ``q_n + dt v_n + dt^2 a_n`` with the last step's
``a_n = (v_n - v_{n-1}) / dt`` (``"acceleration"``: the same solution within the tolerance, in
about one Newton iteration less per step on smooth dynamics). Newton stops when
``max |f| < tol`` on the free dofs, ``tol = rtol * force_scale``, or when the Newton update
has shrunk to roundoff (``max |dq| < 1e-13 max(1, |q|)``: stiff systems have a residual floor
of about machine epsilon times the internal forces, which may exceed ``tol``). A step whose
Newton fails is
retried as two half steps, recursively, ``max_halvings`` times; then ``ConvergenceError`` says
at which time, step and residual it failed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from groundtruth.system import MechanicalSystem

_XTOL = 1e-13
PREDICTORS = ("velocity", "acceleration")


class ConvergenceError(RuntimeError):
    """Newton did not converge even after the step (or load increment) was halved repeatedly."""


@dataclass(frozen=True)
class NewtonSettings:
    """Settings of the implicit solver.

    Attributes:
        dt: internal time step, s.
        rtol: Newton residual tolerance relative to the system's ``force_scale``.
        max_iter: Newton iterations before a step counts as failed.
        max_halvings: how many times a failed step is halved before giving up.
        predictor: Newton's starting point, ``"velocity"`` or ``"acceleration"``.
    """

    dt: float = 0.01
    rtol: float = 1e-3
    max_iter: int = 30
    max_halvings: int = 8
    predictor: str = "velocity"

    def __post_init__(self):
        for name in ("dt", "rtol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"NewtonSettings.{name} must be a positive number, got {v!r}")
        if self.predictor not in PREDICTORS:
            raise ValueError(f"NewtonSettings.predictor must be one of {PREDICTORS}, "
                             f"got {self.predictor!r}")
        if self.max_iter < 1 or self.max_halvings < 0:
            raise ValueError(f"NewtonSettings: max_iter >= 1 and max_halvings >= 0 required, "
                             f"got {self.max_iter!r}, {self.max_halvings!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class StepStats:
    steps: int = 0
    newton_iterations: int = 0
    halvings: int = 0


def newton_step(system: MechanicalSystem, q_n: np.ndarray, v_n: np.ndarray, dt: float,
                tol: float, max_iter: int, stats: StepStats | None = None,
                a_n: np.ndarray | None = None):
    """One backward-Euler step. Returns ``(q, v, residual)``; ``q is None`` on failure.
    With ``a_n`` (an acceleration estimate) Newton starts from ``q_n + dt v_n + dt^2 a_n``."""
    m, c, f_ext = system.mass_dofs, system.damping_dofs, system.force_dofs
    free = ~system.fixed_dofs
    diag = m / dt**2 + c / dt
    if a_n is None:
        q = q_n + dt * v_n * free
    else:
        q = q_n + (dt * v_n + dt * dt * a_n) * free
    res = np.inf
    # the iterates are those of plain Newton; the tangent is assembled with the gradient at the
    # predictor (almost always needed) and later only when another update is needed
    g, K = system.gradient_hessian(q, diag)
    for it in range(max_iter):
        if it > 0:
            g, K = system.gradient(q), None
        f = m * ((q - q_n) / dt - v_n) / dt + g + c * (q - q_n) / dt - f_ext
        f[~free] = 0.0
        res = float(np.max(np.abs(f)))
        if stats is not None:
            stats.newton_iterations += 1
        if not np.isfinite(res):
            return None, None, res
        if res < tol:
            return q, (q - q_n) / dt, res
        if K is None:
            K = system.gradient_hessian(q, diag)[1]
        dq = K.solve(f)
        q = q - dq
        if np.max(np.abs(dq)) < _XTOL * max(1.0, np.max(np.abs(q))):
            return q, (q - q_n) / dt, res
    return None, None, res


def _advance(system, q, v, t, dt, settings, tol, stats, depth=0, a=None):
    """Advance by ``dt``, halving on Newton failure. Returns ``(q, v)``."""
    q1, v1, res = newton_step(system, q, v, dt, tol, settings.max_iter, stats, a)
    if q1 is not None:
        stats.steps += 1
        return q1, v1
    if depth >= settings.max_halvings:
        raise ConvergenceError(
            f"Newton failed at t = {t:.6g} s with dt = {dt:.3g} s after {depth} halvings: "
            f"residual {res:.3e} N > tolerance {tol:.3e} N")
    stats.halvings += 1
    q, v = _advance(system, q, v, t, dt / 2, settings, tol, stats, depth + 1, a)
    return _advance(system, q, v, t + dt / 2, dt / 2, settings, tol, stats, depth + 1, a)


def simulate(system: MechanicalSystem, q0: np.ndarray, v0: np.ndarray, t_save: np.ndarray,
             settings: NewtonSettings,
             progress: Callable[[float], None] | None = None) -> tuple[np.ndarray, np.ndarray, StepStats]:
    """Integrate from ``t_save[0]`` and return positions and velocities at ``t_save``.

    Args:
        q0, v0: initial positions and velocities ``(3N,)``.
        t_save: increasing save times ``(T,)``, s; each interval is split into
            ``ceil(interval / dt)`` equal internal steps.
        progress: optional callback receiving the simulated time after each saved frame.

    Returns:
        ``pos, vel`` of shape ``(T, 3N)`` and the step statistics.
    """
    q, v = np.array(q0, float), np.array(v0, float) * ~system.fixed_dofs
    tol = settings.rtol * system.force_scale
    pos, vel = [q.copy()], [v.copy()]
    stats = StepStats()
    a = np.zeros_like(v) if settings.predictor == "acceleration" else None
    for t0, t1 in zip(t_save[:-1], t_save[1:]):
        n_sub = max(1, int(np.ceil((t1 - t0) / settings.dt - 1e-9)))
        h = (t1 - t0) / n_sub
        for k in range(n_sub):
            q1, v1 = _advance(system, q, v, t0 + k * h, h, settings, tol, stats, a=a)
            if a is not None:
                a = (v1 - v) / h
            q, v = q1, v1
        pos.append(q.copy())
        vel.append(v.copy())
        if progress is not None:
            progress(float(t1))
    return np.array(pos), np.array(vel), stats


def solve_static(system: MechanicalSystem, q0: np.ndarray, settings: NewtonSettings,
                 n_load_steps: int = 10, max_cuts: int = 12,
                 first_load: float | None = None) -> np.ndarray:
    """Static equilibrium ``grad E(q) = F`` by Newton with load stepping.

    By default the load factor rises from 0 to 1 in ``n_load_steps`` equal increments. With
    ``first_load`` in (0, 1] it starts at ``first_load`` and rises geometrically (equal steps
    of log load, ``n_load_steps`` of them), and the Newton tolerance is taken relative to the
    applied load (``tol * load factor``), which suits very flexible structures whose
    deflection saturates (a soft cantilever hangs down long before the full load). An
    increment whose Newton fails is halved (in load or log load; at most ``max_cuts`` times
    in a row); a successful one lets the next grow by 1.5. Needs clamped dofs that remove
    every rigid motion, otherwise the tangent is singular.
    """
    if not system.fixed_nodes.any():
        raise ValueError("solve_static: the system has no clamped node, so static equilibrium "
                         "is undefined (rigid motion); use a case with a clamp")
    geometric = first_load is not None
    if geometric and not (np.isfinite(first_load) and 0 < first_load <= 1):
        raise ValueError(f"solve_static: first_load must be in (0, 1], got {first_load!r}")
    tol = settings.rtol * system.force_scale
    free = ~system.fixed_dofs
    q = np.array(q0, float)
    lam, cuts = 0.0, 0
    step = -np.log(first_load) / n_load_steps if geometric else 1.0 / n_load_steps
    zero = np.zeros(q.size)
    while lam < 1.0 - 1e-12:
        if geometric:
            target = first_load if lam == 0.0 else min(1.0, lam * np.exp(step))
        else:
            target = min(1.0, lam + step)
        tol_k = tol * target if geometric else tol
        q_try, res = _static_newton(system, q, target, tol_k, settings.max_iter, free, zero)
        if q_try is None:
            cuts += 1
            if cuts > max_cuts:
                raise ConvergenceError(
                    f"static Newton failed at load factor {target:.4g}: residual {res:.3e} N "
                    f"> tolerance {tol_k:.3e} N after {max_cuts} load-step cuts")
            if geometric and lam == 0.0:
                first_load /= 2
            else:
                step /= 2
            continue
        q, lam, cuts = q_try, target, 0
        if lam < 1:
            step = min(step * 1.5, -np.log(lam) if geometric else 1.0 - lam)
    return q


def _static_newton(system, q, lam, tol, max_iter, free, zero):
    res = np.inf
    for _ in range(max_iter):
        g, K = system.gradient_hessian(q, zero)
        f = g - lam * system.force_dofs
        f[~free] = 0.0
        res = float(np.max(np.abs(f)))
        if not np.isfinite(res):
            return None, res
        if res < tol:
            return q, res
        dq = K.solve(f)
        q = q - dq
        if np.max(np.abs(dq)) < _XTOL * max(1.0, np.max(np.abs(q))):
            return q, res
    return None, res
