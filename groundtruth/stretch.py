"""Stretching of an edge: a nonlinear spring, shared by rods (DER) and plates (DEP).

For an edge ``e = x1 - x0`` of rest length ``l0`` and stiffness ``k`` (N: EA for a rod edge,
k_s = (sqrt 3 / 2) Y h l0 for a plate edge):

    E_s = 1/2 k l0 (|e|/l0 - 1)^2
    dE/de = k eps e_hat,                    eps = |e|/l0 - 1
    d2E/de2 = (k/l0) e_hat e_hat^T + k eps (I - e_hat e_hat^T) / |e|
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def spring(x0: np.ndarray, x1: np.ndarray, l0: np.ndarray, k: np.ndarray, order: int = 2):
    """Energy ``(n,)``, gradient ``(n, 6)`` and Hessian ``(n, 6, 6)`` w.r.t. ``(x0, x1)``.

    Shapes: ``x0, x1`` (n, 3) m; ``l0, k`` (n,) or scalars. Units J, N, N/m.
    """
    e = x1 - x0
    l = np.linalg.norm(e, axis=1)
    eps = l / l0 - 1.0
    energy = 0.5 * k * l0 * eps**2
    if order < 1:
        return energy, None, None
    t = e / l[:, None]
    ge = (k * eps)[:, None] * t
    grad = np.concatenate([-ge, ge], axis=1)
    if order < 2:
        return energy, grad, None
    tt = t[:, :, None] * t[:, None, :]
    he = (k / l0)[..., None, None] * tt + (k * eps / l)[:, None, None] * (np.eye(3) - tt)
    return energy, grad, _pair_block(he)


def _pair_block(he: np.ndarray) -> np.ndarray:
    n = he.shape[0]
    h = np.empty((n, 6, 6))
    h[:, :3, :3] = he
    h[:, 3:, 3:] = he
    h[:, :3, 3:] = -he
    h[:, 3:, :3] = -he
    return h


@dataclass
class StretchTerm:
    """All edge springs of a mesh.

    Attributes:
        edges: ``(E, 2)`` node indices.
        l0: rest lengths ``(E,)``, m.
        k: stiffness ``(E,)``, N.
    """

    edges: np.ndarray
    l0: np.ndarray
    k: np.ndarray

    def __post_init__(self):
        self.edges = np.asarray(self.edges, np.int64)
        self.l0 = np.broadcast_to(np.asarray(self.l0, float), (len(self.edges),)).copy()
        self.k = np.broadcast_to(np.asarray(self.k, float), (len(self.edges),)).copy()
        self.dofs = (3 * self.edges[:, :, None] + np.arange(3)).reshape(-1, 6)

    def evaluate(self, xe: np.ndarray, order: int):
        return spring(xe[:, :3], xe[:, 3:], self.l0, self.k, order)
