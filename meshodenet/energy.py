r"""A learned elastic energy over a mesh's edges and rod hinges: its values, forces and Hessians
(the model that steps it is ``meshodenet.models.energy``).

The energy is a sum of element energies, each a function of one rotation- and
translation-invariant measure ``q`` of its element's deformation:

- edges ``(i, j)``: the stretch ``q = |x_j - x_i| / l_0 - 1``;
- rod hinges ``(a, b, c)`` of line meshes: the squared curvature ``q = |kappa_b - kappa_{b,0}|^2``,
  ``kappa_b = 2 e x f / (|e| |f| + e . f)`` of the edges ``e = x_b - x_a``, ``f = x_c - x_b``
  (``kappa_{b,0}`` of the rest shape; a fixed vector, so invariant under translations and
  rotations about the rest plane's normal, exact for planar rods).

.. math::
    U_k = \frac{Y}{\bar Y} \, e^{a_t} \, \tfrac12 \hat q_k^{p_t} \, g_t(\hat q_k, s_k, \hat y),
    \qquad g_t = \operatorname{softplus}(\mathrm{MLP}_t) / \ln 2,

``p_t`` 2 for edges and 1 for hinges (``POWER``: quadratic in the stretch and the curvature at
small strain), ``hat q = q / sigma_t`` (``sigma_t`` the RMS of ``q`` over the training frames),
``s_k`` the element's normalised static features (``static_features``), ``hat y`` the normalised
logarithm of the modulus, ``a_t`` one log-stiffness per element type. The rest shape is stress
free and every element stiff at rest (``g > 0``). The MLP's last layer starts at zero
(``g = 1``) and ``a_t`` at a least-squares fit of the training frames' momentum balance
(``ImplicitEnergy._fit_log_stiffness``).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.func import hessian, jacrev, vmap

from meshodenet.data import Mesh
from meshodenet.graph import rod_hinges

TYPES = ("edge", "hinge")
N_STATIC = 4


def _curvature(e: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    d = e.norm(dim=-1) * f.norm(dim=-1) + (e * f).sum(-1)
    return 2.0 * torch.cross(e, f, dim=-1) / d[..., None]


def static_features(mesh: Mesh) -> dict:
    """Per element type: ``(nodes (n, k) long, features (n, N_STATIC) float64, rest (n, 3))``.

    Edge features: ``log(l_0 / mean l_0)``, the summed area of its triangles over ``l_0^2``,
    the sum of the cotangents of the angles opposite it, its number of triangles. Hinge
    features: ``log`` of its Voronoi length over the mean, zeros. Each column is standardised
    over the elements (a constant column becomes zero). ``rest`` is the rest curvature
    binormal of hinges (zeros for edges)."""
    x = np.asarray(mesh.rest_pos, float)
    e = np.asarray(mesh.edges, np.int64)
    l0 = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
    area, cot, count = np.zeros(len(e)), np.zeros(len(e)), np.zeros(len(e))
    index = {tuple(sorted(map(int, p))): k for k, p in enumerate(e)}
    for tri in np.asarray(mesh.cells, np.int64):
        p = x[tri]
        a = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        for m in range(3):
            i, j, o = tri[m], tri[(m + 1) % 3], tri[(m + 2) % 3]
            k = index.get(tuple(sorted((int(i), int(j)))))
            if k is None:
                continue
            u, w = x[i] - x[o], x[j] - x[o]
            area[k] += a
            cot[k] += np.dot(u, w) / max(np.linalg.norm(np.cross(u, w)), 1e-300)
            count[k] += 1
    out = {"edge": (e, np.stack([np.log(l0 / l0.mean()), area / l0**2, cot, count], 1),
                    np.zeros((len(e), 3)))}
    hg = rod_hinges(mesh.edges, mesh.n_nodes) if not len(mesh.cells) else np.zeros((0, 3), int)
    if len(hg):
        ea, fb = x[hg[:, 1]] - x[hg[:, 0]], x[hg[:, 2]] - x[hg[:, 1]]
        lv = 0.5 * (np.linalg.norm(ea, axis=1) + np.linalg.norm(fb, axis=1))
        feats = np.zeros((len(hg), N_STATIC))
        feats[:, 0] = np.log(lv / lv.mean())
        kap0 = _curvature(torch.as_tensor(ea), torch.as_tensor(fb)).numpy()
        out["hinge"] = (hg, feats, kap0)
    for name, (nodes, f, rest) in out.items():
        sd = f.std(0)
        out[name] = (nodes, np.where(sd > 1e-12, (f - f.mean(0)) / np.where(sd > 0, sd, 1), 0.0),
                     rest)
    return out


def measure(kind: str, xe: torch.Tensor, rest: torch.Tensor, l0: torch.Tensor) -> torch.Tensor:
    """The invariant ``q`` of elements ``xe (..., k, 3)``: an edge's stretch, a hinge's squared
    curvature ``|kappa_b - kappa_{b,0}|^2`` (smooth at the rest shape)."""
    if kind == "edge":
        return (xe[..., 1, :] - xe[..., 0, :]).norm(dim=-1) / l0 - 1.0
    kap = _curvature(xe[..., 1, :] - xe[..., 0, :], xe[..., 2, :] - xe[..., 1, :]) - rest
    return (kap * kap).sum(-1)


def _edge_geometry(x, nodes, l0, second: bool):
    """Stretch ``q = |e| / l0 - 1`` of edges and its first and second derivatives in
    ``(x_i, x_j)``: ``dq = (-t, t) / l0``, ``d2q = [[P, -P], [-P, P]] / (l0 |e|)``,
    ``P = I - t t^T``."""
    e = x[:, nodes[:, 1]] - x[:, nodes[:, 0]]                       # (B, n, 3)
    le = e.norm(dim=-1)
    t = e / le[..., None]
    q = le / l0 - 1.0
    dq = torch.cat([-t, t], -1) / l0[:, None]
    if not second:
        return q, dq, None
    P = torch.eye(3, dtype=x.dtype, device=x.device) - t[..., :, None] * t[..., None, :]
    P = P / (l0 * le)[..., None, None]
    d2q = torch.cat([torch.cat([P, -P], -1), torch.cat([-P, P], -1)], -2)
    return q, dq, d2q


#: the energy's dependence on the normalised invariant at small strain: quadratic in an edge's
#: stretch, linear in a hinge's squared curvature (quadratic in the curvature)
POWER = {"edge": 2, "hinge": 1}


class ElementEnergy(nn.Module):
    """``U = Y/Ybar exp(a) 1/2 qhat^p g(qhat, s, yhat)`` of one element type
    (``p = POWER[kind]``)."""

    def __init__(self, kind: str, hidden: int, layers: int):
        super().__init__()
        self.power = POWER[kind]
        dims = [2 + N_STATIC] + [hidden] * layers
        mods = []
        for a, b in zip(dims[:-1], dims[1:]):
            mods += [nn.Linear(a, b), nn.SiLU()]
        last = nn.Linear(dims[-1], 1)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*mods, last)
        self.log_stiffness = nn.Parameter(torch.zeros(()))

    def forward(self, qhat, static, yhat, yrel):
        inp = torch.cat([qhat[..., None], static, yhat[..., None]], -1)
        g = nn.functional.softplus(self.mlp(inp)[..., 0]) / math.log(2.0)
        return yrel * torch.exp(self.log_stiffness) * 0.5 * qhat**self.power * g

    def taylor(self, qhat, static, yhat, yrel):
        """``(U, dU/dqhat, d2U/dqhat2)``, propagated through the MLP in forward mode by hand
        (no autograd graph of its own: differentiable in the parameters, and about three times
        cheaper than double backward)."""
        z = torch.cat([qhat[..., None], static, yhat[..., None]], -1)
        dz = d2z = None
        for layer in self.mlp:
            if isinstance(layer, nn.Linear):
                w = layer.weight
                dz = w[:, 0].expand(*z.shape[:-1], -1) if dz is None else dz @ w.T
                d2z = None if d2z is None else d2z @ w.T
                z = layer(z)
            else:  # SiLU: a = z s(z)
                sg = torch.sigmoid(z)
                a1 = sg * (1 + z * (1 - sg))
                a2 = sg * (1 - sg) * (2 + z * (1 - 2 * sg))
                d2z = a2 * dz**2 + (0 if d2z is None else a1 * d2z)
                dz = a1 * dz
                z = z * sg
        o, do = z[..., 0], dz[..., 0]
        d2o = torch.zeros_like(o) if d2z is None else d2z[..., 0]
        sg = torch.sigmoid(o)
        ln2 = math.log(2.0)
        g = nn.functional.softplus(o) / ln2
        g1 = sg * do / ln2
        g2 = (sg * (1 - sg) * do**2 + sg * d2o) / ln2
        c = yrel * torch.exp(self.log_stiffness)
        q = qhat
        if self.power == 2:
            return (c * 0.5 * q**2 * g, c * (q * g + 0.5 * q**2 * g1),
                    c * (g + 2 * q * g1 + 0.5 * q**2 * g2))
        return c * 0.5 * q * g, c * 0.5 * (g + q * g1), c * (g1 + 0.5 * q * g2)


class EnergySystem:
    """The learned energy of one mesh for a batch of ``B`` moduli, in float64.

    Every element energy is a function ``U(q)`` of one invariant ``q(x_e)``, so its gradient is
    ``U'(q) dq/dx`` and its Hessian ``U''(q) dq dq^T + U'(q) d2q/dx2``: the geometry
    (``q`` and its derivatives, ``Geometry``) is computed once per configuration without the
    parameters, and the network is evaluated on the scalars ``q`` only."""

    def __init__(self, terms: nn.ModuleDict, elems: dict, sigma: dict, youngs, ybar: float,
                 ylog: tuple):
        self.terms, self.elems, self.sigma = terms, elems, sigma
        y = youngs.to(torch.float64)
        self.yrel = y / ybar
        self.yhat = (torch.log(y) - ylog[0]) / ylog[1]
        self.B = len(y)

    def _dofs(self, kind, N):
        nodes = self.elems[kind][0]
        k = nodes.shape[1]
        return (3 * nodes[:, :, None] + torch.arange(3, device=nodes.device)).reshape(-1, 3 * k)

    def geometry(self, x: torch.Tensor, second: bool = True) -> dict:
        """Per kind ``(q (B, n), dq (B, n, 3k), d2q (B, n, 3k, 3k) or None)`` at ``x (B, N, 3)``
        (no graph)."""
        out = {}
        with torch.no_grad():
            for kind, (nodes, _, rest, l0) in self.elems.items():
                n, k = nodes.shape
                if kind == "edge":
                    out[kind] = _edge_geometry(x.detach(), nodes, l0, second)
                    continue
                xe = x.detach()[:, nodes].reshape(-1, 3 * k)
                r = rest.repeat(self.B, 1)
                ll = l0.repeat(self.B)
                f = lambda z, rr, lll, kind=kind, k=k: measure(kind, z.reshape(k, 3), rr, lll)
                q = measure(kind, xe.reshape(-1, k, 3), r, ll)
                dq = vmap(jacrev(f))(xe, r, ll)
                d2q = vmap(hessian(f))(xe, r, ll) if second else None
                out[kind] = (q.reshape(self.B, n), dq.reshape(self.B, n, 3 * k),
                             None if d2q is None else d2q.reshape(self.B, n, 3 * k, 3 * k))
        return out

    def _energy_q(self, kind, q):
        nodes, static, _, _ = self.elems[kind]
        n = len(nodes)
        return self.terms[kind](q / self.sigma[kind], static.expand(self.B, n, -1),
                                self.yhat[:, None].expand(self.B, n),
                                self.yrel[:, None].expand(self.B, n))

    def derivatives(self, kind, q, order: int, create_graph: bool):
        """``(U'(q), U''(q) or None)`` per element ``(B, n)`` (on the parameters' graph with
        ``create_graph``)."""
        nodes, static, _, _ = self.elems[kind]
        n, sig = len(nodes), self.sigma[kind]
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            _, d1, d2 = self.terms[kind].taylor(
                q / sig, static.expand(self.B, n, -1), self.yhat[:, None].expand(self.B, n),
                self.yrel[:, None].expand(self.B, n))
        return d1 / sig, (d2 / sig**2 if order > 1 else None)

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """Total energy per graph ``(B,)`` (differentiable in the parameters)."""
        total = x.new_zeros(self.B)
        for kind, (nodes, _, rest, l0) in self.elems.items():
            q = measure(kind, x.detach()[:, nodes], rest, l0)
            total = total + self._energy_q(kind, q).sum(1)
        return total

    def gradient(self, x: torch.Tensor, create_graph: bool = False, geo=None) -> torch.Tensor:
        """``dU/dx (B, N, 3)`` at ``x`` (taken as a constant); with ``create_graph``
        differentiable in the parameters."""
        B, N, _ = x.shape
        geo = geo or self.geometry(x, second=False)
        g = x.new_zeros(B, 3 * N)
        for kind, (q, dq, _) in geo.items():
            d1, _ = self.derivatives(kind, q, 1, create_graph)
            g = g.index_add(1, self._dofs(kind, N).reshape(-1),
                            (d1[..., None] * dq).reshape(B, -1))
        return g.reshape(B, N, 3)

    @torch.no_grad()
    def hessian(self, x: torch.Tensor, geo=None, act: torch.Tensor | None = None):
        """``d2U/dx2`` assembled from the element Hessians: dense ``(B, 3N, 3N)``, or only the
        rows and columns of the coordinates ``act`` (``(B, n, n)``, the others never formed)."""
        B, N, _ = x.shape
        geo = geo or self.geometry(x)
        where = torch.arange(3 * N, device=x.device) if act is None else \
            torch.full((3 * N,), -1, dtype=torch.long, device=x.device).index_copy_(
                0, act, torch.arange(len(act), device=x.device))
        n = 3 * N if act is None else len(act)
        H = x.new_zeros(B, n * n)
        for kind, (q, dq, d2q) in geo.items():
            d1, d2 = self.derivatives(kind, q, 2, False)
            he = d2[..., None, None] * dq[..., :, None] * dq[..., None, :] \
                + d1[..., None, None] * d2q
            dof = where[self._dofs(kind, N)]
            keep = ((dof[:, :, None] >= 0) & (dof[:, None, :] >= 0)).reshape(-1)
            flat = (dof[:, :, None] * n + dof[:, None, :]).reshape(-1)
            H.index_add_(1, flat[keep], he.reshape(B, -1)[:, keep])
        return H.reshape(B, n, n)
