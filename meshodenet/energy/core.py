r"""A learned elastic energy over a mesh's edges, rod hinges and triangle hinges: its values,
forces and Hessians (the model that steps it is ``meshodenet.energy.model``).

The energy is a sum of element energies, each a function of one rotation- and
translation-invariant measure ``q`` of its element's deformation:

- edges ``(i, j)``: the stretch ``q = |x_j - x_i| / l_0 - 1``;
- rod hinges ``(a, b, c)`` of line meshes: the squared curvature ``q = |kappa_b - kappa_{b,0}|^2``,
  ``kappa_b = 2 e x f / (|e| |f| + e . f)`` of the edges ``e = x_b - x_a``, ``f = x_c - x_b``
  (``kappa_{b,0}`` of the rest shape; a fixed vector, so invariant under translations and
  rotations about the rest plane's normal, exact for planar rods);
- dihedral hinges ``(i, j, k, l)`` of triangle meshes (the interior edge ``(i, j)`` and the
  opposite vertices ``k``, ``l`` of its two triangles): the squared change of the dihedral
  angle ``q = (theta - theta_0)^2``, ``theta = atan2((a x b) . e/|e|, a . b)`` of the normals
  ``a = e x p``, ``b = m x e``, ``e = x_j - x_i``, ``p = x_k - x_i``, ``m = x_l - x_i``
  (``dihedral_angle``; invariant under all rigid motions, and under swapping the two triangles
  or the edge's ends, which negate both ``theta`` and ``theta_0``).

.. math::
    U_k = \frac{Y}{\bar Y} \, e^{a_t} \, \tfrac12 \hat q_k^{p_t} \, g_t(\hat q_k, s_k, \hat y),
    \qquad g_t = \operatorname{softplus}(\mathrm{MLP}_t) / \ln 2,

``p_t`` 2 for edges and 1 for both kinds of hinge (``POWER``: quadratic in the stretch, the
curvature and the change of angle at small strain), ``hat q = q / sigma_t`` (``sigma_t`` the
RMS of ``q`` over the training frames), ``s_k`` the element's normalised static features
(``static_features``), ``hat y`` the normalised logarithm of the modulus, ``a_t`` one
log-stiffness per element type. The rest shape is stress free and every element stiff at rest
(``g > 0``; ``q`` of hinges is a square, so its derivative vanishes at rest). The MLP's last
layer starts at zero (``g = 1``) and ``a_t`` at a least-squares fit of the training frames'
momentum balance (``ImplicitEnergy._fit_log_stiffness``); with a ``prior`` (``EnergySystem``,
``stiffness_prior = "features"``) each element's coefficient ``Y/Ybar e^{a_t}`` is multiplied
by its fixed factor ``kappa_k > 0``, a function of its rest features only. The geometry's
derivatives ``dq/dx``, ``d2q/dx2`` are analytic (``_edge_geometry``, ``_hinge_geometry``,
``_dihedral_geometry``; ``EnergySystem(analytic=False)`` takes the rod hinges' from
``torch.func``, as the first version did). ``BatchedEnergy`` evaluates the energy for a rollout's
batched Newton solves: banded Hessian, one MLP pass for all element types. The element energies
(``ElementEnergy``, ``clamp_q``'s saturation) live in ``meshodenet.energy.elements``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.func import hessian, jacrev, vmap

from meshodenet.energy.band import BandPattern
from meshodenet.energy.elements import (  # noqa: F401  (re-exported)
    N_STATIC,
    POWER,
    SATURATION,
    ElementEnergy,
    _clamped,
    _powered,
    zero_output_mlp,
)
from meshodenet.mesh.data import Mesh
from meshodenet.mesh.graph import rod_hinges, triangle_hinges

TYPES = ("edge", "hinge", "dihedral")
#: the power of the element size ``l`` in each type's invariant ``q`` at a given smooth
#: deformation: a stretch is a strain (``l^0``), a rod hinge's squared curvature binormal and a
#: dihedral hinge's squared change of angle are squared turning angles, ``(curvature l)^2``.
#: On a mesh with elements ``rho`` times the size, ``q / rho^LENGTH_POWER`` is the training
#: mesh's ``q`` of the same deformation (``ImplicitEnergy.transfer``).
LENGTH_POWER = {"edge": 0, "hinge": 2, "dihedral": 2}


def _curvature(e: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    d = e.norm(dim=-1) * f.norm(dim=-1) + (e * f).sum(-1)
    return 2.0 * torch.cross(e, f, dim=-1) / d[..., None]


def standardised(f: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Each column of ``f (n, F)`` standardised with the mean and std of ``ref``'s (``f``
    itself on the mesh the features are of, the training mesh's on another mesh); a column
    constant in ``ref`` becomes zero."""
    sd = ref.std(0)
    return np.where(sd > 1e-12, (f - ref.mean(0)) / np.where(sd > 0, sd, 1), 0.0)


def static_features(mesh: Mesh, reference: Mesh | None = None) -> dict:
    """Per element type: ``(nodes (n, k) long, features (n, N_STATIC) float64, rest)``.

    Edge features: ``log(l_0 / mean l_0)``, the summed area of its triangles over ``l_0^2``,
    the sum of the cotangents of the angles opposite it, its number of triangles. Rod hinge
    features (line meshes): ``log`` of its Voronoi length over the mean, zeros. Dihedral hinge
    features (triangle meshes, ``triangle_hinges``): ``log(l_0 / mean l_0)`` of the hinge
    edge, ``log`` of its two triangles' area ``A_1 + A_2`` over the mean, ``l_0^2 / (A_1 +
    A_2)`` (the discrete-shell stiffness factor, length over height) and the sum of the
    cotangents of the two angles opposite the edge (zero on a rectangle's diagonal), all
    symmetric in the two triangles. Each column is standardised over the elements (a constant
    column becomes zero), or with ``reference`` (a model's training mesh) over that mesh's
    elements of the same type (``standardised``). ``rest``: zeros ``(n, 3)`` for edges, the
    rest curvature binormal ``(n, 3)`` of rod hinges, the rest dihedral angle ``(n, 1)`` of
    dihedral hinges."""
    if reference is None:
        out = ref = _raw_static_features(mesh)[0]
    else:
        ref, means = _raw_static_features(reference)
        out = _raw_static_features(mesh, scaled_means(means, mesh, reference))[0]
    return {name: (nodes, standardised(f, ref[name][1] if name in ref else f), rest)
            for name, (nodes, f, rest) in out.items()}


def scaled_means(means: dict, mesh: Mesh, reference: Mesh) -> dict:
    """``means`` (lengths, and areas under keys ending in ``area``) of the mesh ``reference``
    scaled to the element size of ``mesh`` (``Mesh.length_scale``): on a mesh ``r`` times finer
    the sizes a feature is relative to are the training mesh's over ``r`` (``r^2``), exactly
    where the refinement is similar, whatever share of its elements lie on a boundary."""
    rho = mesh.length_scale / reference.length_scale
    return {k: v * rho ** (2 if k.endswith("area") else 1) for k, v in means.items()}


def _raw_static_features(mesh: Mesh, means: dict | None = None) -> tuple[dict, dict]:
    """``static_features`` before the columns are standardised, and the mean sizes its
    relative-size features (``log(l_0 / mean l_0)``, ...) are taken against: ``means`` where
    given (``scaled_means`` of a training mesh), else this mesh's own."""
    means = {} if means is None else dict(means)
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
    l0_mean = means.setdefault("edge_l0", l0.mean())
    out = {"edge": (e, np.stack([np.log(l0 / l0_mean), area / l0**2, cot, count], 1),
                    np.zeros((len(e), 3)))}
    hg = rod_hinges(mesh.edges, mesh.n_nodes) if not len(mesh.cells) else np.zeros((0, 3), int)
    if len(hg):
        ea, fb = x[hg[:, 1]] - x[hg[:, 0]], x[hg[:, 2]] - x[hg[:, 1]]
        lv = 0.5 * (np.linalg.norm(ea, axis=1) + np.linalg.norm(fb, axis=1))
        feats = np.zeros((len(hg), N_STATIC))
        feats[:, 0] = np.log(lv / means.setdefault("hinge_lv", lv.mean()))
        kap0 = _curvature(torch.as_tensor(ea), torch.as_tensor(fb)).numpy()
        out["hinge"] = (hg, feats, kap0)
    if len(mesh.cells):
        out["dihedral"] = _dihedral_features(x, triangle_hinges(mesh.cells), means)
    return out, means


def _dihedral_features(x: np.ndarray, hg: np.ndarray, means: dict):
    """``(hinges, features (n, N_STATIC), theta_0 (n, 1))`` of the dihedral hinges ``hg``
    (unstandardised; see ``static_features``; ``means`` as ``_raw_static_features``)."""
    e, p, m = (x[hg[:, c]] - x[hg[:, 0]] for c in (1, 2, 3))
    l0 = np.linalg.norm(e, axis=1)
    twice = [np.linalg.norm(np.cross(e, w), axis=1) for w in (p, m)]  # 2 A_1, 2 A_2
    area = 0.5 * (twice[0] + twice[1])
    # the angle at the opposite vertex w of the edge: cot = (e_i - w) . (e_j - w) / |... x ...|
    cot = sum(np.einsum("ni,ni->n", w, w - e) / np.maximum(t, 1e-300) for w, t in zip((p, m), twice))
    feats = np.stack([np.log(l0 / means.setdefault("dihedral_l0", l0.mean())),
                      np.log(area / means.setdefault("dihedral_area", area.mean())),
                      l0**2 / area, cot], 1)
    theta0 = dihedral_angle(torch.as_tensor(x[hg])).numpy()
    return hg, feats, theta0[:, None]


def _dihedral_sc(e, p, m):
    """``(s, c)`` with ``theta = atan2(s, c)``: ``s = -|e| e . (p x m)`` and
    ``c = (e . m)(e . p) - |e|^2 (p . m)`` (``(a x b) . e/|e|`` and ``a . b`` written out)."""
    ee = (e * e).sum(-1)
    s = -ee.sqrt() * (e * torch.cross(p, m, dim=-1)).sum(-1)
    c = (e * m).sum(-1) * (e * p).sum(-1) - ee * (p * m).sum(-1)
    return s, c


def dihedral_angle(xe: torch.Tensor, rest: torch.Tensor | None = None) -> torch.Tensor:
    """Signed dihedral angle ``theta`` in ``(-pi, pi]`` of hinges ``xe (..., 4, 3)`` (nodes
    ``(i, j, k, l)``): zero when flat, the angle between the normals ``a = e x p`` and
    ``b = m x e`` about ``e``. With ``rest`` (``theta_0``, shape ``(...)``) the change
    ``theta - theta_0`` wrapped to ``(-pi, pi]`` (``(s, c)`` rotated by ``-theta_0``: exactly
    ``theta`` when ``theta_0 = 0``)."""
    e, p, m = (xe[..., c, :] - xe[..., 0, :] for c in (1, 2, 3))
    s, c = _dihedral_sc(e, p, m)
    if rest is None:
        return torch.atan2(s, c)
    c0, s0 = torch.cos(rest), torch.sin(rest)
    return torch.atan2(s * c0 - c * s0, c * c0 + s * s0)


def measure(kind: str, xe: torch.Tensor, rest: torch.Tensor, l0: torch.Tensor) -> torch.Tensor:
    """The invariant ``q`` of elements ``xe (..., k, 3)``: an edge's stretch, a rod hinge's
    squared curvature ``|kappa_b - kappa_{b,0}|^2``, a dihedral hinge's squared change of angle
    ``(theta - theta_0)^2`` (both smooth at the rest shape)."""
    if kind == "edge":
        return (xe[..., 1, :] - xe[..., 0, :]).norm(dim=-1) / l0 - 1.0
    if kind == "dihedral":
        return dihedral_angle(xe, rest[..., 0]) ** 2
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


#: ``y = (e, f) = (x_b - x_a, x_c - x_b) = D x`` of a rod hinge's nodes ``x = (x_a, x_b, x_c)``
_D_HINGE = torch.cat([torch.cat([-torch.eye(3), torch.eye(3), torch.zeros(3, 3)], 1),
                      torch.cat([torch.zeros(3, 3), -torch.eye(3), torch.eye(3)], 1)]).double()


def _hinge_geometry(x, nodes, kap0, second: bool):
    r"""``q = |delta|^2``, ``delta = kappa_b - kappa_{b,0}``, of rod hinges ``nodes (n, 3)`` at
    ``x (B, N, 3)``, with ``dq = 2 delta^T dkappa`` ``(B, n, 9)`` and
    ``d2q = 2 (dkappa^T dkappa + sum_c delta_c d2kappa_c)`` ``(B, n, 9, 9)``.

    ``kappa = 2 w / d`` on ``y = (e, f)``, ``w = e x f``, ``d = |e| |f| + e . f``:
    ``dw = (-[f]_x, [e]_x)``, ``dd = (|f| u + f, |e| v + e)`` (``u = e/|e|``, ``v = f/|f|``),
    ``dkappa = 2 (dw - kappa/2 dd^T) / d``; ``d2w_c`` is ``eps_cij`` on ``(e_i, f_j)``, so
    ``sum_c delta_c d2w_c`` has the blocks ``(e, f) = -[delta]_x``, ``(f, e) = [delta]_x``;
    ``d2d``: ``(e, e) = |f| (I - u u^T) / |e|``, ``(f, f) = |e| (I - v v^T) / |f|``,
    ``(e, f) = u v^T + I``. With ``a = dw^T delta`` and ``s = delta . w``:
    ``sum_c delta_c d2kappa_c = 2 (sum_c delta_c d2w_c / d - (a dd^T + dd a^T) / d^2
    - s d2d / d^2 + 2 s dd dd^T / d^3)``. On the nodes ``D^T (.)`` and ``D^T (.) D``
    (``_D_HINGE``)."""
    xe = x[:, nodes]                                                  # (B, n, 3, 3)
    e, f = xe[..., 1, :] - xe[..., 0, :], xe[..., 2, :] - xe[..., 1, :]
    le, lf = e.norm(dim=-1, keepdim=True), f.norm(dim=-1, keepdim=True)
    w = torch.cross(e, f, dim=-1)
    d = le * lf + (e * f).sum(-1, keepdim=True)                       # (B, n, 1)
    kap = 2 * w / d
    delta = kap - kap0
    q = (delta * delta).sum(-1)
    u, v = e / le, f / lf
    dw = torch.cat([-_skew(f), _skew(e)], -1)                         # (B, n, 3, 6)
    dd = torch.cat([lf * u + f, le * v + e], -1)                      # (B, n, 6)
    dk = (2 * dw - kap[..., :, None] * dd[..., None, :]) / d[..., None]
    D = _D_HINGE.to(x)
    dq = (2 * (delta[..., None, :] @ dk)[..., 0, :]) @ D
    if not second:
        return q, dq, None
    I = torch.eye(3, dtype=x.dtype, device=x.device).expand(*e.shape[:-1], 3, 3)
    kd = _skew(delta)
    Z = torch.zeros_like(I)
    d2w = _blocks([[Z, -kd], [kd, Z]])
    d2d = _blocks([[lf[..., None] * (I - _outer(u, u)) / le[..., None], _outer(u, v) + I],
                   [_outer(v, u) + I, le[..., None] * (I - _outer(v, v)) / lf[..., None]]])
    a = (delta[..., None, :] @ dw)[..., 0, :]                         # (B, n, 6)
    s = (delta * w).sum(-1)[..., None, None]
    d1, d2 = d[..., None], d[..., None] ** 2
    sk = 2 * (d2w / d1 - (_outer(a, dd) + _outer(dd, a)) / d2 - s * d2d / d2
              + 2 * s * _outer(dd, dd) / (d2 * d1))
    d2q = 2 * (dk.transpose(-1, -2) @ dk + sk)
    return q, dq, D.T @ d2q @ D


def _skew(v):
    """``[v]_x (..., 3, 3)``, the matrix of ``w -> v x w``."""
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _outer(a, b):
    return a[..., :, None] * b[..., None, :]


def _blocks(rows):
    """A ``(..., 3r, 3r)`` matrix from ``r`` rows of ``r`` blocks ``(..., 3, 3)``."""
    return torch.cat([torch.cat(r, -1) for r in rows], -2)


#: ``y = (x_j - x_i, x_k - x_i, x_l - x_i) = D x`` of a hinge's nodes ``x = (x_i, x_j, x_k, x_l)``
_D = torch.cat([-torch.eye(3).repeat(3, 1), torch.eye(9)], 1).double()


def _dihedral_geometry(x, nodes, theta0, second: bool):
    r"""``q = d^2``, ``d = theta - theta_0`` (wrapped) of dihedral hinges ``nodes (n, 4)`` at
    ``x (B, N, 3)``, with ``dq = 2 d dtheta`` ``(B, n, 12)`` and
    ``d2q = 2 (dtheta dtheta^T + d d2theta)`` ``(B, n, 12, 12)``.

    ``theta = atan2(s, c)`` (``_dihedral_sc``) on ``y = (e, p, m)``:
    ``dtheta = (c ds - s dc) / r^2``, ``r^2 = s^2 + c^2``, and
    ``d2theta = (c d2s - s d2c) / r^2 + (2 s c (dc dc^T - ds ds^T)
    + (s^2 - c^2)(ds dc^T + dc ds^T)) / r^4``; with ``V = e . (p x m)``, ``l = |e|``,
    ``u = e / l``: ``s = -l V``, ``dV = (p x m, m x e, e x p)``, ``d2V`` the blocks
    ``(e, p) = -[m]_x``, ``(e, m) = [p]_x``, ``(p, m) = -[e]_x``; ``ds = -(V dl + l dV)``,
    ``dl = (u, 0, 0)``, ``d2s = -(V d2l + dl dV^T + dV dl^T + l d2V)``,
    ``d2l = (I - u u^T) / l`` on ``(e, e)``; ``dc = (m (e.p) + p (e.m) - 2 e (p.m),
    e (e.m) - m l^2, e (e.p) - p l^2)``, ``d2c``: ``(e, e) = m p^T + p m^T - 2 (p.m) I``,
    ``(e, p) = m e^T - 2 e m^T + (e.m) I``, ``(e, m) = p e^T - 2 e p^T + (e.p) I``,
    ``(p, m) = e e^T - l^2 I``, ``(p, p) = (m, m) = 0``. On the nodes ``D^T (.)`` and
    ``D^T (.) D`` (``_D``). As Tamstorf & Grinspun (2013) and ``groundtruth.hinge``, derived
    here again."""
    xe = x[:, nodes]                                                  # (B, n, 4, 3)
    e, p, m = (xe[..., c, :] - xe[..., 0, :] for c in (1, 2, 3))
    s, c = _dihedral_sc(e, p, m)
    d = dihedral_angle(xe, theta0[:, 0])
    ee, ep, em, pm = ((a * b).sum(-1)[..., None] for a, b in ((e, e), (e, p), (e, m), (p, m)))
    l = ee.sqrt()
    u = e / l
    V = (-s / l[..., 0])[..., None]
    r2 = (s * s + c * c)[..., None]
    zero = torch.zeros_like(e)
    dV = torch.cat([torch.cross(p, m, dim=-1), torch.cross(m, e, dim=-1),
                    torch.cross(e, p, dim=-1)], -1)
    dl = torch.cat([u, zero, zero], -1)
    ds = -(V * dl + l * dV)
    dc = torch.cat([m * ep + p * em - 2 * e * pm, e * em - m * ee, e * ep - p * ee], -1)
    dth = (c[..., None] * ds - s[..., None] * dc) / r2
    D = _D.to(x)
    dq = (2 * d[..., None] * dth) @ D
    if not second:
        return d * d, dq, None
    I = torch.eye(3, dtype=x.dtype, device=x.device).expand(*e.shape[:-1], 3, 3)
    Z = torch.zeros_like(I)
    km, kp, ke = _skew(m), _skew(p), _skew(e)
    d2V = _blocks([[Z, -km, kp], [km, Z, -ke], [-kp, ke, Z]])
    d2l = _blocks([[(I - _outer(u, u)) / l[..., None], Z, Z], [Z, Z, Z], [Z, Z, Z]])
    d2s = -(V[..., None] * d2l + _outer(dl, dV) + _outer(dV, dl) + l[..., None] * d2V)
    ce = _outer(m, p) + _outer(p, m) - 2 * pm[..., None] * I
    cp = _outer(m, e) - 2 * _outer(e, m) + em[..., None] * I
    cm = _outer(p, e) - 2 * _outer(e, p) + ep[..., None] * I
    cpm = _outer(e, e) - ee[..., None] * I
    t = lambda a: a.transpose(-1, -2)  # noqa: E731
    d2c = _blocks([[ce, cp, cm], [t(cp), Z, cpm], [t(cm), t(cpm), Z]])
    sc, r4 = (s * c)[..., None, None], r2[..., None] ** 2
    d2th = (c[..., None, None] * d2s - s[..., None, None] * d2c) / r2[..., None] \
        + (2 * sc * (_outer(dc, dc) - _outer(ds, ds))
           + (s * s - c * c)[..., None, None] * (_outer(ds, dc) + _outer(dc, ds))) / r4
    d2q = 2 * (_outer(dth, dth) + d[..., None, None] * d2th)
    return d * d, dq, D.T @ d2q @ D


class EnergySystem:
    """The learned energy of one mesh for a batch of ``B`` moduli, in float64.

    Every element energy is a function ``U(q)`` of one invariant ``q(x_e)``, so its gradient is
    ``U'(q) dq/dx`` and its Hessian ``U''(q) dq dq^T + U'(q) d2q/dx2``: the geometry
    (``q`` and its derivatives, ``Geometry``) is computed once per configuration without the
    parameters, and the network is evaluated on the scalars ``q`` only."""

    def __init__(self, terms: nn.ModuleDict, elems: dict, sigma: dict, youngs, ybar: float,
                 ylog: tuple, analytic: bool = True, prior: dict | None = None,
                 qrange: dict | None = None):
        self.terms, self.elems, self.sigma = terms, elems, sigma
        self.qrange = qrange or {}  # per kind (lo, hi) of the MLP's input (clamp_q)
        self.analytic = analytic  # rod hinges' geometry by hand (else torch.func, as before)
        self.prior = prior or {}  # per kind: each element's fixed stiffness factor kappa (n,)
        y = youngs.to(torch.float64)
        self.yrel = y / ybar
        self.yhat = (torch.log(y) - ylog[0]) / ylog[1]
        self.B = len(y)

    def scale(self, kind: str) -> torch.Tensor:
        """``(B, n)``: ``Y / Ybar``, times each element's factor ``kappa`` where the kind has
        one (the coefficient ``ElementEnergy`` multiplies by ``e^a 1/2 qhat^p g``)."""
        n = len(self.elems[kind][0])
        if kind not in self.prior:
            return self.yrel[:, None].expand(self.B, n)
        return self.yrel[:, None] * self.prior[kind]

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
                if kind == "dihedral":
                    out[kind] = _dihedral_geometry(x.detach(), nodes, rest, second)
                    continue
                if self.analytic:
                    out[kind] = _hinge_geometry(x.detach(), nodes, rest, second)
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
                                self.yhat[:, None].expand(self.B, n), self.scale(kind),
                                self.qrange.get(kind))

    def derivatives(self, kind, q, order: int, create_graph: bool):
        """``(U'(q), U''(q) or None)`` per element ``(B, n)`` (on the parameters' graph with
        ``create_graph``)."""
        nodes, static, _, _ = self.elems[kind]
        n, sig = len(nodes), self.sigma[kind]
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            _, d1, d2 = self.terms[kind].taylor(
                q / sig, static.expand(self.B, n, -1), self.yhat[:, None].expand(self.B, n),
                self.scale(kind), self.qrange.get(kind))
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

    def hessian(self, x: torch.Tensor, geo=None, act: torch.Tensor | None = None,
                create_graph: bool = False):
        """``d2U/dx2`` assembled from the element Hessians: dense ``(B, 3N, 3N)``, or only the
        rows and columns of the coordinates ``act`` (``(B, n, n)``, the others never formed);
        with ``create_graph`` differentiable in the parameters (``x`` a constant)."""
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            return self._hessian(x.detach(), geo, act, create_graph)

    def hessian_band(self, x: torch.Tensor, pattern: BandPattern, geo=None,
                     create_graph: bool = False, diag: torch.Tensor | None = None):
        """``d2U/dx2`` (plus ``diag (n,)``) on ``pattern``'s unknowns in its band storage
        ``(B, width + 1, n)`` (``BandPattern.band``): ``O(N)`` memory where ``hessian``'s
        matrix is ``O(N^2)``; with ``create_graph`` differentiable in the parameters (``x`` a
        constant)."""
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            return pattern.band(self.element_hessians(x.detach(), geo, create_graph), diag)

    def element_hessians(self, x, geo=None, create_graph: bool = False) -> dict:
        """Per kind its elements' Hessians ``U''(q) dq dq^T + U'(q) d2q`` ``(B, n_e, 3k, 3k)`` at
        ``x`` (``geo``: its ``geometry``, else computed)."""
        out = {}
        for kind, (q, dq, d2q) in (geo or self.geometry(x)).items():
            d1, d2 = self.derivatives(kind, q, 2, create_graph)
            out[kind] = d2[..., None, None] * dq[..., :, None] * dq[..., None, :] \
                + d1[..., None, None] * d2q
        return out

    def _hessian(self, x, geo, act, create_graph: bool):
        B, N, _ = x.shape
        where = torch.arange(3 * N, device=x.device) if act is None else \
            torch.full((3 * N,), -1, dtype=torch.long, device=x.device).index_copy_(
                0, act, torch.arange(len(act), device=x.device))
        n = 3 * N if act is None else len(act)
        H = x.new_zeros(B, n * n)
        for kind, he in self.element_hessians(x, geo, create_graph).items():
            dof = where[self._dofs(kind, N)]
            keep = ((dof[:, :, None] >= 0) & (dof[:, None, :] >= 0)).reshape(-1)
            flat = (dof[:, :, None] * n + dof[:, None, :]).reshape(-1)
            H.index_add_(1, flat[keep], he.reshape(B, -1)[:, keep])
        return H.reshape(B, n, n)


#: ``(q, dq, d2q)`` of each element type (``geometry``'s analytic functions)
_GEOMETRY = {"edge": lambda x, nodes, rest, l0, second: _edge_geometry(x, nodes, l0, second),
             "hinge": lambda x, nodes, rest, l0, second: _hinge_geometry(x, nodes, rest, second),
             "dihedral": lambda x, nodes, rest, l0, second: _dihedral_geometry(x, nodes, rest,
                                                                              second)}


class BatchedEnergy:
    """The energy of an ``EnergySystem`` on the ``n`` unknowns of a rollout's Newton solves,
    for any subset of its batch of ``B`` trajectories, without an autograd graph.

    The unknowns are the coordinates ``act`` of the free nodes, reordered (``band_order``) so
    that the Hessian is banded: ``unknowns (n,)`` are the flat coordinates ``3 node + axis`` in
    that order, ``width`` the number of sub-diagonals. ``evaluate`` gives the energy, its
    gradient and its Hessian in LAPACK's lower band storage (``ab[i - j, j] = H[i, j]``,
    ``i >= j``) from one MLP pass for all element types (their MLPs stacked along a leading
    axis and applied with ``torch.bmm``, the input layer's part from the static features and
    the modulus computed once here)."""

    def __init__(self, sys: EnergySystem, act: torch.Tensor, n_nodes: int,
                 pattern: BandPattern | None = None):
        self.sys, self.kinds = sys, list(sys.elems)
        pat = pattern or BandPattern(sys, act, n_nodes)
        self.unknowns, self.cols, self.n, self.width, self.maps = \
            pat.unknowns, pat.cols, pat.n, pat.width, pat.maps
        self._stack_mlps()

    @torch.no_grad()
    def _stack_mlps(self) -> None:
        sys, kinds = self.sys, self.kinds
        lins = [[m for m in sys.terms[k].mlp if isinstance(m, nn.Linear)] for k in kinds]
        self.counts = [len(sys.elems[k][0]) for k in kinds]
        nmax = max(self.counts)
        w0 = torch.stack([li[0].weight for li in lins])                 # (T, h, 2 + N_STATIC)
        static = w0.new_zeros(len(kinds), nmax, N_STATIC)
        for t, k in enumerate(kinds):
            static[t, :self.counts[t]] = sys.elems[k][1]
        c1 = static @ w0[..., 1:1 + N_STATIC].transpose(1, 2) \
            + torch.stack([li[0].bias for li in lins])[:, None]           # (T, nmax, h)
        # features first, elements last: (h, h) @ (h, M) is about twice as fast as
        # (M, h) @ (h, h) with MKL here
        #: the input layer without ``qhat``: (T, h, B, nmax)
        self.c1 = (c1[:, None] + sys.yhat[None, :, None, None] * w0[:, None, None, :, -1]) \
            .permute(0, 3, 1, 2).contiguous()
        self.w0q = w0[..., 0]                                            # (T, h)
        self.layers = [(torch.stack([li[j].weight for li in lins]),
                        torch.stack([li[j].bias for li in lins])[..., None])
                       for j in range(1, len(lins[0]))]
        #: ``Y / Ybar e^a kappa`` of every element: (T, B, nmax)
        self.coef = w0.new_zeros(len(kinds), sys.B, nmax)
        for t, k in enumerate(kinds):
            self.coef[t, :, :self.counts[t]] = sys.scale(k) * torch.exp(sys.terms[k].log_stiffness)
        self.sigma = [float(sys.sigma[k]) for k in kinds]
        #: (T, 2, 1, 1): each type's range of qhat (clamp_q; else none)
        self.clamp = bool(sys.qrange)
        self.qrange = torch.stack([torch.as_tensor(sys.qrange.get(k, (-math.inf, math.inf)),
                                                   dtype=w0.dtype, device=w0.device)
                                   for k in kinds])[..., None, None]

    def _mlp(self, qhat, idx, order: int):
        """``(g, g', g'')`` of all types' elements ``(T, b, nmax)`` at ``qhat (T, b, nmax)``
        (derivatives in ``qhat``, forward mode as ``ElementEnergy.taylor``; ``None`` above
        ``order``)."""
        T, b, nmax = qhat.shape
        c1 = self.c1 if b == self.c1.shape[2] else self.c1[:, :, idx]  # idx: all or a subset
        qin, s1, s2 = _clamped(qhat, (self.qrange[:, 0], self.qrange[:, 1])) if self.clamp \
            else (qhat, None, None)
        z = torch.addcmul(c1, qin[:, None], self.w0q[..., None, None])
        z = z.reshape(T, -1, b * nmax)                                   # (T, h, M)
        dz, d2z = self.w0q[..., None].expand_as(z), None
        if self.clamp:
            dz = dz * s1.reshape(T, 1, -1)
            d2z = self.w0q[..., None] * s2.reshape(T, 1, -1) if order > 1 else None
        for w, bias in self.layers:  # SiLU, then the next linear layer
            # fused kernels: silu_backward(u, z) = u silu'(z), sigmoid_backward(u, s) = u s (1 - s)
            if order > 1:
                sg = torch.sigmoid(z)
                a2 = torch.ops.aten.sigmoid_backward(2 + z * (1 - 2 * sg), sg) * dz**2
                d2z = a2 if d2z is None else a2 + torch.ops.aten.silu_backward(d2z, z)
            if order > 0:
                dz = torch.ops.aten.silu_backward(dz, z)
            z = torch.baddbmm(bias, w, nn.functional.silu(z))
            dz = torch.bmm(w, dz) if order > 0 else None
            d2z = torch.bmm(w, d2z) if d2z is not None else None
        o = z.reshape(T, b, nmax)
        ln2 = math.log(2.0)
        g = nn.functional.softplus(o) / ln2
        if order == 0:
            return g, None, None
        sg, do = torch.sigmoid(o), dz.expand(T, 1, b * nmax).reshape(T, b, nmax)
        g1 = sg * do / ln2
        if order == 1:
            return g, g1, None
        d2o = torch.zeros_like(o) if d2z is None else d2z.reshape(T, b, nmax)
        return g, g1, (sg * (1 - sg) * do**2 + sg * d2o) / ln2

    @torch.no_grad()
    def evaluate(self, x: torch.Tensor, idx: torch.Tensor, order: int):
        """``(U (b,), dU (b, n) or None, ab (b, width + 1, n) or None)``: the energy, with
        ``order`` 1 its gradient on the unknowns, with 2 also its Hessian (band storage), at
        positions ``x (b, N, 3)`` (float64, m) of the trajectories ``idx (b,)`` of the batch."""
        b, n, T = len(x), self.n, len(self.kinds)
        geo = {k: _GEOMETRY[k](x, nodes, rest, l0, order > 1) if order else
               (measure(k, x[:, nodes], rest, l0), None, None)
               for k, (nodes, _, rest, l0) in self.sys.elems.items()}
        qhat = x.new_zeros(T, b, max(self.counts))
        for t, k in enumerate(self.kinds):
            qhat[t, :, :self.counts[t]] = geo[k][0] / self.sigma[t]
        gs = self._mlp(qhat, idx, order)
        U = x.new_zeros(b)
        dU = x.new_zeros(b, n) if order else None
        ab = x.new_zeros(b, (self.width + 1) * n) if order > 1 else None
        for t, k in enumerate(self.kinds):
            m, sig = self.counts[t], self.sigma[t]
            u, d1, d2 = _powered(POWER[k], self.coef[t, idx, :m], qhat[t, :, :m],
                                 *(None if g is None else g[t, :, :m] for g in gs))
            U += u.sum(1)
            if not order:
                continue
            _, dq, d2q = geo[k]
            g_at, g_to, h_at, h_to = self.maps[k]
            dU.index_add_(1, g_to, (d1[..., None] / sig * dq).reshape(b, -1)[:, g_at])
            if order > 1:
                he = (d2 / sig**2)[..., None, None] * dq[..., :, None] * dq[..., None, :] \
                    + (d1 / sig)[..., None, None] * d2q
                ab.index_add_(1, h_to, he.reshape(b, -1)[:, h_at])
        return U, dU, None if ab is None else ab.reshape(b, self.width + 1, n)
