"""Models written in PyTorch Geometric, trained and rolled out like MeshODENet and MeshGraphNet.

A user writes a ``torch.nn.Module`` ``net(batch) -> (M, 3)`` on a ``torch_geometric.data.Batch``
and registers it (``register_pyg_model``, e.g. from a ``meshbench --plugin`` file; example in
docs/examples/pyg_plugin.py). The engine wraps it in ``PyGStepModel``, a one-step model behind
the ``TrajectoryModel`` interface: same trainer, checkpoints, validation, rollouts and metrics
as every other model.

What the net is handed, per graph of the batch (one trajectory's state at one frame; the batch
is the disjoint union of ``B`` graphs, ``M = B N`` nodes, ``D = B 2E`` directed edges):

- ``pos (M, 3)`` positions (m), ``vel (M, 3)`` velocities (m/s, the backward difference of
  the positions over one frame interval, as the rollout also computes them),
  ``rest_pos (M, 3)`` rest positions (m);
- ``edge_index (2, D)`` both directions of every mesh edge (row 0 sender, row 1 receiver:
  PyG's ``source_to_target``), ``node_type (M,)`` long (0 free, 1 clamped),
  ``youngs (B,)`` Young's modulus (Pa) per graph, ``batch (M,)`` the graph of each node;
- normalised features ready for a GNN: ``x (M, 6)`` = [velocity / its training std per
  component, one-hot node type, standardised ln E] and ``edge_attr (D, 8)`` =
  [(x_recv - x_send) / L, |x_recv - x_send| / L, the same two at rest], with ``L`` the mean
  rest edge length.

The net predicts the normalised acceleration of every node; the model de-normalises it with
training statistics and steps ``x_{k+1} = 2 x_k - x_{k-1} + dt^2 a_k`` (clamped nodes stay
put). Training: one-step loss on the normalised acceleration ``(x_{k+1} - 2 x_k + x_{k-1}) /
dt^2`` of the free nodes, as MeshGraphNet's (optional training noise: ``noise`` times the
RMS of a one-frame displacement, added to ``x_k``, drawn from the trainer's generator).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import torch

from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.mesh.graph import GraphTopology

D_NODE = 6
D_EDGE = 8


@dataclass(frozen=True)
class PyGModelConfig:
    """``hidden`` width and ``layers`` message-passing layers (the net decides what they
    mean); ``noise``: training noise in units of the RMS one-frame displacement (0: none)."""

    hidden: int = 64
    layers: int = 2
    noise: float = 0.0

    def __post_init__(self):
        for name in ("hidden", "layers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"PyGModelConfig.{name} must be an int >= 1, got {v!r}")
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float)) \
                or not 0 <= self.noise < float("inf"):
            raise ValueError(f"PyGModelConfig.noise must be a number >= 0, got {self.noise!r}")


def _frame_dt(t: torch.Tensor) -> float:
    dt = t[1:] - t[:-1]
    if not torch.allclose(dt, dt[0].expand_as(dt), rtol=1e-3, atol=0):
        raise ValueError("a one-step PyG model needs uniformly spaced frames")
    return float(dt[0])


class PyGStepModel(TrajectoryModel):
    """A one-step model around ``make_net(d_node, d_edge, config)`` (module docstring).
    Subclasses (``register_pyg_model``) set ``name`` and ``make_net``."""

    name = "pyg"
    make_net: Callable = None

    def __init__(self, mesh: Mesh, config: PyGModelConfig, train: Trajectories | None = None):
        super().__init__(mesh, config)
        self.topology = GraphTopology(mesh)
        for k, v in (("acc_mean", torch.zeros(3)), ("acc_std", torch.ones(3)),
                     ("vel_std", torch.ones(3)), ("log_e", torch.tensor([0.0, 1.0])),
                     ("step_rms", torch.ones(())),
                     ("length", torch.ones(()))):
            self.register_buffer(k, v.double())
        rest = torch.as_tensor(mesh.rest_pos, dtype=torch.float64)
        e = torch.as_tensor(mesh.edges, dtype=torch.long)
        self.length.fill_(float((rest[e[:, 1]] - rest[e[:, 0]]).norm(dim=-1).mean()))
        if train is not None:
            self._compute_stats(train)
        self.net = type(self).make_net(D_NODE, D_EDGE, config)
        self._templates: dict = {}

    @torch.no_grad()
    def _compute_stats(self, train: Trajectories) -> None:
        dt = _frame_dt(train.t)
        x = train.pos.double()
        free = torch.as_tensor(self.mesh.node_type == 0)
        v = ((x[:, 1:] - x[:, :-1]) / dt)[:, :, free].reshape(-1, 3)
        a = ((x[:, 2:] - 2 * x[:, 1:-1] + x[:, :-2]) / dt ** 2)[:, :, free].reshape(-1, 3)
        std = lambda s: torch.where(s > 1e-12, s, torch.ones_like(s))
        self.acc_mean.copy_(a.mean(0))
        self.acc_std.copy_(std(a.std(0)))
        self.vel_std.copy_(std(v.std(0)))
        le = torch.log(train.youngs.double())
        self.log_e.copy_(torch.stack([le.mean(), le.std() if len(le) > 1 and le.std() > 0
                                      else torch.ones(()).double()]))
        self.step_rms.fill_(float((v * dt).pow(2).sum(-1).mean().sqrt()))

    # --- graphs -----------------------------------------------------------------------
    def _template(self, n_graphs: int, device, dtype):
        from torch_geometric.data import Batch, Data

        key = (n_graphs, str(device), dtype)
        if key not in self._templates:
            b = self.topology.batch(n_graphs, device, dtype)
            N = self.mesh.n_nodes
            single = Data(edge_index=torch.stack([b.senders[: len(b.senders) // n_graphs],
                                                  b.receivers[: len(b.receivers) // n_graphs]]),
                          num_nodes=N)
            tmpl = Batch.from_data_list([single] * n_graphs)
            rest = torch.as_tensor(self.mesh.rest_pos, dtype=dtype, device=device)
            tmpl.rest_pos = rest.repeat(n_graphs, 1)
            tmpl.node_type = b.node_type.long()
            snd, rcv = tmpl.edge_index
            d = tmpl.rest_pos[rcv] - tmpl.rest_pos[snd]
            L = float(self.length)
            rest_attr = torch.cat([d / L, d.norm(dim=-1, keepdim=True) / L], -1)
            onehot = torch.nn.functional.one_hot(tmpl.node_type, 2).to(dtype)
            self._templates[key] = (tmpl, rest_attr, onehot, b.free)
        return self._templates[key]

    def graph(self, x: torch.Tensor, v: torch.Tensor, youngs: torch.Tensor):
        """The ``torch_geometric.data.Batch`` the net sees for states ``x, v (B, N, 3)`` and
        moduli ``youngs (B,)`` (fields in the module docstring)."""
        B, N, _ = x.shape
        tmpl, rest_attr, onehot, _ = self._template(B, x.device, x.dtype)
        g = copy.copy(tmpl)
        g.pos, g.vel = x.reshape(-1, 3), v.reshape(-1, 3)
        g.youngs = youngs.to(x.dtype)
        snd, rcv = g.edge_index
        d = g.pos[rcv] - g.pos[snd]
        L = float(self.length)
        g.edge_attr = torch.cat([d / L, d.norm(dim=-1, keepdim=True) / L, rest_attr], -1)
        le = ((torch.log(youngs.double()) - self.log_e[0]) / self.log_e[1]).to(x.dtype)
        g.x = torch.cat([g.vel / self.vel_std.to(x.dtype), onehot,
                         le.repeat_interleave(N)[:, None]], -1)
        return g

    def acceleration(self, x, v, youngs) -> torch.Tensor:
        """De-normalised accelerations ``(B, N, 3)`` (zero at clamped nodes)."""
        g = self.graph(x, v, youngs)
        out = self.net(g)
        if out.shape != (g.num_nodes, 3):
            raise ValueError(f"{self.name}: the net returned shape {tuple(out.shape)}, expected "
                             f"({g.num_nodes}, 3): one acceleration per node")
        free = self._template(x.shape[0], x.device, x.dtype)[3]
        a = (out * self.acc_std.to(x.dtype) + self.acc_mean.to(x.dtype)) * free
        return a.reshape(x.shape)

    # --- TrajectoryModel ----------------------------------------------------------------
    def rollout(self, x0, v0, youngs, t):
        dt = _frame_dt(t)
        free = torch.as_tensor(self.mesh.node_type == 0, device=x0.device)[None, :, None]
        v0 = v0 * free
        pos, vel = [x0], [v0]
        x_prev, x = x0 - dt * v0, x0
        for _ in range(len(t) - 1):
            v = (x - x_prev) / dt
            x_next = torch.where(free, 2 * x - x_prev + dt ** 2 * self.acceleration(x, v, youngs),
                                 x0)
            x_prev, x = x, x_next
            pos.append(x)
            vel.append((x - x_prev) / dt)
        return torch.stack(pos, 1), torch.stack(vel, 1)

    def n_training_samples(self, data: Trajectories) -> int:
        return len(data) * (data.n_frames - 2)

    def training_loss(self, data, samples, generator=None):
        dt = _frame_dt(data.t)
        per = data.n_frames - 2
        samples = samples.to("cpu")
        traj, k = samples // per, samples % per + 1
        dev = data.pos.device
        traj, k = traj.to(dev), k.to(dev)
        x_prev, x, x_next = data.pos[traj, k - 1], data.pos[traj, k], data.pos[traj, k + 1]
        free = torch.as_tensor(self.mesh.node_type == 0, device=dev)[None, :, None].to(x.dtype)
        if self.config.noise > 0:
            n = torch.randn(x.shape, generator=generator, dtype=x.dtype).to(dev)
            x = x + n * (self.config.noise * float(self.step_rms)) * free
        target = (x_next - 2 * x + x_prev) / dt ** 2
        target = (target - self.acc_mean.to(x.dtype)) / self.acc_std.to(x.dtype)
        g = self.graph(x, (x - x_prev) / dt, data.youngs[traj])
        pred = self.net(g).reshape(x.shape)
        err = ((pred - target) ** 2).sum(-1, keepdim=True) * free
        return err.sum() / (free.sum() * len(traj)).clamp_min(1)


def pyg_presets(preset: str, kind: str):
    """``(TrainConfig, PyGModelConfig)``: ``smoke`` (2 epochs of 3 steps, hidden 16),
    ``quick`` (20 epochs of 120 steps of 32 frames, hidden 64, 4 layers, lr 1e-3 then 1e-4),
    ``paper`` (the paper's optimiser and schedule, hidden 128, 15 layers)."""
    from dataclasses import replace

    from meshodenet.training.presets import check_preset, paper_train_config

    check_preset(preset)
    base = paper_train_config(kind)
    if preset == "paper":
        return base, PyGModelConfig(hidden=128, layers=15)
    if preset == "quick":
        return (replace(base, epochs=20, lr=1e-3, lr_milestones=(14,), batch_size=32,
                        max_batches=120), PyGModelConfig(hidden=64, layers=4))
    return (replace(base, epochs=2, lr=1e-3, lr_milestones=(), batch_size=8, max_batches=3),
            PyGModelConfig(hidden=16, layers=2))


def register_pyg_model(name: str, make_net: Callable, presets: Callable = pyg_presets,
                       config_cls: type = PyGModelConfig, description: str = "",
                       overwrite: bool = False):
    """Register a PyG network as model ``name``: ``make_net(d_node, d_edge, config) ->
    nn.Module`` whose ``forward(batch)`` returns normalised accelerations ``(M, 3)``.
    ``config_cls``: a frozen dataclass with at least the fields of ``PyGModelConfig``."""
    from meshodenet.registry import ModelSpec, register_model

    if not callable(make_net):
        raise ValueError(f"register_pyg_model({name!r}): make_net must be callable")
    cls = type(f"PyGStepModel_{name}", (PyGStepModel,),
               {"name": name, "make_net": staticmethod(make_net), "__module__": __name__})
    return register_model(name, ModelSpec(cls, config_cls, presets, description
                                          or "a PyTorch Geometric network as a one-step model"),
                          overwrite=overwrite)


__all__ = ["D_EDGE", "D_NODE", "PyGModelConfig", "PyGStepModel", "pyg_presets",
           "register_pyg_model"]
