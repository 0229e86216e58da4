r"""MeshODENet-IMEX: MeshODENet's graph field with the case's linear drag integrated implicitly;
its config, presets and model.

Both cases of the paper are strongly damped. The falling rod's Stokes drag relaxes a node's
velocity at ``gamma = c / m = 2.6e6`` 1/s, so its velocity is slaved to its shape
(``v = F(x) / c``) within microseconds, while MeshODENet's explicit RK4 takes 0.1 s steps:
a learned acceleration field can follow that relaxation only if it is about 10^5 times softer
than the physics (RK4 is stable for ``gamma h < 2.8``), and then the model's velocity lags the
truth after every start from rest. The plate's mass-proportional damping (20.75 1/s) is mild
at its 3 ms step. This model keeps MeshODENet's GNN, features and trajectory loss, and writes
the acceleration as a relaxation, at the case's known linear drag rate, towards a learned
velocity:

.. math::
    \dot x = v, \qquad \dot v = \gamma \, (w_\theta(x, v) - v), \qquad \gamma = c / m
    \ \text{per node (the case's damping and lumped mass, > 0 at every free node)},

stepped with one evaluation per saved interval by the implicit-explicit (semi-implicit) Euler
scheme, the drag implicit, the learned part explicit, the position with the new velocity:

.. math::
    v_{k+1} = \frac{v_k + h \gamma w_\theta(x_k, v_k)}{1 + h \gamma}, \qquad
    x_{k+1} = x_k + h v_{k+1}.

Any ``gamma h`` is stable; for ``gamma h >> 1`` the step becomes ``v_{k+1} = w_theta``, a
first-order (Stokes) model of the velocity, for ``gamma h << 1`` symplectic Euler with the
acceleration ``gamma (w - v)``. ``w`` is a velocity at every node whatever its drag (the
rod's middle sphere has 2 500 times the drag rate of its other nodes, so a learned force
would span orders of magnitude across one rod); the decoder's output is normalised by the
statistics of its training target ``v_{k+1} + (v_{k+1} - v_k) / (h gamma)`` (stored frames,
free nodes, training split only). One evaluation per interval instead of RK4's four: a
training step costs a quarter of the evaluations. Training (loss, multiple-shooting
curriculum, validation) is MeshODENet's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch.utils.checkpoint import checkpoint

from meshodenet.gnn.features import _Moments
from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig, meshodenet_presets
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.training.presets import (
    check_engine,
    check_fraction,
    check_int,
    check_nonnegative,
    check_preset,
)

#: the fields ``ImexConfig`` shares with ``MeshODENetConfig`` (same meaning)
SHARED_FIELDS = ("hidden", "layers", "mlp_hidden_layers", "activation", "shooting",
                 "shooting_epochs", "youngs_feature", "rest_position", "release_fraction",
                 "frame_weight", "release_weight", "engine", "message_passing")


@dataclass(frozen=True)
class ImexConfig:
    """Architecture and training horizon of MeshODENet-IMEX (meanings as ``MeshODENetConfig``):
    ``hidden``, ``layers``, ``mlp_hidden_layers``, ``activation``, ``shooting``,
    ``shooting_epochs``, ``youngs_feature``, ``rest_position``, ``release_fraction``,
    ``frame_weight``, ``release_weight``, ``engine``, ``message_passing`` (``SHARED_FIELDS``);
    ``checkpoint_every`` steps per recomputed segment in the backward pass (0: keep the whole
    graph; the same gradient either way)."""

    hidden: int = 128
    layers: int = 1
    mlp_hidden_layers: int = 2
    activation: str = "relu"
    shooting: int = 0
    shooting_epochs: int = 0
    checkpoint_every: int = 0
    youngs_feature: str = "linear"
    rest_position: bool = False
    release_fraction: float = 0.0
    frame_weight: float = 0.0
    release_weight: float = 0.0
    engine: str = "fast"
    message_passing: str = "pyg"

    def __post_init__(self):
        check_engine(self)
        for name in ("release_fraction", "frame_weight"):
            check_fraction("ImexConfig", name, getattr(self, name))
        check_nonnegative("ImexConfig", "release_weight", self.release_weight)
        # MeshODENetConfig checks the shared fields (names, types, ranges)
        self.base()
        check_int(self, "checkpoint_every", 0)

    def base(self) -> MeshODENetConfig:
        return MeshODENetConfig(**{n: getattr(self, n) for n in SHARED_FIELDS})


class MeshODENetIMEX(MeshODENet):
    """See the module docstring. Shapes as ``TrajectoryModel``."""

    name = "meshodenet_imex"
    #: the ``integrator`` / ``grad_mode`` columns of results CSVs (segment checkpoints, when
    #: set, give the same gradient as direct backpropagation)
    integrator_id = "imex_euler"
    grad_mode_id = "direct"

    def __init__(self, mesh: Mesh, config: ImexConfig, train: Trajectories | None = None,
                 hinges=None):
        super().__init__(mesh, config.base(), train, hinges)
        self.config = config
        gamma = torch.as_tensor(mesh.damping / mesh.mass, dtype=torch.float64)
        bad = ~torch.isfinite(gamma) | ((gamma <= 0) & torch.as_tensor(mesh.node_type == 0))
        if bad.any():
            i = int(bad.nonzero()[0])
            raise ValueError(f"MeshODENet-IMEX needs damping / mass finite and > 0 at every free "
                             f"node; node {i} has {float(gamma[i])!r}")
        self.register_buffer("gamma", gamma)
        if train is not None:
            self._output_stats(train)

    @torch.no_grad()
    def _output_stats(self, train: Trajectories) -> None:
        """Normalise the decoder's output by its target ``v_{k+1} + (v_{k+1} - v_k) / (h gamma)``."""
        free = torch.as_tensor(self.mesh.node_type == 0, device=train.vel.device)
        h = (train.t[1:] - train.t[:-1])[:, None, None]
        # the model is still on the CPU here; the training data may be on a GPU
        g = self.gamma.to(train.vel.device, train.vel.dtype)[None, :, None]
        mom = _Moments()
        for b in range(len(train)):
            v = train.vel[b][:, free]
            mom.add(v[1:] + (v[1:] - v[:-1]) / (h * g[:, free]))
        self.stats.acc.set_stats(*mom.result())

    def mesh_state_keys(self) -> set:
        """``gamma``: the case's drag rate per node, the new mesh's own on another mesh."""
        return {"gamma"}

    def _gamma(self, B: int, dtype) -> torch.Tensor:
        return self.gamma.to(dtype).repeat(B)[:, None]

    def _steps(self, x, v, h, g, ctx, field):
        """Steps of sizes ``h (S,)`` from ``(x, v)``: positions and velocities ``(S, M, 3)``."""
        xs, vs = [], []
        for hk in h:
            w = field(torch.stack([x, v]))[1]
            hg = hk * g
            v = (v + hg * w) / (1 + hg)
            x = x + hk * v
            xs.append(x)
            vs.append(v)
        return torch.stack(xs), torch.stack(vs)

    def rollout(self, x0, v0, youngs, t):
        B, N, _ = x0.shape
        t = t.to(x0.dtype)
        ctx = self.field_context(youngs, x0.dtype)
        x, v = x0.reshape(-1, 3), v0.reshape(-1, 3) * ctx.batch.free
        g = self._gamma(B, x0.dtype)
        h = t[1:] - t[:-1]
        field = self.field_fn(ctx)  # differentiable on both engines
        seg = self.config.checkpoint_every if torch.is_grad_enabled() else 0
        seg = seg or max(len(h), 1)
        xs, vs = [x], [v]
        for s in range(0, len(h), seg):
            if seg < len(h):
                xk, vk = checkpoint(self._steps, x, v, h[s:s + seg], g, ctx, field,
                                    use_reentrant=False)
            else:
                xk, vk = self._steps(x, v, h[s:s + seg], g, ctx, field)
            x, v = xk[-1], vk[-1]
            xs.append(xk)
            vs.append(vk)
        pos, vel = torch.cat([xs[0][None], *xs[1:]]), torch.cat([vs[0][None], *vs[1:]])
        shape = (len(t), B, N, 3)
        return pos.reshape(shape).transpose(0, 1), vel.reshape(shape).transpose(0, 1)

    def integrate(self, z0, t, ctx):  # pragma: no cover - not used by this model
        raise NotImplementedError("MeshODENet-IMEX steps its own scheme; use rollout")


#: ``quick`` changes from MeshODENet's ``quick`` (validation experiments in docs/TRAINING.md):
#: the logarithm of the modulus as feature; rods: twice the epochs (a quarter of the field
#: evaluations per optimizer step), the learning rate divided by 10 for the last 8, frames
#: weighted by the inverse square root of their no-motion error (``frame_weight``) and the
#: first step after the release weighted apart (``release_weight``); plates: windows of 16
#: intervals throughout (MeshODENet's plate protocol before it moved to whole rollouts:
#: hidden 32, 10 epochs of 24 steps of 4 at lr 1e-3: each seed validated best at epoch 5-7 of
#: the 24 it had, and diverged from epoch 9-10), 5 % of them started at the release
#: (``release_fraction``); both: the nodes' rest coordinates as features (``rest_position``).
QUICK_CHANGES = {
    "line": (dict(epochs=20, lr_milestones=(12,)),
             dict(youngs_feature="log", frame_weight=0.5, release_weight=0.05,
                  rest_position=True)),
    "triangle": (dict(epochs=10, lr_milestones=(), batch_size=4, max_batches=24),
                 dict(hidden=32, shooting=16, shooting_epochs=0, frame_weight=0.0, release_weight=0.0,
                      youngs_feature="log", release_fraction=0.05, rest_position=True)),
}


def imex_presets(preset: str, kind: str) -> tuple:
    """``(TrainConfig, ImexConfig)``: MeshODENet's preset of the same name (the same GNN,
    optimiser and curriculum); ``quick`` with ``QUICK_CHANGES``."""
    check_preset(preset)
    tc, mc = meshodenet_presets(preset, kind)
    cfg = ImexConfig(**{n: getattr(mc, n) for n in SHARED_FIELDS})
    if preset == "quick" and kind in QUICK_CHANGES:
        t, m = QUICK_CHANGES[kind]
        tc, cfg = replace(tc, **t), replace(cfg, **m)
    return tc, cfg


__all__ = ["ImexConfig", "MeshODENetIMEX", "imex_presets"]
