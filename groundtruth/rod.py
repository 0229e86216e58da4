"""Discrete Elastic Rods (DER) without twist: stretching and bending of a polyline.

Nodes ``x_0 … x_{N-1}`` (3-D), edges ``e_k = x_{k+1} - x_k``. At each interior node ``k`` the
integrated curvature binormal of the two edges ``e = e_{k-1}``, ``f = e_k`` is

    kappa_b = 2 (e x f) / (|e||f| + e . f),         |kappa_b| = 2 tan(phi / 2),

phi the turning angle. The bending energy divides by the Voronoi length ``l_k`` (mean rest
length of the two edges) so that the sum converges to the integral of 1/2 EI kappa^2 ds:

    E_b = 1/2 EI |kappa_b - kappa_b0|^2 / l_k,

with the natural curvature ``kappa_b0`` taken from the rest shape. For a planar rod this is
the signed scalar formula of the paper (docs/SOURCES.md, ``kappa . z``) plus a stiffness against
leaving the plane; for a straight rest shape it is the isotropic 3-D bending energy.

Limitation (no material frame, no twist): ``kappa_b0`` is a fixed vector in space, so the
energy of a *naturally curved* rod is invariant under translations and rotations about the
normal of its rest plane, not under arbitrary 3-D rotations. That is exact for the paper's
rods (straight rest shape, motion in the x-y plane); curved rods moving in 3-D need DER's
material frames. Stretching is ``groundtruth.stretch.spring`` with ``k = EA``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from groundtruth.stretch import StretchTerm

_EPS3 = np.zeros((3, 3, 3))
_EPS3[0, 1, 2] = _EPS3[1, 2, 0] = _EPS3[2, 0, 1] = 1.0
_EPS3[0, 2, 1] = _EPS3[2, 1, 0] = _EPS3[1, 0, 2] = -1.0
# y = (e, f) = B x for x = (x_{k-1}, x_k, x_{k+1})
_B = np.zeros((6, 9))
_B[0:3, 0:3], _B[0:3, 3:6] = -np.eye(3), np.eye(3)
_B[3:6, 3:6], _B[3:6, 6:9] = -np.eye(3), np.eye(3)


def skew(v: np.ndarray) -> np.ndarray:
    """``(n, 3) -> (n, 3, 3)`` with ``skew(v) @ w = v x w``."""
    return np.einsum("ijk,nj->nik", _EPS3, v)


def curvature_binormal(e: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Integrated curvature binormal ``2 e x f / (|e||f| + e.f)`` of edge pairs ``(n, 3)``."""
    d = np.linalg.norm(e, axis=1) * np.linalg.norm(f, axis=1) + np.sum(e * f, axis=1)
    return 2.0 * np.cross(e, f) / d[:, None]


def bending(x0, x1, x2, kappa0, EI, lv, order: int = 2):
    """Bending energy of node triples and its gradient and Hessian w.r.t. ``(x0, x1, x2)``.

    Shapes: ``x0, x1, x2`` (n, 3) m; ``kappa0`` (n, 3) natural curvature binormal;
    ``EI`` (n,) N m^2; ``lv`` (n,) Voronoi length, m. Returns ``(n,)``, ``(n, 9)``,
    ``(n, 9, 9)`` in J, N, N/m.
    """
    e, f = x1 - x0, x2 - x1
    le, lf = np.linalg.norm(e, axis=1), np.linalg.norm(f, axis=1)
    a = np.cross(e, f)
    D = le * lf + np.sum(e * f, axis=1)
    kappa = 2.0 * a / D[:, None]
    r = kappa - kappa0
    c = EI / lv
    energy = 0.5 * c * np.sum(r * r, axis=1)
    if order < 1:
        return energy, None, None
    te, tf = e / le[:, None], f / lf[:, None]
    dD = np.concatenate([lf[:, None] * te + f, le[:, None] * tf + e], axis=1)   # (n, 6)
    dA = np.concatenate([-skew(f), skew(e)], axis=2)                              # (n, 3, 6)
    J = 2.0 * dA / D[:, None, None] - 2.0 * a[:, :, None] * dD[:, None, :] / D[:, None, None] ** 2
    gy = c[:, None] * np.einsum("nc,nci->ni", r, J)
    grad = gy @ _B
    if order < 2:
        return energy, grad, None
    ra = np.sum(r * a, axis=1)
    w = np.einsum("nc,nci->ni", r, dA)                                            # (n, 6)
    d2A = np.zeros((e.shape[0], 6, 6))
    d2A[:, :3, 3:] = np.einsum("nc,cij->nij", r, _EPS3)
    d2A[:, 3:, :3] = np.transpose(d2A[:, :3, 3:], (0, 2, 1))
    I3 = np.eye(3)
    d2D = np.zeros_like(d2A)
    d2D[:, :3, :3] = (lf / le)[:, None, None] * (I3 - te[:, :, None] * te[:, None, :])
    d2D[:, 3:, 3:] = (le / lf)[:, None, None] * (I3 - tf[:, :, None] * tf[:, None, :])
    d2D[:, :3, 3:] = te[:, :, None] * tf[:, None, :] + I3
    d2D[:, 3:, :3] = np.transpose(d2D[:, :3, 3:], (0, 2, 1))
    Dn = D[:, None, None]
    wD = w[:, :, None] * dD[:, None, :]
    second = (2.0 * d2A / Dn - 2.0 * (wD + np.transpose(wD, (0, 2, 1))) / Dn**2
              + 4.0 * ra[:, None, None] * dD[:, :, None] * dD[:, None, :] / Dn**3
              - 2.0 * ra[:, None, None] * d2D / Dn**2)
    hy = c[:, None, None] * (np.einsum("nci,ncj->nij", J, J) + second)
    hess = _B.T @ hy @ _B
    return energy, grad, hess


@dataclass
class BendTerm:
    """Bending at every interior node of a polyline ``0 … N-1``.

    Attributes:
        n_nodes: N.
        rest: rest positions ``(N, 3)``; gives the natural curvature and Voronoi lengths.
        EI: bending stiffness, N m^2 (scalar or ``(N-2,)``).
    """

    n_nodes: int
    rest: np.ndarray
    EI: float | np.ndarray

    def __post_init__(self):
        k = np.arange(1, self.n_nodes - 1)
        nodes = np.stack([k - 1, k, k + 1], axis=1)
        self.dofs = (3 * nodes[:, :, None] + np.arange(3)).reshape(-1, 9)
        x = np.asarray(self.rest, float)
        l0 = np.linalg.norm(np.diff(x, axis=0), axis=1)
        self.lv = 0.5 * (l0[:-1] + l0[1:])
        self.kappa0 = curvature_binormal(x[k] - x[k - 1], x[k + 1] - x[k])
        self.EI_el = np.broadcast_to(np.asarray(self.EI, float), (k.size,)).copy()

    def evaluate(self, xe: np.ndarray, order: int):
        return bending(xe[:, 0:3], xe[:, 3:6], xe[:, 6:9], self.kappa0, self.EI_el, self.lv, order)


def rod_terms(rest: np.ndarray, EA: float, EI: float) -> list:
    """Stretching of every edge and bending at every interior node of a polyline."""
    rest = np.asarray(rest, float)
    n = rest.shape[0]
    if n < 3:
        raise ValueError(f"a rod needs at least 3 nodes (n_nodes), got {n}")
    edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    l0 = np.linalg.norm(np.diff(rest, axis=0), axis=1)
    return [StretchTerm(edges, l0, EA), BendTerm(n, rest, EI)]
