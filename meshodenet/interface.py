"""The one model interface every learned simulator of meshbench implements.

Training (``meshodenet.training.train``), rollouts and metrics call only these methods, so MeshODENet,
MeshGraphNet and any user model are trained and compared on identical terms.
"""

from __future__ import annotations

import torch
from torch import nn

from meshodenet.mesh.data import Mesh, Trajectories


class TrajectoryModel(nn.Module):
    """A model that rolls out a whole trajectory of one mesh from an initial state.

    Subclasses set ``name`` (their id in ``MODELS``) and are constructed as
    ``Model(mesh, config, train=None)``: ``mesh`` is the case's ``Mesh``, ``config`` the model's
    frozen config dataclass, ``train`` the training ``Trajectories`` from which the model takes
    its normalisation statistics (``None`` when it is about to load a ``state_dict``; all
    statistics must be buffers). They implement:

    ``rollout(x0, v0, youngs, t) -> (pos, vel)``
        ``x0, v0 (B, N, 3)`` initial positions (m) and velocities (m/s), ``youngs (B,)`` Pa,
        ``t (T,)`` s with ``t[0]`` the initial time; returns predicted ``pos, vel (B, T, N, 3)``
        with ``pos[:, 0] == x0``. Uses nothing of the ground truth beyond the initial state.

    ``n_training_samples(data) -> int``
        How many training samples one epoch over ``data`` (``Trajectories``) holds: whole
        trajectories or segments for MeshODENet, (trajectory, frame) pairs for one-step models.

    ``training_loss(data, samples, generator) -> Tensor``
        Scalar loss of the samples ``samples (S,)`` (long, in ``[0, n_training_samples)``);
        ``generator`` (``torch.Generator``, owned by the trainer and checkpointed) is the only
        source of randomness allowed (e.g. training noise), so that resuming is exact.

    ``start_epoch(epoch)`` (optional)
        Called by the trainer before every epoch (0-based, also after resuming), for models
        whose training changes with the epoch (a curriculum); the default does nothing.

    ``trainable`` (class attribute, default True) is False for a model with nothing to learn
    (a reference solver): ``fit`` refuses it, and the suite's runner records it without
    training (an empty checkpoint, zero epochs).

    Clamped nodes (``mesh.node_type == 1``) must not move in a rollout.
    """

    name = "base"
    trainable = True

    def __init__(self, mesh: Mesh, config):
        super().__init__()
        self.mesh = mesh
        self.config = config

    def rollout(self, x0, v0, youngs, t):
        raise NotImplementedError

    def start_epoch(self, epoch: int) -> None:
        pass

    def n_training_samples(self, data: Trajectories) -> int:
        raise NotImplementedError

    def training_loss(self, data: Trajectories, samples: torch.Tensor,
                      generator: torch.Generator) -> torch.Tensor:
        raise NotImplementedError

    # ------------------------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def check_mesh(self, mesh: Mesh, what: str = "data") -> None:
        """Raise ``DataError`` unless ``mesh`` is the mesh this model was built for."""
        self.mesh.check_same(mesh, what)

    @torch.no_grad()
    def rollout_all(self, data: Trajectories, batch_size: int = 16):
        """Roll out every trajectory of ``data`` from its first frame, ``batch_size`` at a time:
        ``(pos, vel)`` each ``(B, T, N, 3)`` on the model's device."""
        if data.pos.shape[2] != self.mesh.n_nodes:
            raise ValueError(f"data has {data.pos.shape[2]} nodes per frame, the model's mesh "
                             f"{self.mesh.n_nodes}")
        pos, vel = [], []
        for s in range(0, len(data), batch_size):
            sl = slice(s, s + batch_size)
            p, v = self.rollout(data.pos[sl, 0], data.vel[sl, 0], data.youngs[sl], data.t)
            pos.append(p)
            vel.append(v)
        return torch.cat(pos), torch.cat(vel)
