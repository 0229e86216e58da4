"""``meshbench bench --impl authors``: a stand-in for the authors' MeshODENet training code, to
measure our engine against the implementation the paper's numbers came from.

Written from the description of the authors' code in docs/SOURCES.md ("The authors' MeshODENet
code"), not taken from it: a ``torch_geometric`` ``MessagePassing`` processor of one layer (edge MLP on
``[h_i, h_j, e]`` with a residual, sum at the receivers, node MLP on ``[h, sum e]`` with a
residual), MLPs of two hidden layers of 128 with ReLU and no LayerNorm, a node encoder on the
normalised velocity, an edge encoder on the normalised current relative position and its norm
beside the rest relative position and its norm, a decoder on ``[h, Young's modulus, node-type
one-hot]`` giving the acceleration, clamped nodes held with ``torch.where``; integrated by
``torchdiffeq.odeint(method="rk4")`` with the step equal to the sampling interval, and trained by
direct backpropagation through the whole rollout, loss ``sqrt(mean(sum over nodes of the squared
error))``. Its forward FLOPs equal those of our reference architecture up to the encoders' first
layers (8 edge inputs instead of 4, 3 node inputs instead of 8 or 9), which the bench's FLOP count
neglects.

It exists for one comparison, the issue "A training engine near the hardware's limit" asks for
(our training rollout at least 3x theirs): the same graph, the same number of RK4 intervals and
evaluations, interleaved round by round with our implementations in one process. The weights are
random and the statistics placeholders: the cost of a fixed-step rollout does not depend on them.
Only its cost is measured; it is never trained, and its outputs are not compared with ours.
"""

from __future__ import annotations

import torch
from torch import nn

HIDDEN = 128


def _mlp(d_in: int, d_out: int, hidden: int = HIDDEN) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, d_out))


def _processor_class():
    # torch_geometric is imported only here: it pulls in torch._dynamo (seconds per process)
    from torch_geometric.nn.conv import MessagePassing
    from torch_geometric.utils import scatter

    class Processor(MessagePassing):
        def __init__(self, d: int):
            super().__init__()
            self.edge_mlp = _mlp(3 * d, d, d)
            self.node_mlp = _mlp(2 * d, d, d)

        def forward(self, h, edge_index, e):
            e = self.edge_mlp(torch.cat([h[edge_index[0]], h[edge_index[1]], e], 1)) + e
            agg = self.propagate(edge_index, edge_attr=e, size=None)
            return h + self.node_mlp(torch.cat([h, agg], 1)), e

        def message(self, edge_attr):
            return edge_attr

        def aggregate(self, inputs, index, dim_size=None):
            return scatter(inputs, index, dim=0, reduce="sum")

    return Processor


class AuthorsField(nn.Module):
    """``f(t, (x, v)) = (v, a)`` of the authors' architecture on one batched graph."""

    def __init__(self, edge_index, mesh_edge_attr, other, clamped, hidden: int = HIDDEN):
        super().__init__()
        self.node_encoder = _mlp(3, hidden, hidden)
        self.edge_encoder = _mlp(4 + mesh_edge_attr.shape[1], hidden, hidden)
        self.processor = nn.ModuleList([_processor_class()(hidden)])
        self.decoder = _mlp(hidden + other.shape[1], 3, hidden)
        self.edge_index, self.mesh_edge_attr, self.other = edge_index, mesh_edge_attr, other
        self.clamped = clamped
        self.stats = {"vel_mean": torch.zeros(3), "vel_std": torch.ones(3),
                      "edge_mean": torch.zeros(4), "edge_std": torch.ones(4)}

    def forward(self, t, state):
        x, v = state
        s = self.stats
        h = self.node_encoder((v - s["vel_mean"]) / s["vel_std"])
        ei = self.edge_index
        u = x[ei[0]] - x[ei[1]]
        ea = (torch.cat([u, torch.norm(u, p=2, dim=1, keepdim=True)], -1) - s["edge_mean"]) \
            / s["edge_std"]
        e = self.edge_encoder(torch.cat([ea, self.mesh_edge_attr], -1))
        for layer in self.processor:
            h, e = layer(h, ei, e)
        a = self.decoder(torch.cat([h, self.other], -1)) * s["vel_std"]
        return (torch.where(self.clamped, torch.zeros_like(v), v),
                torch.where(self.clamped, torch.zeros_like(a), a))


class AuthorsStyle:
    """The bench's ``Regime`` protocol for the authors' architecture: ``run(n)`` performs ``n``
    units of ``regime`` (``nograd``, ``fwdbwd`` or ``train``) on the first ``n_graphs``
    trajectories of ``data`` (``meshodenet.mesh.data.Trajectories``) over ``mesh``, batched as one
    graph, and returns the number of field evaluations they stand for."""

    def __init__(self, mesh, data, n_graphs: int, regime: str, train_intervals: int):
        from torchdiffeq import odeint

        self.odeint, self.regime = odeint, regime
        N = mesh.n_nodes
        edges = torch.as_tensor(mesh.edges, dtype=torch.long)
        one = torch.cat([edges.t(), edges.t().flip(0)], 1)
        ei = torch.cat([one + g * N for g in range(n_graphs)], 1)
        T = train_intervals + 1
        self.pos = data.pos[:n_graphs, :T].transpose(0, 1).reshape(T, n_graphs * N, 3)
        self.vel = data.vel[:n_graphs, :T].transpose(0, 1).reshape(T, n_graphs * N, 3)
        x_rest = torch.as_tensor(mesh.rest_pos, dtype=torch.float32).repeat(n_graphs, 1)
        u0 = x_rest[ei[0]] - x_rest[ei[1]]
        rest = torch.cat([u0, u0.norm(dim=1, keepdim=True)], 1)
        rest = (rest - rest.mean(0)) / (rest.std(0) + 1e-8)
        node_type = torch.as_tensor(mesh.node_type, dtype=torch.long).repeat(n_graphs)
        youngs = data.youngs[:n_graphs].repeat_interleave(N)[:, None]
        youngs = (youngs - youngs.mean()) / (youngs.std() if n_graphs > 1 else 1.0)
        other = torch.cat([youngs.float(), nn.functional.one_hot(node_type, 2).float()], 1)
        torch.manual_seed(0)
        self.f = AuthorsField(ei, rest, other, (node_type == 1)[:, None])
        self.t = data.t[:T].float()
        self.dt = float(data.t[1] - data.t[0])
        self.w = (torch.randn_like(x_rest), torch.randn_like(x_rest))
        self.evals = 4 * train_intervals if regime == "train" else 1

    def run(self, reps: int) -> int:
        f = self.f
        state = (self.pos[1], self.vel[1])
        for _ in range(reps):
            if self.regime == "nograd":
                with torch.no_grad():
                    f(None, state)
                continue
            f.zero_grad(set_to_none=True)
            if self.regime == "fwdbwd":
                x, v = (s.clone().requires_grad_(True) for s in state)
                dx, dv = f(None, (x, v))
                ((dx * self.w[0]).sum() + (dv * self.w[1]).sum()).backward()
                continue
            xs, _ = self.odeint(f, (self.pos[0], self.vel[0]), self.t, method="rk4",
                                options={"step_size": self.dt})
            torch.sqrt(torch.mean(torch.sum((self.pos - xs) ** 2, 1))).backward()
        return reps * self.evals
