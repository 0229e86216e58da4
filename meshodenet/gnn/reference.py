"""The reference implementation of MeshODENet's vector field and rollouts: the module-by-module
code (``GraphContext.inputs``, ``EncodeProcessDecode``, ``meshodenet.integrators.explicit.odesolve``)
that the fast path (``meshodenet.gnn.fast``) replaces. Kept as the definition the fast path is
tested against (``tests/test_fast.py``) and measured against (``meshbench bench engine --impl
reference,fast``); select it with a model config's ``engine = "reference"``.
"""

from __future__ import annotations

import torch
from torch import nn

from meshodenet.integrators.explicit import odesolve


def vector_field(model, z: torch.Tensor, ctx) -> torch.Tensor:
    """``dz/dt = [v, a]`` for ``z = [x, v]`` of shape ``(2, M, 3)``; clamped nodes frozen."""
    b = ctx.batch
    x, v = z[0], z[1] * b.free
    node_in, edge_in = ctx.inputs(x, v)
    a = model.gnn(node_in, edge_in, b.senders, b.receivers, ctx.decoder_static)
    a = (a * ctx.acc_std + ctx.acc_mean) * b.free
    return torch.stack([v, a])


class BoundField(nn.Module):
    """``f(t, z)`` for the solvers: ``field(z)`` of the model on one context. An ``nn.Module``
    whose parameters are the model's, as the adjoint needs."""

    def __init__(self, model, ctx, field=vector_field):
        super().__init__()
        self.model = model
        self.ctx = ctx
        self.field = field

    def forward(self, t, z):
        self.model.nfe += 1
        return self.field(self.model, z, self.ctx)

    def coupling(self):
        """The ``MeshCoupling`` of the model's field on this batch (implicit integrators): a
        node depends on nodes within ``layers + 1`` hops (``layers`` message-passing rounds
        on features of the node's edges and rod hinges)."""
        from meshodenet.integrators.implicit import MeshCoupling

        topo, b = self.model.topology, self.ctx.batch
        return MeshCoupling(topo.senders, topo.receivers, b.n_per_graph,
                            self.model.config.layers + 1, b.n_graphs)


def integrate(model, z0: torch.Tensor, t: torch.Tensor, ctx, field=vector_field) -> torch.Tensor:
    """``z`` at times ``t`` ``(T, 2, M, 3)`` with the model's integrator and gradient mode."""
    c = model.config
    return odesolve(BoundField(model, ctx, field), z0, t, c.integrator, c.grad_mode, c.substeps,
                    checkpoint_every=c.checkpoint_every, seminorm=c.seminorm,
                    params=tuple(model.parameters()), **c.tolerances)
