"""Total-Lagrangian St. Venant–Kirchhoff elastodynamics in 2-D with scikit-fem (cross-check).

An independent continuum model of the same mechanical problems as the DER/DEP solvers. The
body occupies a rectangle of the (x, y) reference plane with an out-of-plane thickness ``t``
(m); displacement ``u(X)`` is in-plane, gravity acts in -y. With

    F = I + grad u,   E = 1/2 (F^T F - I),   S = lam tr(E) I + 2 mu E,   P = F S,

the elastic energy is ``t * int W dA`` with ``W = 1/2 lam tr(E)^2 + mu E:E``, the internal force
``f_int(u) = t int P : grad v dA`` and its tangent

    K(u)[du, v] = t int (grad du S) : grad v + dS : dE(v) dA,   dE(w) = sym(F^T grad w),

with ``(lam, mu)`` of plane stress or plane strain (computed here, never taken from
``skfem.models``: its ``plane_stress`` changed meaning between releases). The semi-discrete
equation is ``M a + C v + f_int(u) = F`` with consistent mass ``M = t int rho u.v``, dead
gravity load ``F = t int rho b.v``, ``C = c M`` (mass-proportional damping, c in 1/s) plus
optional point masses, drags and weights through ``basis.probes``. Dofs on the clamped edge
``x = x0`` are fixed. Elements are 9-node biquadratic quadrilaterals (``ElementQuad2``): the
linear ones lock in bending.

scikit-fem supplies the mesh, the element, the quadrature, the dof numbering, the constant
operators and the probes; the nonlinear kernel is vectorised numpy (``svk_element``) and is
checked against scikit-fem forms (``reference_forms``) in the tests. Units SI throughout.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from skfem import Basis, BilinearForm, ElementQuad2, ElementVector, LinearForm, MeshQuad, asm
from skfem.helpers import dot

from groundtruth.implicit import ConvergenceError, NewtonSettings

# --- material ------------------------------------------------------------------------------


def lame_plane_stress(youngs: float, poisson: float) -> tuple[float, float]:
    """2-D Lamé constants of plane stress: ``lam* = E nu / (1 - nu^2)``, ``mu = E / (2(1+nu))``."""
    return youngs * poisson / (1.0 - poisson**2), youngs / (2.0 * (1.0 + poisson))


def lame_plane_strain(youngs: float, poisson: float) -> tuple[float, float]:
    """Lamé constants of plane strain: ``lam = E nu / ((1+nu)(1-2nu))``, ``mu = E / (2(1+nu))``."""
    return (youngs * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson)),
            youngs / (2.0 * (1.0 + poisson)))


LAME = {"plane_stress": lame_plane_stress, "plane_strain": lame_plane_strain}


@dataclass(frozen=True)
class Material:
    """An isotropic St. Venant–Kirchhoff material of a 2-D body.

    Attributes:
        youngs: Young's modulus E, Pa.
        poisson: Poisson's ratio nu (0 <= nu < 0.5).
        density: rho, kg/m^3.
        thickness: out-of-plane thickness t, m (plane stress) or width represented (plane strain).
        model: ``"plane_stress"`` or ``"plane_strain"``.
    """

    youngs: float
    poisson: float
    density: float
    thickness: float
    model: str = "plane_stress"

    def __post_init__(self):
        for name in ("youngs", "density", "thickness"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"Material.{name} must be a positive number, got {v!r}")
        if not (isinstance(self.poisson, (int, float)) and 0.0 <= self.poisson < 0.5):
            raise ValueError(f"Material.poisson must be in [0, 0.5), got {self.poisson!r}")
        if self.model not in LAME:
            raise ValueError(f"Material.model must be one of {sorted(LAME)}, got {self.model!r}")

    @property
    def lame(self) -> tuple[float, float]:
        return LAME[self.model](self.youngs, self.poisson)

    @property
    def plane_modulus(self) -> float:
        """Uniaxial in-plane modulus ``lam + 2 mu - lam^2/(lam + 2 mu)`` of the 2-D model:
        E (plane stress) or E / (1 - nu^2) (plane strain). Bending: EI = plane_modulus t h^3/12."""
        lam, mu = self.lame
        return 4.0 * mu * (lam + mu) / (lam + 2.0 * mu)


def rod_section(r0: float) -> tuple[float, float]:
    """Rectangle ``(height, thickness) = (sqrt 3 r0, pi r0 / sqrt 3)`` with the circular rod's
    A = pi r0^2 and I = pi r0^4 / 4 (bending in the height direction)."""
    return math.sqrt(3.0) * r0, math.pi * r0 / math.sqrt(3.0)


# --- the St. Venant–Kirchhoff kernel (pure numpy) --------------------------------------------


def green_lagrange(F: np.ndarray) -> np.ndarray:
    """``E = 1/2 (F^T F - I)``; ``F`` is ``(2, 2, ...)``."""
    C = np.einsum("kI...,kJ...->IJ...", F, F)
    C[0, 0] -= 1.0
    C[1, 1] -= 1.0
    return 0.5 * C


def svk_stress(E: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """Second Piola–Kirchhoff stress ``S = lam tr(E) I + 2 mu E``; ``E`` is ``(2, 2, ...)``."""
    S = 2.0 * mu * E
    tr = E[0, 0] + E[1, 1]
    S[0, 0] += lam * tr
    S[1, 1] += lam * tr
    return S


def svk_element(dphi: np.ndarray, ue: np.ndarray, lam: float, mu: float, wdx: np.ndarray,
                order: int = 2):
    """Energy, internal force and tangent of every element.

    Args:
        dphi: reference gradients of the vector basis ``(n, 2, 2, n_el, n_qp)``:
            ``dphi[i, k, I] = d(phi_i)_k / dX_I``.
        ue: element dofs ``(n, n_el)``, m.
        lam, mu: Lamé constants, Pa.
        wdx: quadrature weights times Jacobian times thickness ``(n_el, n_qp)``, m^3.
        order: 0 energy only, 1 with force, 2 with tangent.

    Returns:
        energy ``(n_el,)`` J; force ``(n, n_el)`` N, ``f_i = int P : grad phi_i``;
        tangent ``(n_el, n, n)`` N/m, ``K_ij = int (grad phi_j S) : grad phi_i + dS_j : dE_i``.
    """
    H = np.einsum("ie,ikIeq->kIeq", ue, dphi)
    F = H + np.eye(2)[:, :, None, None]
    E = green_lagrange(F)
    S = svk_stress(E, lam, mu)
    trE = E[0, 0] + E[1, 1]
    W = 0.5 * lam * trE**2 + mu * np.einsum("IJeq,IJeq->eq", E, E)
    energy = np.sum(W * wdx, axis=1)
    if order < 1:
        return energy, None, None
    P = np.einsum("kJeq,JIeq->kIeq", F, S)
    force = np.einsum("kIeq,ikIeq,eq->ie", P, dphi, wdx)
    if order < 2:
        return energy, force, None
    n, n_el = dphi.shape[0], wdx.shape[0]
    G = np.einsum("kIeq,ikJeq->iIJeq", F, dphi)                 # F^T grad phi_i
    dE = 0.5 * (G + G.transpose(0, 2, 1, 3, 4))
    dphiS = np.einsum("ikJeq,JIeq->ikIeq", dphi, S)            # grad phi_i S
    w = np.sqrt(wdx)                                             # weights are positive

    def rows(a):  # (n, ..., e, q) -> (e, n, ... * q), weighted by sqrt(w)
        a = a * w
        return np.moveaxis(a, -2, 0).reshape(n_el, n, -1)

    geo = rows(dphi) @ rows(dphiS).transpose(0, 2, 1)
    mat = 2.0 * mu * rows(dE) @ rows(dE).transpose(0, 2, 1)
    trdE = rows(dE[:, 0, 0] + dE[:, 1, 1])
    mat += lam * trdE @ trdE.transpose(0, 2, 1)
    return energy, force, geo + mat


# --- mesh ------------------------------------------------------------------------------------


def graded_points(x0: float, x1: float, n: int, ratio: float = 1.0) -> np.ndarray:
    """``n + 1`` points from ``x0`` to ``x1`` whose interval lengths grow geometrically so that
    the last is ``ratio`` times the first (``ratio = 1``: uniform)."""
    if n < 1:
        raise ValueError(f"need at least one element along the length, got {n!r}")
    if ratio == 1.0:
        return np.linspace(x0, x1, n + 1)
    g = ratio ** (1.0 / max(n - 1, 1))
    h = g ** np.arange(n)
    return x0 + (x1 - x0) * np.concatenate([[0.0], np.cumsum(h) / h.sum()])


def strip_mesh(x0: float, length: float, height: float, nx: int, ny: int = 1,
               grading: float = 1.0) -> MeshQuad:
    """Rectangle ``[x0, x0 + length] x [-height/2, height/2]`` of ``nx x ny`` quadrilaterals,
    graded along x (``grading`` = last / first element length)."""
    if ny < 1:
        raise ValueError(f"need at least one element through the height (ny), got {ny!r}")
    x = graded_points(x0, x0 + length, nx, grading)
    y = np.linspace(-height / 2, height / 2, ny + 1)
    return MeshQuad.init_tensor(x, y)


# --- the model -------------------------------------------------------------------------------


@dataclass
class PointLoads:
    """Point masses (kg), drag coefficients (N s/m) and weights (N, downward) at ``points``
    ``(2, n)`` of the reference configuration; each acts on both displacement components."""

    points: np.ndarray
    mass: np.ndarray
    drag: np.ndarray
    weight: np.ndarray


@dataclass
class FemModel:
    """A clamped 2-D SVK body on a quadratic-quadrilateral mesh.

    Attributes:
        mesh: reference mesh (clamped along its left edge ``x = min x``).
        material: the material; its thickness multiplies every integral.
        gravity: g, m/s^2, acting in -y as a dead load.
        damping: mass-proportional damping coefficient c, 1/s (C = c M).
        points: optional point masses, drags and weights.
        intorder: quadrature order (4: 3 x 3 Gauss points, exact for the mass matrix).
    """

    mesh: MeshQuad
    material: Material
    gravity: float = 9.81
    damping: float = 0.0
    points: PointLoads | None = None
    intorder: int = 4
    basis: Basis = field(init=False, repr=False)

    def __post_init__(self):
        if not (math.isfinite(self.damping) and self.damping >= 0):
            raise ValueError(f"FemModel.damping must be >= 0 (1/s), got {self.damping!r}")
        self.basis = Basis(self.mesh, ElementVector(ElementQuad2()), intorder=self.intorder)
        b = self.basis
        self.dphi = np.array([b.basis[i][0].grad for i in range(b.Nbfun)])
        self.wdx = b.dx * self.material.thickness
        self.element_dofs = b.element_dofs
        x0 = self.mesh.p[0].min()
        self.fixed = np.unique(b.get_dofs(lambda x: np.isclose(x[0], x0)).flatten())
        free = np.ones(b.N, bool)
        free[self.fixed] = False
        self.free = np.flatnonzero(free)
        self._setup_operators()
        self._setup_pattern()

    # constant operators from scikit-fem forms
    def _setup_operators(self):
        b, mat = self.basis, self.material
        rho_t, g = mat.density * mat.thickness, self.gravity
        self.M = asm(BilinearForm(lambda u, v, w: rho_t * dot(u, v)), b).tocsr()
        self.F = asm(LinearForm(lambda v, w: -rho_t * g * v[1]), b)
        self.C = self.damping * self.M
        if self.points is not None:
            pl = self.points
            P = self.probe_matrix(np.asarray(pl.points, float))
            npt = P.shape[0] // 2
            rep = lambda a: np.tile(np.broadcast_to(np.asarray(a, float), (npt,)), 2)
            self.M = (self.M + P.T @ scipy.sparse.diags(rep(pl.mass)) @ P).tocsr()
            self.C = (self.C + P.T @ scipy.sparse.diags(rep(pl.drag)) @ P).tocsr()
            w = np.zeros(2 * npt)
            w[npt:] = -np.broadcast_to(np.asarray(pl.weight, float), (npt,))
            self.F = self.F + P.T @ w
        # Newton also stops when its update is below round-off of the coordinates
        self.xtol = 1e-13 * float(np.ptp(self.mesh.p[0]) + np.ptp(self.mesh.p[1]))
        f = np.abs(self.F[self.free])
        self.force_scale = float(f.max()) if f.size and f.max() > 0 else 1.0

    def _setup_pattern(self):
        """Map element-matrix entries to the free-dof numbering once; fixed entries dropped."""
        ed = self.element_dofs                                  # (n, n_el)
        rows = np.broadcast_to(ed.T[:, :, None], (ed.shape[1], ed.shape[0], ed.shape[0]))
        cols = rows.transpose(0, 2, 1)
        number = -np.ones(self.basis.N, np.int64)
        number[self.free] = np.arange(self.free.size)
        r, c = number[rows].ravel(), number[cols].ravel()
        self._keep = (r >= 0) & (c >= 0)
        self._rc = (r[self._keep], c[self._keep])
        sel = np.ix_(self.free, self.free)
        self.M_ff = self.M[sel].tocsr()
        self.C_ff = self.C[sel].tocsr()

    # --- physics ---------------------------------------------------------------------------
    @property
    def ndof(self) -> int:
        return self.basis.N

    def evaluate(self, u: np.ndarray, order: int = 2):
        """Elastic energy (J), internal force ``(ndof,)`` (N), tangent on free dofs (CSR)."""
        lam, mu = self.material.lame
        e, f_el, K_el = svk_element(self.dphi, u[self.element_dofs], lam, mu, self.wdx, order)
        f = None
        if order >= 1:
            f = np.bincount(self.element_dofs.ravel(), f_el.ravel(), minlength=self.ndof)
        K = None
        if order >= 2:
            n = self.free.size
            K = scipy.sparse.csr_matrix((K_el.ravel()[self._keep], self._rc), shape=(n, n))
        return float(e.sum()), f, K

    def internal_force(self, u: np.ndarray) -> np.ndarray:
        return self.evaluate(u, 1)[1]

    def total_energy(self, u: np.ndarray, v: np.ndarray) -> float:
        """Kinetic + elastic + potential of the dead load (J)."""
        return 0.5 * float(v @ (self.M @ v)) + self.evaluate(u, 0)[0] - float(self.F @ u)

    def probe_matrix(self, points: np.ndarray) -> scipy.sparse.csr_matrix:
        """``(2 n, ndof)``: rows ``0..n-1`` give u_x, rows ``n..2n-1`` u_y at ``points (2, n)``."""
        return self.basis.probes(np.asarray(points, float)).tocsr()

    def positions(self, u: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Current positions ``(T, n, 2)`` of reference ``points (2, n)`` for ``u (T, ndof)``."""
        P = self.probe_matrix(points)
        n = P.shape[0] // 2
        d = (P @ np.atleast_2d(u).T).T.reshape(-1, 2, n)
        return np.asarray(points, float).T[None] + d.transpose(0, 2, 1)

    def natural_frequencies(self, k: int = 1) -> np.ndarray:
        """Lowest ``k`` angular frequencies (rad/s) of small vibration about the reference."""
        return self.modes(k)[0]

    def modes(self, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Lowest ``k`` angular frequencies ``(k,)`` (rad/s) and mass-normalised mode shapes
        ``(k, ndof)`` (zero on the clamp) of ``K(0) phi = omega^2 M phi``."""
        K = self.evaluate(np.zeros(self.ndof), 2)[2]
        if self.free.size <= 2000:
            w2, vec = scipy.linalg.eigh(K.toarray(), self.M_ff.toarray(),
                                        subset_by_index=[0, k - 1])
        else:
            w2, vec = scipy.sparse.linalg.eigsh(K.tocsc(), k, self.M_ff.tocsc(), sigma=0)
            order = np.argsort(w2)
            w2, vec = w2[order], vec[:, order]
        phi = np.zeros((k, self.ndof))
        phi[:, self.free] = vec.T
        return np.sqrt(w2), phi


# --- time integration ------------------------------------------------------------------------
#
# Each scheme writes the new acceleration and velocity as affine functions of the new
# displacement u:  a = a0 + ca u,  v = v0 + cv u,  and Newton solves
#     r(u) = M a + C v + f_int(u) - F = 0,   tangent  ca M + cv C + K(u).


def backward_euler_coefficients(u_n, v_n, a_n, dt):
    """``v = (u - u_n)/dt``, ``a = (v - v_n)/dt`` (the DER/DEP scheme)."""
    ca, cv = 1.0 / dt**2, 1.0 / dt
    return -u_n / dt**2 - v_n / dt, ca, -u_n / dt, cv


def newmark_coefficients(u_n, v_n, a_n, dt, beta=0.25, gamma=0.5):
    """Newmark: ``u = u_n + dt v_n + dt^2 ((1/2 - beta) a_n + beta a)``,
    ``v = v_n + dt ((1 - gamma) a_n + gamma a)``; beta = 1/4, gamma = 1/2 conserves energy."""
    ca = 1.0 / (beta * dt**2)
    a0 = -(u_n + dt * v_n) * ca - (0.5 / beta - 1.0) * a_n
    cv = gamma * dt * ca
    v0 = v_n + dt * (1.0 - gamma) * a_n + gamma * dt * a0
    return a0, ca, v0, cv


INTEGRATORS: dict[str, Callable] = {
    "backward_euler": backward_euler_coefficients,
    "newmark": newmark_coefficients,
}


def get_integrator(name: str) -> Callable:
    try:
        return INTEGRATORS[name]
    except KeyError:
        raise ValueError(f"unknown FEM integrator {name!r}; valid: {', '.join(INTEGRATORS)}") \
            from None


@dataclass
class FemStats:
    steps: int = 0
    newton_iterations: int = 0
    halvings: int = 0


def _solve(A: scipy.sparse.csr_matrix, r: np.ndarray) -> np.ndarray:
    return scipy.sparse.linalg.spsolve(A.tocsc(), r)


def newton_dynamic(model: FemModel, state, dt: float, scheme: Callable, tol: float,
                   max_iter: int, stats: FemStats | None = None):
    """One implicit step from ``state = (u, v, a)``; returns ``(new state or None, residual)``."""
    u_n, v_n, a_n = state
    a0, ca, v0, cv = scheme(u_n, v_n, a_n, dt)
    fr = model.free
    u = u_n + dt * v_n
    u[model.fixed] = 0.0
    for it in range(max_iter + 1):
        if stats is not None:
            stats.newton_iterations += 1
        a, v = a0 + ca * u, v0 + cv * u
        _, f, K = model.evaluate(u, 2 if it < max_iter else 1)
        r = (model.M @ a + model.C @ v + f - model.F)[fr]
        res = float(np.max(np.abs(r)))
        if not np.isfinite(res):
            return None, res
        if res < tol:
            return (u, v, a), res
        if it == max_iter:
            break
        du = _solve(K + ca * model.M_ff + cv * model.C_ff, r)
        u = u.copy()
        u[fr] -= du
        if np.max(np.abs(du)) < model.xtol:  # converged to round-off (stiff, tiny residual)
            return (u, v0 + cv * u, a0 + ca * u), res
    return None, res


def initial_acceleration(model: FemModel, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``a = M^{-1} (F - f_int(u) - C v)`` on the free dofs (zero on the clamp)."""
    a = np.zeros(model.ndof)
    r = (model.F - model.internal_force(u) - model.C @ v)[model.free]
    a[model.free] = _solve(model.M_ff, r)
    return a


def _advance(model, state, t, dt, scheme, settings, tol, stats, depth=0):
    new, res = newton_dynamic(model, state, dt, scheme, tol, settings.max_iter, stats)
    if new is not None:
        stats.steps += 1
        return new
    if depth >= settings.max_halvings:
        raise ConvergenceError(f"FEM Newton failed at t = {t:.6g} s with dt = {dt:.3g} s after "
                               f"{depth} halvings: residual {res:.3e} N > {tol:.3e} N")
    stats.halvings += 1
    state = _advance(model, state, t, dt / 2, scheme, settings, tol, stats, depth + 1)
    return _advance(model, state, t + dt / 2, dt / 2, scheme, settings, tol, stats, depth + 1)


def simulate(model: FemModel, t_save: np.ndarray, settings: NewtonSettings,
             integrator: str = "backward_euler", u0: np.ndarray | None = None,
             v0: np.ndarray | None = None, progress: Callable[[float], None] | None = None):
    """Integrate from rest (or ``u0, v0``) and return the displacements at ``t_save``.

    Each save interval is split into ``ceil(interval / settings.dt)`` equal steps; Newton stops
    when ``max |r| < settings.rtol * model.force_scale`` on the free dofs; failed steps are
    halved. Returns ``u, v`` of shape ``(T, ndof)`` (m, m/s) and ``FemStats``.
    """
    scheme = get_integrator(integrator)
    u = np.zeros(model.ndof) if u0 is None else np.array(u0, float)
    v = np.zeros(model.ndof) if v0 is None else np.array(v0, float)
    u[model.fixed], v[model.fixed] = 0.0, 0.0
    state = (u, v, initial_acceleration(model, u, v))
    tol = settings.rtol * model.force_scale
    stats = FemStats()
    us, vs = [u.copy()], [v.copy()]
    for t0, t1 in zip(t_save[:-1], t_save[1:], strict=True):
        n_sub = max(1, int(np.ceil((t1 - t0) / settings.dt - 1e-9)))
        h = (t1 - t0) / n_sub
        for k in range(n_sub):
            state = _advance(model, state, t0 + k * h, h, scheme, settings, tol, stats)
        us.append(state[0].copy())
        vs.append(state[1].copy())
        if progress is not None:
            progress(float(t1))
    return np.array(us), np.array(vs), stats


def solve_static(model: FemModel, settings: NewtonSettings, n_load_steps: int = 10,
                 max_cuts: int = 12, load_factor: float = 1.0) -> np.ndarray:
    """Static equilibrium ``f_int(u) = load_factor * F`` by Newton with load stepping
    (increments halved on failure, at most ``max_cuts`` times in a row). Returns ``u (ndof,)``."""
    tol = settings.rtol * model.force_scale * load_factor
    u = np.zeros(model.ndof)
    lam, dlam, cuts = 0.0, 1.0 / n_load_steps, 0
    while lam < 1.0 - 1e-12:
        target = min(1.0, lam + dlam)
        u_try, res = _static_newton(model, u, target * load_factor, tol, settings.max_iter)
        if u_try is None:
            cuts += 1
            if cuts > max_cuts:
                raise ConvergenceError(f"FEM static Newton failed at load factor {target:.4g}: "
                                       f"residual {res:.3e} N > {tol:.3e} N")
            dlam /= 2
            continue
        u, lam, cuts = u_try, target, 0
        dlam = min(dlam * 1.5, 1.0 - lam) if lam < 1 else dlam
    return u


def _static_newton(model, u, factor, tol, max_iter):
    fr, res = model.free, np.inf
    u = u.copy()
    for _ in range(max_iter):
        _, f, K = model.evaluate(u, 2)
        r = (f - factor * model.F)[fr]
        res = float(np.max(np.abs(r)))
        if not np.isfinite(res):
            return None, res
        if res < tol:
            return u, res
        du = _solve(K, r)
        u[fr] -= du
        if np.max(np.abs(du)) < model.xtol:
            return u, res
    return None, res


# --- reference scikit-fem forms (for tests: an independent statement of the same kernel) -----


def reference_forms(material: Material):
    """scikit-fem ``LinearForm`` of ``f_int`` and ``BilinearForm`` of the tangent; pass the
    current displacement as ``u=basis.interpolate(u)`` to ``asm``."""
    from skfem.helpers import ddot, grad, mul, trace, transpose

    lam, mu, t = *material.lame, material.thickness

    def kinematics(w):
        Gu = grad(w["u"])
        eye = np.zeros_like(Gu)
        eye[0, 0] = eye[1, 1] = 1.0
        F = eye + Gu
        E = 0.5 * (mul(transpose(F), F) - eye)
        return eye, F, lam * trace(E) * eye + 2 * mu * E

    @LinearForm
    def residual(v, w):
        _, F, S = kinematics(w)
        return t * ddot(mul(F, S), grad(v))

    @BilinearForm
    def tangent(du, v, w):
        eye, F, S = kinematics(w)
        dE = 0.5 * (mul(transpose(F), grad(du)) + mul(transpose(grad(du)), F))
        dS = lam * trace(dE) * eye + 2 * mu * dE
        return t * (ddot(mul(grad(du), S), grad(v)) + ddot(mul(F, dS), grad(v)))

    return residual, tangent


# --- builders --------------------------------------------------------------------------------


def cantilever(length: float, height: float, material: Material, nx: int, ny: int = 1,
               x0: float = 0.0, grading: float = 1.0, gravity: float = 9.81,
               damping: float = 0.0, points: PointLoads | None = None) -> FemModel:
    """A strip ``[x0, x0 + length] x [-height/2, height/2]`` clamped on its whole left edge."""
    for name, v in (("length", length), ("height", height)):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"cantilever: {name} must be a positive length in m, got {v!r}")
    mesh = strip_mesh(x0, length, height, nx, ny, grading)
    return FemModel(mesh, material, gravity=gravity, damping=damping, points=points)


def tip_point(model: FemModel) -> np.ndarray:
    """Reference point ``(2, 1)`` at the middle of the free (right) edge."""
    return np.array([[model.mesh.p[0].max()], [0.5 * (model.mesh.p[1].min()
                                                      + model.mesh.p[1].max())]])


# --- the plate's free strip in cylindrical bending (cross-check of DEP) -----------------------
#
# DEP on an equilateral mesh has an in-plane modulus Y h, Poisson ratio 1/3 and bending rigidity
# D = Y h^3/12, so its strip bends like a beam with EI = Y w h^3/12 (docs/SOURCES.md, "The plate", and
# the EI of the plate's beam tests, tests/test_plate.py). The strip's section (length x thickness) is the
# FEM plane; the width w is the out-of-plane direction. Cylindrical bending (load and shape
# uniform across the width) is plane strain in that direction, with the DEP's nu = 1/3; then
# the plane-strain modulus E/(1 - nu^2) sets both EI and EA, so E = Y (1 - nu^2) reproduces
# D = Y h^3/12 and the membrane modulus Y h. (Plane strain with E = Y would be 9/8 stiffer
# in bending than the DEP; plane stress with E = Y and any nu gives the same EI, EA and differs
# only in the shear modulus, which is immaterial at L/h = 1000.)


def plate_strip_material(youngs: float, poisson: float = 1.0 / 3.0, density: float = 1200.0,
                         width: float = 0.1) -> Material:
    """Plane strain with ``E = Y (1 - nu^2)``: plane modulus Y, ``EI = Y w h^3 / 12``."""
    return Material(youngs * (1.0 - poisson**2), poisson, density, width, "plane_strain")


def plate_strip(youngs: float, damping: float = 0.0, *, length: float = 1.0,
                thickness: float = 1e-3, width: float = 0.1, density: float = 1200.0,
                gravity: float = 9.81, poisson: float = 1.0 / 3.0, clamp_x: float = 0.0,
                nx: int = 200, ny: int = 1, grading: float = 4.0) -> FemModel:
    """The plate case's free strip ``[clamp_x, length] x [-h/2, h/2]`` (m), clamped at
    ``clamp_x`` (where the DEP clamp acts), under gravity with mass-proportional damping
    ``damping`` (1/s). Elements grow by ``grading`` from the clamp (bending boundary layer
    ~ (EI/q)^(1/3), about 3 cm) to the tip."""
    mat = plate_strip_material(youngs, poisson, density, width)
    return cantilever(length - clamp_x, thickness, mat, nx, ny, x0=clamp_x, grading=grading,
                      gravity=gravity, damping=damping)


def fem_plate_strip(youngs: float, t_save: np.ndarray, damping: float, *, dt: float = 0.003,
                    integrator: str = "backward_euler", rtol: float = 1e-8,
                    progress: Callable[[float], None] | None = None, **strip) -> dict:
    """Release the plate strip from straight at rest and integrate it.

    Args:
        youngs: DEP Young's modulus Y, Pa.
        t_save: save times ``(T,)``, s, from 0.
        damping: mass-proportional damping c, 1/s (force -c m v, as the DEP case).
        dt: internal time step, s (use the DEP's for a like-for-like comparison).
        strip: keyword arguments of ``plate_strip`` (length, thickness, width, density,
            gravity, poisson, clamp_x, nx, ny, grading).

    Returns:
        ``t (T,)``; ``tip (T, 2)`` displacement (m) of the free edge's midpoint
        (longitudinal, vertical); ``u (T, ndof)``; ``model``; ``stats``; ``wall_s``.
    """
    import time

    model = plate_strip(youngs, damping, **strip)
    t0 = time.perf_counter()
    u, _, stats = simulate(model, np.asarray(t_save, float), NewtonSettings(dt=dt, rtol=rtol),
                           integrator, progress=progress)
    wall = time.perf_counter() - t0
    tip = (model.probe_matrix(tip_point(model)) @ u.T).T
    return {"t": np.asarray(t_save, float), "tip": tip, "u": u, "model": model,
            "stats": {"steps": stats.steps, "newton_iterations": stats.newton_iterations,
                      "halvings": stats.halvings}, "wall_s": wall}
