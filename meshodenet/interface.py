"""The one model interface every learned simulator of meshbench implements.

Training (``meshodenet.training.train``), rollouts and metrics call only these methods, so MeshODENet,
MeshGraphNet and any user model are trained and compared on identical terms.
"""

from __future__ import annotations

import torch
from torch import nn

from meshodenet.mesh.data import DataError, Mesh, Trajectories


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

    ``on_mesh(mesh)`` rolls a trained model out on another mesh of the same kind (a finer mesh
    of the same case, another case): the model rebuilt on ``mesh`` with the same learned
    weights and statistics (``transfer``), or the model itself on its own mesh. A model whose
    state holds quantities of the mesh (per node, edge or element: computed from the mesh,
    not learned) names them in ``mesh_state_keys``; they are the new mesh's own there.
    ``rollout_settings`` names the attributes a rollout is configured with that the copy
    keeps (e.g. a solver).
    """

    name = "base"
    trainable = True
    rollout_settings: tuple = ()

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

    # --- other meshes -------------------------------------------------------------------------
    def on_mesh(self, mesh: Mesh, what: str = "data") -> TrajectoryModel:
        """This model on ``mesh``: itself where ``mesh`` holds the arrays of its own mesh (the
        same rollouts, bit for bit), else ``transfer(mesh)``. ``DataError`` (one line, naming
        ``what``) for a mesh the model cannot represent (``check_transfer``)."""
        if self.mesh.same_as(mesh):
            return self
        self.check_transfer(mesh, what)
        return self.transfer(mesh, what)

    def check_transfer(self, mesh: Mesh, what: str = "data") -> None:
        """Raise ``DataError`` unless the model can run on ``mesh``: a mesh of its training
        mesh's kind (``Mesh.kind``: the node and edge features, element types), not moving in
        more dimensions than it was trained in (``Mesh.dims``: a model trained in a plane never
        saw motion out of it). Subclasses add what they need of a mesh."""
        ours = self.mesh
        if mesh.kind != ours.kind:
            raise DataError(f"{what} is {mesh.describe()} but model {self.name!r} was trained "
                            f"on {ours.describe()}: it runs on {ours.kind} meshes only (its "
                            f"features and elements are those of {ours.kind} meshes), not on a "
                            f"{mesh.kind} mesh")
        if mesh.dims > ours.dims:
            raise DataError(f"{what} is {mesh.describe()}, which moves in {mesh.dims}-D (rest "
                            f"shape or loads out of the x-y plane), but model {self.name!r} was "
                            f"trained on {ours.describe()}, which stays in its plane: it never "
                            "learned motion out of the plane")

    def mesh_state_keys(self) -> set:
        """Keys of ``state_dict`` computed from the mesh (``on_mesh`` takes the new mesh's)."""
        return set()

    @torch.no_grad()
    def transfer(self, mesh: Mesh, what: str = "data") -> TrajectoryModel:
        """A copy of this model built on ``mesh`` (``type(self)(mesh, config)``) that shares
        its weights and statistics: every entry of ``state_dict`` but ``mesh_state_keys``,
        which must have the same shape (``DataError`` for one tied to the training mesh's
        size); entries for parts the new mesh lacks (an element type it has none of) stay
        unused. Same device, dtypes and ``rollout_settings``."""
        new = type(self)(mesh, self.config)
        own, state = new.mesh_state_keys(), self.state_dict()
        target = new.state_dict()
        for key, value in target.items():
            if key in own:
                continue
            if key not in state:
                raise DataError(f"{what} is {mesh.describe()}, which needs {key!r}, but model "
                                f"{self.name!r} trained on {self.mesh.describe()} has none")
            if state[key].shape != value.shape:
                raise DataError(f"{what} is {mesh.describe()} but model {self.name!r} holds "
                                f"{key!r} of shape {tuple(state[key].shape)}, tied to its "
                                f"training mesh ({self.mesh.describe()}); it runs on that "
                                "mesh only")
        device = next((t.device for t in state.values()), None)
        new.load_state_dict({k: target[k].to(device) if k in own else state[k] for k in target},
                            assign=True)
        for name in self.rollout_settings:
            setattr(new, name, getattr(self, name))
        return new.train(self.training)

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
