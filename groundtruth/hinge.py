"""Hinge bending of a triangle mesh (Discrete Elastic Plates / discrete shells).

A hinge is an interior edge with its two triangles. Its nodes are ``(x0, x1, x2, x3)``: the
shared edge runs from ``x0`` to ``x1``, ``x2`` is the opposite vertex of triangle
``A = (x0, x1, x2)`` and ``x3`` that of triangle ``B = (x1, x0, x3)``; both triangles are
counter-clockwise, so ``A`` traverses the edge as ``x0 -> x1`` and ``B`` as ``x1 -> x0``. With

    e = x1 - x0,  p = x2 - x0,  m = x3 - x0,
    a = e x p  (normal of A, |a| = 2 area A),   b = m x e  (normal of B),

the signed dihedral angle between the normals, about the edge, is

    theta = atan2((a x b) . e/|e|, a . b) = atan2(s, c),
    s = -|e| V,  V = e . (p x m)  (since a x b = -e V),
    c = (e . m)(e . p) - |e|^2 (p . m)  (Binet-Cauchy),

zero for a flat hinge and positive when the hinge folds "mountain" seen from the side the
normals point to (``x2`` or ``x3`` moves to the -normal side). Classic check (Bridson et al.):
d theta / d x2 = -|e| a / |a|^2 and d theta / d x3 = -|e| b / |b|^2. The energy of a hinge is

    E_b = 1/2 k_b (theta - theta_bar)^2,

with the rest angle ``theta_bar`` from the rest mesh. The reference stiffness of Discrete
Elastic Plates is k_b = (2 / sqrt 3) Y h^3 / 12, which makes an equilateral mesh bend with
D = Y h^3 / 12; ``hinge_stiffness`` generalises it to other triangles (see there).

Derivatives (the quantities of Tamstorf & Grinspun 2013, here as a chain rule through the
two polynomials s and c so that every factor is elementary). On ``y = (e, p, m)``:

    grad theta = (c grad s - s grad c) / r^2,        r^2 = s^2 + c^2,
    hess theta = f_cc (gc gc^T - gs gs^T) + f_cs (gc gs^T + gs gc^T) + f_c hess c + f_s hess s,
        f_c = -s/r^2, f_s = c/r^2, f_cc = 2cs/r^4, f_cs = (s^2 - c^2)/r^4  (atan2 derivatives),
    grad V = (p x m, m x e, e x p),   hess V: blocks (e,p) = [eps_ijk m_k], (e,m) = -[eps_ijk p_k],
        (p,m) = [eps_ijk e_k] and their transposes,
    grad s = -(V (u, 0, 0) + |e| grad V),   u = e/|e|,
    hess s = -(V (I - u u^T)/|e| on (e,e) + (u,0,0) grad V^T + grad V (u,0,0)^T + |e| hess V),
    grad c = (m (e.p) + p (e.m) - 2 e (p.m),  e (e.m) - m |e|^2,  e (e.p) - p |e|^2),
    hess c: (e,e) = m p^T + p m^T - 2 (p.m) I,  (e,p) = m e^T - 2 e m^T + (e.m) I,
            (e,m) = p e^T - 2 e p^T + (e.p) I,  (p,m) = e e^T - |e|^2 I,  (p,p) = (m,m) = 0;
    and on q = (x0, x1, x2, x3), since y = (x1 - x0, x2 - x0, x3 - x0):
    grad_q = (-sum of the three blocks, blocks),  hess_q = B^T hess_y B.

Every formula is checked by finite differences in ``tests/test_plate.py`` on random, strongly
folded hinges of both signs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_I3 = np.eye(3)


def dihedral_angle(x0, x1, x2, x3) -> np.ndarray:
    """Signed dihedral angle ``theta (n,)`` in (-pi, pi] of hinges ``(x0, x1, x2, x3)``,
    each ``(n, 3)``; see the module docstring for the orientation."""
    e, p, m = x1 - x0, x2 - x0, x3 - x0
    ee = np.einsum("ni,ni->n", e, e)
    s = -np.sqrt(ee) * np.einsum("ni,ni->n", e, _cross(p, m))
    c = np.einsum("ni,ni->n", e, m) * np.einsum("ni,ni->n", e, p) - ee * np.einsum("ni,ni->n", p, m)
    return np.arctan2(s, c)


def dihedral_derivatives(x0, x1, x2, x3, order: int = 2):
    """``theta (n,)``, its gradient ``(n, 12)`` and Hessian ``(n, 12, 12)`` w.r.t.
    ``q = (x0, x1, x2, x3)`` (the Hessian is ``None`` when ``order < 2``).

    Works on ``y = (e, p, m)`` with ``s = -|e| V``, ``V = e . (p x m)``,
    ``c = (e.m)(e.p) - |e|^2 (p.m)`` (see the module docstring), then ``q``-derivatives are
    ``B^T (.)`` and ``B^T (.) B``. Singular when a triangle is degenerate, as the angle is.
    """
    theta, g, H = _dihedral_y(x0, x1, x2, x3, order)
    return theta, _to_nodes(g), None if H is None else _to_nodes_2(H)


def _dihedral_y(x0, x1, x2, x3, order: int):
    """theta and its gradient ``(n, 9)`` and Hessian ``(n, 9, 9)`` on ``y = (e, p, m)``."""
    e, p, m = x1 - x0, x2 - x0, x3 - x0
    ee = np.einsum("ni,ni->n", e, e)
    l = np.sqrt(ee)
    u = e / l[:, None]
    pxm, mxe, exp = _cross(p, m), _cross(m, e), _cross(e, p)
    V = np.einsum("ni,ni->n", e, pxm)
    ep, em, pm = (np.einsum("ni,ni->n", e, p), np.einsum("ni,ni->n", e, m),
                  np.einsum("ni,ni->n", p, m))
    s, c = -l * V, em * ep - ee * pm
    r2 = s * s + c * c
    theta = np.arctan2(s, c)

    dV = np.concatenate([pxm, mxe, exp], axis=1)                       # (n, 9) over (e, p, m)
    ds = -l[:, None] * dV
    ds[:, 0:3] -= V[:, None] * u
    dc = np.concatenate([m * ep[:, None] + p * em[:, None] - 2 * e * pm[:, None],
                         e * em[:, None] - m * ee[:, None],
                         e * ep[:, None] - p * ee[:, None]], axis=1)
    grad_y = (c[:, None] * ds - s[:, None] * dc) / r2[:, None]
    if order < 2:
        return theta, grad_y, None

    r4 = r2 * r2
    f_c, f_s = -s / r2, c / r2
    f_cc, f_cs = 2 * c * s / r4, (s * s - c * c) / r4
    # f_cc (dc dc^T - ds ds^T) + f_cs (dc ds^T + ds dc^T) - f_s (dl dV^T + dV dl^T),
    # dl = (u, 0, 0), written as P^T Q with four rank-one terms
    D = f_s[:, None] * dV
    P = np.stack([dc, ds, D, np.zeros_like(D)], axis=1)
    Q = np.stack([f_cc[:, None] * dc + f_cs[:, None] * ds, f_cs[:, None] * dc - f_cc[:, None] * ds,
                  np.zeros_like(D), -D], axis=1)
    Q[:, 2, 0:3] = -u
    P[:, 3, 0:3] = u
    H = P.transpose(0, 2, 1) @ Q
    # - f_s (V d2l + l d2V), d2l = (I - u u^T)/|e| on (e, e); d2V: eps blocks (e,p),(e,m),(p,m)
    fsl = f_s * l
    _add_eps(H, 0, 3, -fsl[:, None] * m)
    _add_eps(H, 0, 6, fsl[:, None] * p)
    _add_eps(H, 3, 6, -fsl[:, None] * e)
    uu = u[:, :, None] * u[:, None, :]
    # + f_c d2c
    fc = f_c[:, None, None]
    mp = m[:, :, None] * p[:, None, :]
    H[:, 0:3, 0:3] += fc * (mp + mp.transpose(0, 2, 1)) \
        - ((2 * f_c * pm)[:, None, None] + (f_s * V / l)[:, None, None]) * _I3 \
        + (f_s * V / l)[:, None, None] * uu
    me = m[:, :, None] * e[:, None, :]
    pe = p[:, :, None] * e[:, None, :]
    b_ep = fc * (me - 2 * me.transpose(0, 2, 1)) + (f_c * em)[:, None, None] * _I3
    b_em = fc * (pe - 2 * pe.transpose(0, 2, 1)) + (f_c * ep)[:, None, None] * _I3
    b_pm = fc * (e[:, :, None] * e[:, None, :]) - (f_c * ee)[:, None, None] * _I3
    for (i, j), b in (((0, 3), b_ep), ((0, 6), b_em), ((3, 6), b_pm)):
        H[:, i:i + 3, j:j + 3] += b
        H[:, j:j + 3, i:i + 3] += b.transpose(0, 2, 1)
    return theta, grad_y, H


def _add_eps(H: np.ndarray, i: int, j: int, v: np.ndarray) -> None:
    """Add ``M_ab = eps_abk v_k`` to block ``(i, j)`` of ``H`` and its transpose to ``(j, i)``."""
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    for a, b, w in ((0, 1, v2), (1, 2, v0), (2, 0, v1)):
        H[:, i + a, j + b] += w
        H[:, i + b, j + a] -= w
        H[:, j + b, i + a] += w
        H[:, j + a, i + b] -= w


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of ``(n, 3)`` arrays (faster than ``np.cross`` for small n)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _to_nodes(g: np.ndarray) -> np.ndarray:
    """``B^T g`` for ``g (n, 9)`` over ``(x1 - x0, x2 - x0, x3 - x0)``: ``(n, 12)``."""
    out = np.empty((g.shape[0], 12))
    out[:, 3:] = g
    out[:, :3] = -g.reshape(-1, 3, 3).sum(axis=1)
    return out


def _to_nodes_2(H: np.ndarray) -> np.ndarray:
    """``B^T H B`` for a symmetric ``H (n, 9, 9)``: ``(n, 12, 12)``."""
    n = H.shape[0]
    out = np.empty((n, 12, 12))
    out[:, 3:, 3:] = H
    rows = H.reshape(n, 3, 3, 9).sum(axis=1)                 # sum over the three node blocks
    out[:, :3, 3:] = -rows
    out[:, 3:, :3] = -rows.transpose(0, 2, 1)
    out[:, :3, :3] = rows.reshape(n, 3, 3, 3).sum(axis=2)
    return out


def hinge_energy(x0, x1, x2, x3, theta_bar, k_b, order: int = 2):
    """E_b = 1/2 k_b (theta - theta_bar)^2 of ``n`` hinges, with gradient ``(n, 12)`` and Hessian
    ``(n, 12, 12)`` w.r.t. ``(x0, x1, x2, x3)``:

        grad = k_b (theta - theta_bar) grad theta,
        hess = k_b [grad theta grad theta^T + (theta - theta_bar) hess theta].

    Shapes: ``x*`` (n, 3) m; ``theta_bar`` (n,) rad; ``k_b`` (n,) or scalar, N m. Units J, N, N/m.
    """
    if order < 1:
        d = dihedral_angle(x0, x1, x2, x3) - theta_bar
        return 0.5 * k_b * d * d, None, None
    theta, g, h = _dihedral_y(x0, x1, x2, x3, order)
    d = theta - theta_bar
    kb = np.broadcast_to(k_b, d.shape)
    energy = 0.5 * kb * d * d
    grad = _to_nodes((kb * d)[:, None] * g)
    if order < 2:
        return energy, grad, None
    # on y = (e, p, m) first (9 x 9), then to the nodes once
    hess = (kb * d)[:, None, None] * h + kb[:, None, None] * (g[:, :, None] * g[:, None, :])
    return energy, grad, _to_nodes_2(hess)


def hinge_stiffness(youngs: float, thickness: float, edge_length: np.ndarray,
                    area_sum: np.ndarray) -> np.ndarray:
    """Per-hinge stiffness ``k_b (n,)`` (N m) of a plate of modulus Y (Pa) and thickness h (m):

        k_b = D |e|^2 / (A_A + A_B),      D = Y h^3 / 12,

    from the rest length ``|e|`` of the hinge edge and the rest areas of its two triangles.
    This is the Discrete Elastic Plates value (2 / sqrt 3) Y h^3 / 12 times the calibration
    factor phi = (sqrt 3 / 2) |e|^2 / (A_A + A_B), which is exactly 1 on equilateral triangles.
    On the row-structured meshes of ``groundtruth.mesh`` (every node on a row x = const, cells
    split by one diagonal) only the hinges along the rows see a cylindrical bend about y, and
    the uniform constant gives them a rigidity (2 / sqrt 3)(Delta x / dy) D, mesh dependent
    (EI_eff = 0.34 EI measured on the default plate mesh); with phi, a cylindrical bend about y
    (or about x) stores exactly 1/2 D kappa^2 per unit area for any row spacing. Right triangles
    also couple bending to twist, which ``PlateCase.diagonal_stiffening`` removes; together the
    default strip bends with EI_eff = 0.9988 Y w h^3 / 12 (``tests/test_plate.py``).
    """
    return youngs * thickness**3 / 12.0 * np.asarray(edge_length) ** 2 / np.asarray(area_sum)


@dataclass
class HingeTerm:
    """Bending of every interior edge of a triangle mesh.

    Attributes:
        hinges: ``(H, 4)`` node indices ``(x0, x1, x2, x3)`` (see the module docstring).
        theta_bar: rest dihedral angles ``(H,)``, rad.
        k_b: stiffness ``(H,)`` or scalar, N m.
    """

    hinges: np.ndarray
    theta_bar: np.ndarray
    k_b: np.ndarray

    def __post_init__(self):
        self.hinges = np.asarray(self.hinges, np.int64).reshape(-1, 4)
        n = len(self.hinges)
        self.theta_bar = np.broadcast_to(np.asarray(self.theta_bar, float), (n,)).copy()
        self.k_b = np.broadcast_to(np.asarray(self.k_b, float), (n,)).copy()
        self.dofs = (3 * self.hinges[:, :, None] + np.arange(3)).reshape(-1, 12)

    @classmethod
    def from_rest(cls, hinges: np.ndarray, rest: np.ndarray, k_b) -> HingeTerm:
        """Hinges with rest angles measured on the rest positions ``(N, 3)``."""
        h = np.asarray(hinges, np.int64).reshape(-1, 4)
        x = np.asarray(rest, float)
        theta_bar = dihedral_angle(x[h[:, 0]], x[h[:, 1]], x[h[:, 2]], x[h[:, 3]])
        return cls(h, theta_bar, k_b)

    def flat_at_rest(self, xe: np.ndarray) -> bool:
        """True when every hinge lies flat, rests flat and is not folded over: the four nodes
        of each hinge share one z (so e, p, m lie in the x-y plane), ``theta_bar = 0`` and
        ``c > 0`` (so ``theta = 0`` exactly). Then, exactly in floating point, the energy and
        the gradient are 0 (``theta - theta_bar = 0``) and the Hessian
        ``k_b grad theta grad theta^T`` has nonzero entries only between z coordinates:
        ``grad theta = (c grad s - s grad c) / r^2`` with ``s = -|e| V = 0`` and ``grad s``
        along z (every cross product of in-plane vectors is). An in-plane plate whose z is at
        rest therefore gets nothing from its hinges on x and y (``MechanicalSystem`` skips
        them there)."""
        z = xe[:, 2::3]
        if not (np.all(self.theta_bar == 0.0) and np.all(z == z[:, :1])):
            return False
        e, p, m = xe[:, 3:5] - xe[:, 0:2], xe[:, 6:8] - xe[:, 0:2], xe[:, 9:11] - xe[:, 0:2]
        ee = np.einsum("ni,ni->n", e, e)
        c = (np.einsum("ni,ni->n", e, m) * np.einsum("ni,ni->n", e, p)
             - ee * np.einsum("ni,ni->n", p, m))
        return bool(np.all(c > 0))

    def evaluate(self, xe: np.ndarray, order: int):
        return hinge_energy(xe[:, 0:3], xe[:, 3:6], xe[:, 6:9], xe[:, 9:12],
                            self.theta_bar, self.k_b, order)
