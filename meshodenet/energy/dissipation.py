r"""A learned Rayleigh dissipation over a mesh's nodes and edges: the damping of Implicit-Energy
when the case's drag is not given (``meshodenet.energy.model_dissipation``).

.. math::
    D(v; x) = \sum_i \tfrac12 \beta_i |v_i|^2
            + \sum_{e = (i, j)} \tfrac12 \alpha_e \dot\epsilon_e^2,
    \qquad \dot\epsilon_e = t_e(x) \cdot (v_j - v_i) / l_{0,e},

a quadratic form ``D = 1/2 v^T C(x) v`` with ``C = diag(beta) (x) I_3 + sum_e alpha_e
dq_e dq_e^T`` (``dq_e = (-t_e, t_e) / l_{0,e}``, the gradient of the edge's stretch,
``meshodenet.energy.core._edge_geometry``; ``t_e`` the edge's unit vector at ``x``):

- ``node``: each node's drag against the static fluid, ``|v_i|^2`` (invariant under rotations);
- ``edge``: each edge's strain rate ``eps_dot_e`` (invariant under rotations, translations and
  rigid rotation rates to first order: internal friction, not a drag).

Both coefficients are positive functions of static, invariant features and the modulus:
``beta_i = e^{b_node} kappa_i g_node(s_i, yhat)``, ``alpha_e = e^{b_edge} kappa_e
g_edge(s_e, yhat)``, ``g = softplus(MLP) / ln 2`` (``DampingCoefficient``; the last layer
starts at zero, ``g = 1``), ``s_i`` a node's features (``node_features``), ``s_e`` an edge's
(``meshodenet.energy.core.static_features``), ``kappa`` a fixed factor per element from the
least-squares start (1 without it). So ``D >= 0``, ``D = 0`` only at ``v = 0`` where
``beta > 0``, ``D`` is convex in ``v``, and the power of the dissipative force
``F = -dD/dv = -C v`` is ``F . v = -2 D <= 0``: it never adds energy.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from meshodenet.energy.core import (
    N_STATIC,
    _edge_geometry,
    scaled_means,
    standardised,
    zero_output_mlp,
)
from meshodenet.mesh.data import Mesh

#: The terms of the dissipation (``DissipationConfig.damping_terms``):
DAMPING_TERMS = {
    "node": "1/2 beta_i |v_i|^2: each node's drag against the static fluid",
    "edge": "1/2 alpha_e (t_e . (v_j - v_i) / l0_e)^2: each edge's strain rate",
}
#: Which of a term's parameters training moves (``DissipationConfig.damping_train``):
DAMPING_TRAIN = {
    "all": "the rate and the MLP",
    "rate": "the rate e^b alone; each element's share stays at its least-squares start",
    "none": "nothing: the coefficients stay at their least-squares start",
}
#: number of static features of a node (``node_features``)
N_NODE = 4
#: static features per term (edges: ``meshodenet.energy.core.static_features``)
N_FEATURES = {"node": N_NODE, "edge": N_STATIC}


def node_features(mesh: Mesh, reference: Mesh | None = None) -> np.ndarray:
    """``(N, N_NODE)`` float64: each node's mass over the mean, its share of the mesh's
    measure over the mean (half its edges' rest lengths on line meshes, a third of its
    triangles' rest areas on triangle meshes), its number of edges and of triangles; each
    column standardised over the nodes (a constant column becomes zero), or with
    ``reference`` (a model's training mesh) over that mesh's nodes."""
    if reference is None:
        f = _raw_node_features(mesh)[0]
        return standardised(f, f)
    ref, means = _raw_node_features(reference)
    return standardised(_raw_node_features(mesh, scaled_means(means, mesh, reference))[0], ref)


def _raw_node_features(mesh: Mesh, means: dict | None = None) -> tuple[np.ndarray, dict]:
    """``node_features`` before the columns are standardised, and the means the mass and the
    share are relative to: ``means`` where given (``scaled_means`` of a training mesh: the
    mass of a triangle mesh scaled as an area, of a line mesh as a length), else this mesh's
    own."""
    means = {} if means is None else dict(means)
    x = np.asarray(mesh.rest_pos, float)
    e = np.asarray(mesh.edges, np.int64)
    cells = np.asarray(mesh.cells, np.int64)
    n = mesh.n_nodes
    degree = np.bincount(e.reshape(-1), minlength=n).astype(float)
    count = np.bincount(cells.reshape(-1), minlength=n).astype(float)
    share = np.zeros(n)
    if len(cells):
        p = x[cells]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        np.add.at(share, cells.reshape(-1), np.repeat(area / 3, 3))
    else:
        length = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
        np.add.at(share, e.reshape(-1), np.repeat(length / 2, 2))
    mass = np.asarray(mesh.mass, float)
    size = "share_area" if len(cells) else "share_length"  # the mass goes as the share
    return np.stack([mass / means.setdefault(f"mass_{size}", mass.mean()),
                     share / means.setdefault(size, share.mean()), degree, count], 1), means


class DampingCoefficient(nn.Module):
    """``e^b kappa g(s, yhat)`` of one term's elements, ``b = b_0 + step * log_rate``,
    ``g = softplus(step * MLP) / ln 2`` (``layers`` hidden layers of ``hidden``, SiLU; the last
    layer starts at zero). ``b_0`` (a buffer) is the least-squares start; ``step`` scales how
    far an optimiser's step of a given size moves the coefficients (Adam moves every
    parameter by about its learning rate, whatever the gradient's size). ``train``: which
    parameters are trained (a key of ``DAMPING_TRAIN``)."""

    def __init__(self, n_static: int, hidden: int, layers: int, step: float = 1.0,
                 train: str = "all"):
        super().__init__()
        self.step = step
        self.mlp = zero_output_mlp(n_static + 1, hidden, layers)
        self.log_rate = nn.Parameter(torch.zeros(()))
        self.register_buffer("log_rate0", torch.zeros(()))
        if train != "all":  # the MLP stays at g = 1, the elements' shape at its start
            self.mlp.requires_grad_(False)
        if train == "none":
            self.log_rate.requires_grad_(False)

    def forward(self, static: torch.Tensor, yhat: torch.Tensor, kappa) -> torch.Tensor:
        """``(B, n)`` coefficients of the elements' ``static (n, F)`` features for the
        normalised log-moduli ``yhat (B,)``; ``kappa (n,)`` or 1."""
        B, (n, F) = len(yhat), static.shape
        inp = torch.cat([static.expand(B, n, F), yhat[:, None, None].expand(B, n, 1)], -1)
        g = nn.functional.softplus(self.step * self.mlp(inp)[..., 0]) / math.log(2.0)
        return torch.exp(self.log_rate0 + self.step * self.log_rate) * kappa * g


class Damping:
    """The damping matrix ``C`` of one step for ``B`` graphs of ``N`` nodes: node
    coefficients ``beta (B, N)`` and edge coefficients ``alpha (B, E)`` (either ``None`` when
    its term is off) with the edges' ``dq (B, E, 6)`` (the stretch's gradient at the step's
    start) and their coordinates ``dofs (E, 6)`` (``3 node + axis``)."""

    def __init__(self, beta, alpha, dq, dofs):
        self.beta, self.alpha, self.dq, self.dofs = beta, alpha, dq, dofs

    @classmethod
    def at(cls, x: torch.Tensor, beta, alpha, nodes, l0) -> Damping:
        """``C`` with the edge directions of positions ``x (B, N, 3)``."""
        dq = None if alpha is None else _edge_geometry(x, nodes, l0, False)[1]
        dofs = (3 * nodes[:, :, None] + torch.arange(3, device=nodes.device)).reshape(-1, 6)
        return cls(beta, alpha, dq, dofs)

    def rates(self, v: torch.Tensor) -> torch.Tensor:
        """The edges' strain rates ``dq_e . v_e`` ``(B, E)`` of velocities ``v (B, N, 3)``."""
        B = len(v)
        return (self.dq * v.reshape(B, -1)[:, self.dofs]).sum(-1)

    def dissipation(self, v: torch.Tensor) -> torch.Tensor:
        """``D = 1/2 v^T C v`` per graph ``(B,)``."""
        out = v.new_zeros(len(v))
        if self.beta is not None:
            out = out + 0.5 * (self.beta * (v * v).sum(-1)).sum(1)
        if self.alpha is not None:
            out = out + 0.5 * (self.alpha * self.rates(v) ** 2).sum(1)
        return out

    def force(self, v: torch.Tensor) -> torch.Tensor:
        """``dD/dv = C v`` ``(B, N, 3)`` (the dissipative force is its negative)."""
        B = len(v)
        out = torch.zeros_like(v) if self.beta is None else self.beta[..., None] * v
        if self.alpha is None:
            return out
        per = (self.alpha * self.rates(v))[..., None] * self.dq                # (B, E, 6)
        return out.reshape(B, -1).index_add(1, self.dofs.reshape(-1), per.reshape(B, -1)) \
            .reshape(v.shape)

    @torch.no_grad()
    def matrix(self, act: torch.Tensor, n_nodes: int) -> torch.Tensor:
        """``C (B, n, n)`` on the coordinates ``act (n,)`` (``d2D/dv2``)."""
        n = len(act)
        B = len(self.beta if self.beta is not None else self.alpha)
        dtype = (self.beta if self.beta is not None else self.alpha).dtype
        C = torch.zeros(B, n * n, dtype=dtype, device=act.device)
        if self.beta is not None:
            C[:, torch.arange(n, device=act.device) * (n + 1)] += self.beta[:, act // 3]
        if self.alpha is not None:
            where = torch.full((3 * n_nodes,), -1, dtype=torch.long, device=act.device)
            where[act] = torch.arange(n, device=act.device)
            dof = where[self.dofs]
            keep = ((dof[:, :, None] >= 0) & (dof[:, None, :] >= 0)).reshape(-1)
            flat = (dof[:, :, None] * n + dof[:, None, :]).reshape(-1)
            he = self.alpha[..., None, None] * self.dq[..., :, None] * self.dq[..., None, :]
            C.index_add_(1, flat[keep], he.reshape(B, -1)[:, keep])
        return C.reshape(B, n, n)

    def band(self, pattern) -> torch.Tensor:
        """``C`` on the unknowns of ``pattern`` (a ``BandPattern``, whose ``edge`` elements
        are these edges) in its band storage ``(B, width + 1, n)``."""
        he = {} if self.alpha is None else \
            {"edge": self.alpha[..., None, None] * self.dq[..., :, None] * self.dq[..., None, :]}
        diag = None if self.beta is None else self.beta[:, pattern.unknowns // 3]
        return pattern.band(he, diag)


__all__ = ["DAMPING_TERMS", "DAMPING_TRAIN", "Damping", "DampingCoefficient", "N_NODE", "node_features"]
