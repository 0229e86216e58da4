"""The element energies of ``meshodenet.energy.core`` (which re-exports everything here): ``U =
Y/Ybar e^a 1/2 qhat^p g`` of one element type with ``g`` a softplus of an MLP, its value and
derivatives in ``qhat`` (``ElementEnergy.taylor``, ``_powered``), and ``clamp_q``'s smooth
saturation of the MLP's input beyond the training range (``_clamped``)."""

from __future__ import annotations

import math

import torch
from torch import nn

#: static features per element (``meshodenet.energy.core.static_features``)
N_STATIC = 4

#: the energy's dependence on the normalised invariant at small strain: quadratic in an edge's
#: stretch, linear in a hinge's squared curvature or squared change of dihedral angle
#: (quadratic in the curvature and the angle)
POWER = {"edge": 2, "hinge": 1, "dihedral": 1}


def zero_output_mlp(inputs: int, hidden: int, layers: int) -> nn.Sequential:
    """``layers`` hidden layers of ``hidden`` (SiLU) from ``inputs`` to one output, the last
    layer zero (the output starts at 0, so ``softplus(out) / ln 2`` starts at 1)."""
    dims = [inputs] + [hidden] * layers
    mods = []
    for a, b in zip(dims[:-1], dims[1:]):
        mods += [nn.Linear(a, b), nn.SiLU()]
    last = nn.Linear(dims[-1], 1)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(*mods, last)


class ElementEnergy(nn.Module):
    """``U = Y/Ybar exp(a) 1/2 qhat^p g(qhat, s, yhat)`` of one element type
    (``p = POWER[kind]``)."""

    def __init__(self, kind: str, hidden: int, layers: int):
        super().__init__()
        self.power = POWER[kind]
        self.mlp = zero_output_mlp(2 + N_STATIC, hidden, layers)
        self.log_stiffness = nn.Parameter(torch.zeros(()))

    def forward(self, qhat, static, yhat, yrel, qrange=None):
        """``qrange``: ``(lo, hi)`` the MLP's input ``qhat`` is clamped to (``clamp_q``)."""
        inp = torch.cat([_clamped(qhat, qrange)[0][..., None], static, yhat[..., None]], -1)
        g = nn.functional.softplus(self.mlp(inp)[..., 0]) / math.log(2.0)
        return yrel * torch.exp(self.log_stiffness) * 0.5 * qhat**self.power * g

    def taylor(self, qhat, static, yhat, yrel, qrange=None):
        """``(U, dU/dqhat, d2U/dqhat2)``, propagated through the MLP in forward mode by hand
        (no autograd graph of its own: differentiable in the parameters, and about three times
        cheaper than double backward); ``qrange`` as ``forward``."""
        qin, s1, s2 = _clamped(qhat, qrange)
        z = torch.cat([qin[..., None], static, yhat[..., None]], -1)
        dz = d2z = None
        for layer in self.mlp:
            if isinstance(layer, nn.Linear):
                w = layer.weight
                if dz is None:  # the input layer; d2z None: the identity's s'' = 0
                    if qrange is None:
                        dz = w[:, 0].expand(*z.shape[:-1], -1)
                    else:
                        dz, d2z = w[:, 0] * s1[..., None], w[:, 0] * s2[..., None]
                else:
                    dz, d2z = dz @ w.T, None if d2z is None else d2z @ w.T
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
        return _powered(self.power, yrel * torch.exp(self.log_stiffness), qhat, g, g1, g2)


#: ``clamp_q``'s saturation width beyond the training range, in units of ``sigma``
SATURATION = 0.25


def _clamped(qhat, qrange):
    """``(s, s', s'')``: the MLP's input ``s(qhat)``, ``qhat`` itself inside ``qrange = (lo,
    hi)`` and saturating beyond it, ``hi + w tanh((qhat - hi) / w)`` (``w = SATURATION``; twice
    differentiable, so the energy's Hessian is continuous), and its derivatives; ``None``:
    ``(qhat, None, None)`` (the identity: no derivative factors to apply)."""
    if qrange is None:
        return qhat, None, None
    w, lo, hi = SATURATION, qrange[0], qrange[1]
    d = torch.where(qhat > hi, qhat - hi, torch.where(qhat < lo, qhat - lo, 0 * qhat))
    t = torch.tanh(d / w)
    return qhat - d + w * t, 1 - t**2, -2 * t * (1 - t**2) / w


def _powered(power: int, c, q, g, g1=None, g2=None):
    """``(U, dU/dq, d2U/dq2)`` of ``U = c/2 q^p g(q)`` (``p = power``, 1 or 2) from ``g`` and
    its derivatives ``g1``, ``g2`` (a derivative is ``None`` where ``g``'s is)."""
    if power == 2:
        return (c * 0.5 * q**2 * g, None if g1 is None else c * (q * g + 0.5 * q**2 * g1),
                None if g2 is None else c * (g + 2 * q * g1 + 0.5 * q**2 * g2))
    return (c * 0.5 * q * g, None if g1 is None else c * 0.5 * (g + q * g1),
            None if g2 is None else c * (g1 + 0.5 * q * g2))
