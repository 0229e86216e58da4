r"""``BatchedEnergy.evaluate`` in numpy for a planar mesh of edges and rod hinges solved in its
plane (the rod; the in-plane cantilever, whose in-plane solve has no bending term): the
batched solver's energy, gradient and banded Hessian from the same parameters, for rollouts
on the CPU (docs/ENERGY.md, "A numpy evaluation for planar meshes").

Why a second evaluation: the rod has 20 edges and 19 hinges, so every torch operation of
``BatchedEnergy.evaluate`` works on a few hundred numbers and its cost is torch's per-operation
overhead (about 0.8 ms per evaluation, 2.6 evaluations per interval: 4.4x the solver at h).
numpy's overhead per operation is several times smaller (the plate's larger arrays gain too:
numpy's MLP pass beats torch's fused kernels there), and in the plane the geometry is
smaller too: each node has the two unknowns ``(x, y)``, an edge's stretch derivatives are
``4``-vectors, a hinge's curvature is the scalar ``kappa = 2 (e x f)_z / (|e| |f| + e . f)``
(the ``z`` component of ``meshodenet.energy.core``'s curvature binormal, whose ``x`` and ``y``
components vanish for a planar rod, at rest and deformed) with ``6``-vectors and ``6 x 6``
Hessians, taken from the turning angle (``hinge_geometry``).

The formulas are those of ``meshodenet.energy.core._edge_geometry`` and ``_hinge_geometry``
restricted to the plane, and the MLP's forward-mode pass that of ``BatchedEnergy._mlp``, from
the stacked weights of the ``BatchedEnergy`` it is built from; ``evaluate`` equals its
``evaluate`` to round-off (``tests/test_energy_line.py``). ``PlanarLineEnergy.applies`` says
when it can stand in: edges and rod hinges only, unknowns in the plane only, no ``clamp_q``,
the CPU.
"""

from __future__ import annotations

import math

import numpy as np

from meshodenet.energy.core import POWER, BatchedEnergy

_LN2 = math.log(2.0)


def _in_plane(i):
    """An element's local coordinate ``3 node + axis`` as ``2 node + axis`` (``axis < 2``)."""
    return 2 * (i // 3) + i % 3


def _sigmoid(z):
    """``1 / (1 + e^-z)`` (twice as fast as scipy's ``expit`` on these sizes; ``e^-z``
    overflows to ``inf`` below ``z = -709``, giving 0: the caller ignores the warning)."""
    return 1.0 / (1.0 + np.exp(-z))


def _softplus(o):
    """``log(1 + e^o)`` (torch's ``softplus`` gives ``o`` itself above 20, 2e-9 lower)."""
    return np.logaddexp(0.0, o)


_BS, _BC = np.array([[1.0, 0], [0, -1]]), np.array([[0.0, 1], [1, 0]])
#: an edge's ``kron([[1, -1], [-1, 1]], M)`` from the entries ``(xx, xy, yy)`` of ``M`` (2 x 2)
_EDGE_D2 = np.stack([np.kron([[1.0, -1], [-1, 1]], m).reshape(-1) for m in
                     (np.diag([1.0, 0]), _BC, np.diag([0.0, 1]))])
_ROT = np.array([-1.0, 1, -1, 1])  # (e_x, e_y) -> (-e_y, e_x) after swapping the pairs
_EYE3 = np.array([1.0, 0, 1])  # the identity's (xx, xy, yy)
#: a hinge's ``d2phi`` from ``(s_e, c_e, s_f, c_f)`` (``hinge_geometry``)
_E, _F = np.array([[-1.0, 1, 0], [1, -1, 0], [0, 0, 0]]), np.array([[0.0, 0, 0], [0, 1, -1],
                                                                  [0, -1, 1]])
_HINGE_D2 = np.stack([np.kron(s, b).reshape(-1) for s in (_E, _F) for b in (_BS, _BC)])
#: a hinge's ``dphi`` on its nodes from ``(g_e, g_f)``
_HINGE_D1 = np.array([[1.0, 0, -1, 0, 0, 0], [0, 1, 0, -1, 0, 0],
                      [0, 0, -1, 0, 1, 0], [0, 0, 0, -1, 0, 1]])


def edge_geometry(x, nodes, l0, second: bool):
    """``(q, dq (b, m, 4), parts or None)`` of the stretch ``q = |e| / l0 - 1`` of the edges
    ``nodes (m, 2)`` at in-plane positions ``x (b, N, 2)``: ``dq = (-t, t) / l0``; ``parts``
    give ``element_hessian``'s ``alpha dq dq^T + beta d2q`` with ``d2q = [[P, -P], [-P, P]] /
    (l0 |e|)``, ``P = I - t t^T``."""
    e = x[:, nodes[:, 1]] - x[:, nodes[:, 0]]
    le = np.sqrt((e * e).sum(-1))
    t = e / le[..., None]
    q = le / l0 - 1.0
    dq = np.concatenate([-t, t], -1) / l0[:, None]
    if not second:
        return q, dq, None
    tx, ty = t[..., 0], t[..., 1]
    return q, dq, ("edge", np.stack([tx * tx, tx * ty, ty * ty], -1), 1 / (l0 * le), 1 / l0**2)


def hinge_geometry(x, nodes, kap0, second: bool):
    r"""``(q, dq (b, m, 6), parts or None)`` of ``q = (kappa - kappa_0)^2`` of the rod hinges
    ``nodes (m, 3)`` at in-plane positions ``x (b, N, 2)``, ``kappa_0 (m,)`` the rest
    curvature's ``z`` component; ``parts`` give ``element_hessian``.

    ``kappa = 2 w / (|e| |f| + e . f)``, ``w = (e x f)_z``, is ``2 tan(phi / 2)`` of the
    turning angle ``phi = theta_f - theta_e`` (``theta`` an edge's direction), so ``dkappa =
    k_1 dphi``, ``d2kappa = k_2 dphi dphi^T + k_1 d2phi`` with ``k_1 = 1 + kappa^2 / 4``,
    ``k_2 = kappa k_1 / 2``; ``dtheta_e / de = (-e_y, e_x) / |e|^2 = g_e`` and ``d2theta_e /
    de^2 = H_e = [[s_e, c_e], [c_e, -s_e]]`` with ``s_e = 2 e_x e_y / |e|^4``, ``c_e = (e_y^2
    - e_x^2) / |e|^4``: on the nodes ``dphi = (g_e, -g_e - g_f, g_f)`` and ``d2phi`` the
    blocks ``(a, a) = -H_e``, ``(a, b) = H_e``, ``(b, b) = H_f - H_e``, ``(b, c) = -H_f``,
    ``(c, c) = H_f``. Then ``dq = c_1 dphi``, ``d2q = c_2 dphi dphi^T + c_1 d2phi`` with
    ``c_1 = 2 delta k_1``, ``c_2 = 2 (k_1^2 + delta k_2)`` (``delta = kappa - kappa_0``):
    ``meshodenet.energy.core._hinge_geometry``'s values in the plane."""
    xe = x[:, nodes].reshape(len(x), len(nodes), 6)
    ef = xe[..., 2:] - xe[..., :4]                                    # (e, f): (b, m, 4)
    sq = ef * ef
    l2 = sq.reshape(*sq.shape[:-1], 2, 2).sum(-1)                     # (|e|^2, |f|^2)
    e, f = ef[..., :2], ef[..., 2:]
    w = e[..., 0] * f[..., 1] - e[..., 1] * f[..., 0]
    kap = 2 * w / (np.sqrt(l2[..., 0] * l2[..., 1]) + (e * f).sum(-1))
    delta = kap - kap0
    k1 = 1 + 0.25 * kap * kap
    l2 = np.repeat(l2, 2, -1)                                         # (b, m, 4)
    dphi = (ef[..., [1, 0, 3, 2]] * _ROT / l2) @ _HINGE_D1
    c1 = 2 * delta * k1
    dq = c1[..., None] * dphi
    if not second:
        return delta * delta, dq, None
    # (s_e, c_e, s_f, c_f) |e|^4 or |f|^4: (2 e_x e_y, e_y^2 - e_x^2, ...)
    sc = np.stack([2 * ef[..., 0::2] * ef[..., 1::2], sq[..., 1::2] - sq[..., 0::2]], -1) \
        .reshape(ef.shape) / (l2 * l2)
    return delta * delta, dq, ("hinge", dphi, c1, 2 * k1 * (k1 + 0.5 * delta * kap), sc)


def element_hessian(parts, alpha, beta):
    """``alpha dq dq^T + beta d2q`` ``(b, m, 2k * 2k)`` of every element from its
    geometry's ``parts`` and ``alpha, beta (b, m)``; ``d2q`` itself with ``(0, 1)``."""
    if parts[0] == "edge":  # kron([[1, -1], [-1, 1]], (alpha / l0^2 - beta / (l0 |e|)) t t^T
        _, tt, inv, il2 = parts  # + beta / (l0 |e|) I)
        bi = beta * inv
        return ((alpha * il2 - bi)[..., None] * tt + bi[..., None] * _EYE3) @ _EDGE_D2
    _, dphi, c1, c2, sc = parts
    w = alpha * c1 * c1 + beta * c2
    return ((w[..., None] * dphi)[..., :, None] * dphi[..., None, :]).reshape(*w.shape, 36) \
        + ((beta * c1)[..., None] * sc) @ _HINGE_D2


_GEOMETRY = {"edge": lambda x, nodes, rest, l0, second: edge_geometry(x, nodes, l0, second),
             "hinge": lambda x, nodes, rest, l0, second: hinge_geometry(x, nodes, rest, second)}


class PlanarLineEnergy:
    """``BatchedEnergy.evaluate`` on numpy arrays for a planar mesh of edges and rod hinges
    whose unknowns are in-plane coordinates (``applies``); ``unknowns`` and ``width`` are the
    ``BatchedEnergy``'s (its banded order), ``numpy = True`` tells the solver which arrays it
    takes."""

    numpy = True

    def __init__(self, be: BatchedEnergy):
        if not self.applies(be):
            raise ValueError("PlanarLineEnergy: needs a planar mesh of edges and rod hinges "
                             "solved in its plane, without clamp_q, on the CPU")
        self.kinds, self.counts, self.sigma = be.kinds, be.counts, be.sigma
        self.unknowns = self.cols = be.cols
        self.n, self.width = be.n, be.width
        self.elems = {}
        # ``be.maps``' gradient and band entries, from its elements' 3k local coordinates to
        # the 2k in-plane ones here (every unknown is in-plane: ``applies``)
        g_to, g_at, h_to, h_at, offset = [], [], [], [], [0, 0]
        for k in self.kinds:
            nodes, _, rest, l0 = (t.numpy() for t in be.sys.elems[k])
            k3, k2 = 3 * nodes.shape[1], 2 * nodes.shape[1]
            gi, gt, hi, ht = (m.cpu().numpy() for m in be.maps[k])
            rc = hi % k3**2
            g_at.append(offset[0] + gi // k3 * k2 + _in_plane(gi % k3))
            h_at.append(offset[1] + hi // k3**2 * k2**2 + _in_plane(rc // k3) * k2 + _in_plane(rc % k3))
            g_to.append(gt)
            h_to.append(ht)
            offset[0] += len(nodes) * k2
            offset[1] += len(nodes) * k2**2
            self.elems[k] = (nodes, rest[:, 2] if k == "hinge" else rest, l0)
        self.g_at, self.g_to = np.concatenate(g_at), np.concatenate(g_to)
        self.h_at, self.h_to = np.concatenate(h_at), np.concatenate(h_to)
        self.c1, self.w0q = be.c1.numpy(), be.w0q.numpy()
        self.layers = [(w.numpy(), bias.numpy()) for w, bias in be.layers]
        # U = c/2 qhat^p g (``meshodenet.energy.elements._powered``) for all types at once: c
        # with the 1 / ln 2 of g (``_mlp``) and the 1 / sigma, 1 / sigma^2 of dq/dx's chain rule
        coef = be.coef.numpy() / _LN2
        sig = np.array(self.sigma)[:, None, None]
        power = np.array([POWER[k] for k in self.kinds], float)[:, None, None]
        self.coef = (0.5 * coef, coef / sig, coef / sig**2)
        #: per type (T, 1, 1): p - 1, p / 2, p, p (p - 1) / 2
        self.powers = (power - 1, power / 2, power, power * (power - 1) / 2)
        self._scatter = {}

    @staticmethod
    def applies(be: BatchedEnergy) -> bool:
        """Whether ``be``'s energy can be evaluated here: only edges and rod hinges, every
        unknown an ``x`` or ``y`` coordinate, no ``clamp_q``, tensors on the CPU."""
        return (set(be.kinds) <= {"edge", "hinge"} and not be.clamp
                and be.unknowns.device.type == "cpu" and bool((be.unknowns % 3 < 2).all()))

    def _mlp(self, qhat, idx, order: int):
        """``(g, g', g'')`` ``ln 2`` of every element ``(T, b, nmax)`` at ``qhat (T, b,
        nmax)`` (``BatchedEnergy._mlp``: forward mode by hand)."""
        T, b, nmax = qhat.shape
        c1 = self.c1 if b == self.c1.shape[2] else self.c1[:, :, idx]
        z = (c1 + qhat[:, None] * self.w0q[..., None, None]).reshape(T, -1, b * nmax)
        dz, d2z = self.w0q[..., None], None
        for w, bias in self.layers:  # SiLU, then the next linear layer
            # silu(z) = z s, silu' = s + z p, silu'' = p (2 + z - 2 z s), p = s (1 - s)
            sg = _sigmoid(z)
            zs = z * sg
            if order > 0:
                p = sg - sg * sg
                a1 = sg + z * p
                if order > 1:
                    a2 = p * (z + 2 - 2 * zs) * (dz * dz)
                    d2z = a2 if d2z is None else a2 + a1 * d2z
                dz = w @ (a1 * dz)
                d2z = None if d2z is None else w @ d2z
            z = w @ zs + bias
        # g = softplus(o) / ln 2: the 1 / ln 2 is in ``coef``
        o = z.reshape(T, b, nmax)
        g = _softplus(o)
        if order == 0:
            return g, None, None
        sg, do = _sigmoid(o), np.broadcast_to(dz, (T, 1, b * nmax)).reshape(T, b, nmax)
        g1 = sg * do
        if order == 1:
            return g, g1, None
        d2o = 0.0 if d2z is None else d2z.reshape(T, b, nmax)
        return g, g1, sg * ((1 - sg) * do**2 + d2o)

    def evaluate(self, x: np.ndarray, idx: np.ndarray, order: int):
        """``(U (b,), dU (b, n) or None, ab (b, width + 1, n) or None)`` at positions ``x
        (b, N, 3)`` of the trajectories ``idx`` (``BatchedEnergy.evaluate``)."""
        with np.errstate(over="ignore"):
            return self._evaluate(x[..., :2], idx, order)

    def _evaluate(self, xy, idx, order):
        b, n, T = len(xy), self.n, len(self.kinds)
        full = b == self.coef[0].shape[1]  # the whole batch, in order (trajectories only drop out)
        qhat = np.zeros((T, b, max(self.counts)))
        geo = []
        for t, k in enumerate(self.kinds):
            nodes, rest, l0 = self.elems[k]
            geo.append(_GEOMETRY[k](xy, nodes, rest, l0, order > 1))
            np.divide(geo[-1][0], self.sigma[t], out=qhat[t, :, :self.counts[t]])
        g, g1, g2 = self._mlp(qhat, idx, order)
        pm1, p2, p, a0 = self.powers
        ch, c1, c2 = self.coef if full else (c[:, idx] for c in self.coef)
        qp1 = qhat**pm1
        qp = qp1 * qhat
        U = (ch * qp * g).sum((0, 2))
        if not order:
            return U, None, None
        hq = 0.5 * qp
        d1 = c1 * (p2 * qp1 * g + hq * g1)                    # dU/dq, with 1 / sigma
        d2 = c2 * (a0 * g + p * qp1 * g1 + hq * g2) if order > 1 else None
        grads, hessians = [], []
        for t in range(T):
            m = self.counts[t]
            _, dq, parts = geo[t]
            grads.append((d1[t, :, :m, None] * dq).reshape(b, -1))
            if order > 1:
                hessians.append(element_hessian(parts, d2[t, :, :m], d1[t, :, :m]).reshape(b, -1))
        if b not in self._scatter:  # bincount's bins of the gradient and the band, per b
            rows = np.arange(b)[:, None]
            self._scatter[b] = ((rows * n + self.g_to).reshape(-1),
                                (rows * (self.width + 1) * n + self.h_to).reshape(-1))
        gi, hi = self._scatter[b]
        dU = np.bincount(gi, np.concatenate(grads, 1)[:, self.g_at].reshape(-1), b * n)
        if order == 1:
            return U, dU.reshape(b, n), None
        ab = np.bincount(hi, np.concatenate(hessians, 1)[:, self.h_at].reshape(-1),
                         b * (self.width + 1) * n)
        return U, dU.reshape(b, n), ab.reshape(b, self.width + 1, n)
