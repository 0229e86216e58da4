"""MeshODENet (section 2.2 of the paper): a GNN vector field integrated over the whole rollout;
its config, presets and model.

State ``z = [x, v]`` of all nodes of a batch of trajectories, ``z (2, M, 3)``, and
``dz/dt = [v, GNN(G_t)]`` with the graph ``G_t`` rebuilt from ``x, v`` at every evaluation.
The GNN is encode-process-decode (``meshodenet.gnn.layers``) on the normalised features of
``meshodenet.gnn.features``; it outputs a normalised acceleration, de-normalised with training
statistics. Clamped nodes get zero velocity and acceleration.

Evaluations and fixed-step rollouts (and their gradients) run on the fast path
(``meshodenet.gnn.fast``, config ``engine = "fast"``); ``engine = "reference"`` runs the
module-by-module definition (``meshodenet.gnn.reference``). Same numbers up to float round-off
(docs/TRAINING.md). The implicit integrators (``meshodenet.integrators.implicit``) always run on the
reference field: their Jacobians need forward-mode AD, which the fast path's hand-written
backward does not provide.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from meshodenet.gnn import fast, reference
from meshodenet.gnn.features import (
    EDGE_DYNAMIC,
    EDGE_STATIC,
    FeatureStats,
    GraphContext,
    authors_nodes,
    check_acc_scale,
    check_layout,
    check_normalizer,
    check_rest_position,
    check_youngs_feature,
    graph_context,
    n_node_features,
    n_static,
)
from meshodenet.gnn.layers import ACTIVATIONS, EncodeProcessDecode
from meshodenet.gnn.network import FastField
from meshodenet.integrators.explicit import GRADIENT_MODES, INTEGRATORS
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.mesh.graph import GraphTopology
from meshodenet.training.presets import (
    check_choice,
    check_engine,
    check_fraction,
    check_int,
    check_nonnegative,
    preset_configs,
)
from meshodenet.training.train import TrainConfig


def release_count(fraction: float, n: int, generator=None) -> int:
    """How many of a batch's ``n`` windows start at the release: ``fraction * n`` rounded down
    or up at random (up with probability its fractional part, one draw from ``generator``
    only when it has one), so that the expected count is ``fraction * n``."""
    if not fraction:
        return 0
    x = round(fraction * n, 9)
    k = math.floor(x)
    if x > k:
        k += int(float(torch.rand((), generator=generator, dtype=torch.float64)) < x - k)
    return k


#: Training losses (``MeshODENetConfig.loss``).
LOSSES = ("mse", "rms")


@dataclass(frozen=True)
class MeshODENetConfig:
    """Architecture, integrator, gradient mode and training windows of MeshODENet.

    - ``hidden``, ``layers``, ``mlp_hidden_layers``, ``activation``: latent width,
      message-passing layers, hidden layers per MLP, activation (paper: 128, 1, 2, ReLU).
    - ``integrator``: a key of ``INTEGRATORS`` (the implicit ``backward_euler`` / ``sdirk2``
      run on the reference field and are differentiated implicitly, whatever ``grad_mode``);
      ``substeps``: steps per saved interval of the fixed-step ones; ``rtol``/``atol``:
      tolerances of ``dopri5`` only (``None``: 1e-4 / 1e-7; set for a fixed-step scheme, an
      error).
    - ``grad_mode``: ``direct``, ``checkpoint`` (segments of ``checkpoint_every`` intervals)
      or ``adjoint`` (``seminorm`` on or off).
    - ``shooting``: 0 trains on whole rollouts from the initial state (the paper); ``S > 0``
      on windows of ``S`` intervals, ``floor(n_intervals / S)`` per trajectory shifted
      together by a random offset, each started from the ground truth at its first frame.
      ``shooting_epochs = E > 0`` doubles the window every ``E`` epochs up to whole
      trajectories (``horizon``); 0 keeps ``S``.
    - ``youngs_feature``: ``linear`` (the modulus in Pa, the paper) or ``log``;
      ``rest_position``: the nodes' rest coordinates (m) as static features
      (``meshodenet.gnn.features``).
    - ``release_fraction`` in [0, 1]: share of a batch's windows started at frame 0 instead
      of their drawn start (``release_count``).
    - ``frame_weight`` ``p`` in [0, 1]: frame ``d`` of a window weighs ``s_d^-p``, ``s_d`` the
      no-motion loss at that frame; 0 weighs all frames the same (``training_loss``).
    - ``release_weight`` ``lambda >= 0``: adds ``lambda`` times the error of one step from
      frame 0, relative to standing still (``_release_loss``).
    - ``acc_scale``: how the decoder's output becomes an acceleration
      (``meshodenet.gnn.features.ACC_SCALES``: ``acceleration``, or ``velocity`` as the authors'
      code); ``loss``: ``mse`` (``training_loss``) or ``rms``, the mean over windows of the
      root of each window's mean square error relative to standing still (the authors' loss,
      up to a constant, is its value for one whole trajectory); ``layout``: the features'
      (``meshodenet.gnn.features.LAYOUTS``: ``ours``, or ``authors``, the authors' code's);
      ``normalizer``: how the statistics are taken (``meshodenet.gnn.features.NORMALIZERS``:
      ``ours``, or ``authors``, whose clamped std leaves a planar case's out-of-plane direction
      alive). The A/B against their code: docs/AB.md.
    - ``engine``, ``message_passing``: how the network is evaluated
      (``meshodenet.training.presets.ENGINES``, ``MESSAGE_PASSING``); not the model itself.

    Every field beyond the paper's defaults to its behaviour; experiments: docs/TRAINING.md.
    """

    hidden: int = 128
    layers: int = 1
    mlp_hidden_layers: int = 2
    activation: str = "relu"
    integrator: str = "rk4"
    substeps: int = 1
    rtol: float | None = None
    atol: float | None = None
    grad_mode: str = "checkpoint"
    checkpoint_every: int = 1
    seminorm: bool = True
    shooting: int = 0
    shooting_epochs: int = 0
    youngs_feature: str = "linear"
    rest_position: bool = False
    release_fraction: float = 0.0
    frame_weight: float = 0.0
    release_weight: float = 0.0
    acc_scale: str = "acceleration"
    loss: str = "mse"
    layout: str = "ours"
    normalizer: str = "ours"
    engine: str = "fast"
    message_passing: str = "pyg"

    def __post_init__(self):
        check_engine(self)
        check_fraction("MeshODENetConfig", "release_fraction", self.release_fraction)
        check_fraction("MeshODENetConfig", "frame_weight", self.frame_weight)
        check_nonnegative("MeshODENetConfig", "release_weight", self.release_weight)
        check_rest_position("MeshODENetConfig", self.rest_position)
        check_youngs_feature("MeshODENetConfig", self.youngs_feature)
        check_acc_scale("MeshODENetConfig", self.acc_scale)
        check_layout("MeshODENetConfig", self.layout)
        check_normalizer("MeshODENetConfig", self.normalizer, self.acc_scale)
        check_choice(self, "loss", LOSSES)
        if self.loss == "rms" and self.frame_weight:
            raise ValueError(f"MeshODENetConfig.frame_weight={self.frame_weight!r} has no "
                             "meaning with loss='rms'; leave it 0 or choose loss='mse'")
        for name, lo in (("hidden", 1), ("layers", 0), ("mlp_hidden_layers", 0),
                         ("substeps", 1), ("checkpoint_every", 1), ("shooting", 0),
                         ("shooting_epochs", 0)):
            check_int(self, name, lo)
        if authors_nodes(self.layout) and self.mlp_hidden_layers < 1:
            raise ValueError("MeshODENetConfig.mlp_hidden_layers must be >= 1 with "
                             "layout='authors' (the decoder's first and last layers apart), got "
                             f"{self.mlp_hidden_layers!r}")
        check_choice(self, "activation", ACTIVATIONS)
        check_choice(self, "integrator", INTEGRATORS)
        check_choice(self, "grad_mode", GRADIENT_MODES)
        adaptive = INTEGRATORS[self.integrator].adaptive
        for name in ("rtol", "atol"):
            v = getattr(self, name)
            if v is None:
                continue
            if not adaptive:
                raise ValueError(f"MeshODENetConfig.{name}={v!r} is only used by adaptive "
                                 f"integrators (dopri5), not by {self.integrator!r}; leave it "
                                 "None or choose integrator='dopri5'")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 \
                    or not math.isfinite(v):
                raise ValueError(f"MeshODENetConfig.{name} must be a positive number, got {v!r}")
        if adaptive and self.substeps != 1:
            raise ValueError(f"MeshODENetConfig.substeps={self.substeps} has no effect on the "
                             "adaptive integrator dopri5; leave it at 1")
        if not isinstance(self.seminorm, bool):
            raise ValueError(f"MeshODENetConfig.seminorm must be a bool, got {self.seminorm!r}")

    @property
    def tolerances(self) -> dict:
        return {"rtol": 1e-4 if self.rtol is None else self.rtol,
                "atol": 1e-7 if self.atol is None else self.atol}


# --- presets ---------------------------------------------------------------------------------
#: ``quick`` per mesh kind: ``(TrainConfig fields, MeshODENetConfig fields)`` over the paper's
#: optimiser. Rods: hidden 64, windows of 10 intervals doubling every epoch up to whole
#: rollouts, lr 1e-3 with gradient clipping, / 10 for the last epoch. Plates: hidden 48, whole
#: rollouts from rest, one trajectory per step, 5 epochs of 24 steps, lr 1e-3 with clipping
#: throughout (still falling fast at the end: a last epoch at 1e-4 validated worse), no weight
#: decay, rest coordinates, the first step after the release weighted apart
#: (``release_weight`` 0.05): a third of the cost of the 64-wide, 7 x 30-step
#: protocol it replaced (the run is compute-bound on the edge MLPs, so its cost goes with
#: hidden^2 x steps). Measured and why: docs/TRAINING.md, "Presets", and docs/HISTORY.md.
QUICK = {
    "line": (dict(epochs=10, lr=1e-3, lr_milestones=(9,), batch_size=8, grad_clip=1.0),
             dict(hidden=64, shooting=10, shooting_epochs=1)),
    "triangle": (dict(epochs=5, lr=1e-3, lr_milestones=(), batch_size=1, grad_clip=1.0,
                      max_batches=24, weight_decay=0.0),
                 dict(hidden=48, shooting=0, shooting_epochs=0, rest_position=True,
                      release_weight=0.05)),
}


#: ``paper`` per mesh kind: the ``MeshODENetConfig`` fields that differ from its defaults. On
#: triangle meshes the authors' code's conventions (their output scale, root loss, feature
#: layout and normaliser): with them our model is their code to float32 round-off (the same
#: gradients from the same weights: ``python -m benchmarks.ab equiv``) and follows or
#: beats their code's test loss on the plate, where ours drifted away from it (the A/B,
#: docs/AB.md, "What differs" and "The out-of-plane channel"; the normaliser since
#: 2026-12-07). Rods keep ours: their A/B followed the authors' code within 0.39-1.11x over 50
#: epochs with them, and the committed ``paper`` rod runs were trained with them.
PAPER = {"triangle": dict(acc_scale="velocity", loss="rms", layout="authors",
                          normalizer="authors")}


def meshodenet_presets(preset: str, kind: str) -> tuple[TrainConfig, MeshODENetConfig]:
    """``(TrainConfig, MeshODENetConfig)`` of ``preset`` for a mesh of ``kind``: ``paper`` the
    paper's model (hidden 128, 1 message-passing layer, MLPs of 2 hidden layers, rk4 with the
    step equal to the sampling interval, whole rollouts, ``checkpoint`` gradients) and
    optimiser, one trajectory per step, with ``PAPER``'s fields; ``quick`` with ``QUICK``;
    ``smoke`` a tiny model, 2 epochs of 3 steps, for tests."""
    return preset_configs(preset, kind, QUICK, MeshODENetConfig,
                          dict(hidden=16, mlp_hidden_layers=1, shooting=5), PAPER)


# --- the model ---------------------------------------------------------------------------------
#: The fixed part of a rollout (graph, normalised static features, normaliser slices).
FieldContext = GraphContext


class MeshODENet(TrajectoryModel):
    """The paper's model behind the ``TrajectoryModel`` interface (see there for shapes).

    ``hinges`` overrides the rod hinges found from the mesh (tests relabel nodes).
    ``nfe`` counts vector-field evaluations (forward solves, recomputations and adjoint solves).
    """

    name = "meshodenet"

    def __init__(self, mesh: Mesh, config: MeshODENetConfig, train: Trajectories | None = None,
                 hinges=None):
        super().__init__(mesh, config)
        self.topology = GraphTopology(mesh, hinges)
        self.kind = mesh.kind
        self.stats = FeatureStats(self.kind, config.youngs_feature, config.rest_position,
                                  config.acc_scale, config.layout, config.normalizer)
        self.epoch = 0
        self._loss_scales: dict = {}  # no-motion losses (_frame_scales, _release_loss)
        if train is not None:
            self.stats.compute(self.topology, train)
        # the authors' layout: the static node features go to the decoder
        n_dec = n_static(self.kind, config.rest_position) if authors_nodes(config.layout) else 0
        n_node = n_node_features(self.kind, config.rest_position, config.layout) - n_dec
        self.gnn = EncodeProcessDecode(
            n_node, EDGE_STATIC + EDGE_DYNAMIC, 3, config.hidden, config.layers,
            config.mlp_hidden_layers, config.activation, layer_norm=False,
            message_passing=config.message_passing, d_decoder_static=n_dec)
        self.nfe = 0

    @property
    def engine(self) -> str:
        """The config's ``engine``: ``fast`` (``meshodenet.gnn.fast``) or ``reference``
        (``meshodenet.gnn.reference``)."""
        return self.config.engine

    # --- the vector field -------------------------------------------------------------------
    def field_context(self, youngs: torch.Tensor, dtype=None) -> FieldContext:
        """Build (once per rollout) the context for trajectories of moduli ``youngs (B,)``."""
        return graph_context(self.stats, self.topology, youngs, dtype)

    def vector_field(self, z: torch.Tensor, ctx: FieldContext) -> torch.Tensor:
        """``dz/dt = [v, a]`` for ``z = [x, v]`` of shape ``(2, M, 3)``; clamped nodes frozen.
        (Builds the fast path's static parts on every call: to evaluate many times, use
        ``field_fn``.)"""
        if self.engine == "reference":
            return reference.vector_field(self, z, ctx)
        return fast.evaluate(FastField(self, ctx), z)

    def field_fn(self, ctx: FieldContext):
        """``z -> dz/dt`` on ``ctx`` with everything that does not depend on ``z`` built once;
        valid while the parameters do not change (rollouts and the solvers use it)."""
        if self.engine == "reference":
            return lambda z: reference.vector_field(self, z, ctx)
        field = FastField(self, ctx)
        return lambda z: fast.evaluate(field, z)

    def forward(self, z: torch.Tensor, ctx: FieldContext) -> torch.Tensor:
        """The vector field (``vector_field``), so that ``torch.func`` can call the model."""
        return self.vector_field(z, ctx)

    def integrate(self, z0: torch.Tensor, t: torch.Tensor, ctx: FieldContext) -> torch.Tensor:
        """``z`` at times ``t``: ``(T, 2, M, 3)``, with the configured integrator and gradient
        mode (the gradient mode only matters when autograd is recording)."""
        c = self.config
        if self.engine == "reference":
            return reference.integrate(self, z0, t, ctx)
        scheme = INTEGRATORS[c.integrator]
        if getattr(scheme, "implicit", False):  # forward-mode AD needs the module field
            return reference.integrate(self, z0, t, ctx)
        if scheme.adaptive or (c.grad_mode == "adjoint" and torch.is_grad_enabled()):
            f = self.field_fn(ctx)
            return reference.integrate(self, z0, t, ctx, field=lambda model, z, ctx_: f(z))
        return fast.rollout(FastField(self, ctx), scheme, z0, t, c.substeps)

    # --- TrajectoryModel ----------------------------------------------------------------------
    def rollout(self, x0, v0, youngs, t):
        B, N, _ = x0.shape
        ctx = self.field_context(youngs, x0.dtype)
        z0 = torch.stack([x0.reshape(-1, 3), v0.reshape(-1, 3) * ctx.batch.free])
        zs = self.integrate(z0, t.to(x0.dtype), ctx)  # (T, 2, B N, 3)
        out = zs.reshape(len(t), 2, B, N, 3).permute(1, 2, 0, 3, 4)
        return out[0], out[1]

    def start_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def horizon(self, n_intervals: int) -> int:
        """Intervals per training window in the current epoch."""
        c = self.config
        if c.shooting == 0:
            return n_intervals
        level = self.epoch // c.shooting_epochs if c.shooting_epochs else 0
        return min(n_intervals, c.shooting * 2 ** min(level, 62))

    def n_training_samples(self, data: Trajectories) -> int:
        """Windows per epoch: ``floor(n_intervals / S)`` per trajectory (1 for whole rollouts)."""
        n_int = data.n_frames - 1
        return len(data) * (n_int // self.horizon(n_int))

    def _loss_scale(self, train: Trajectories, S: int) -> float:
        """The mean of ``_frame_scales`` over the window's frames: the loss of the prediction
        "nothing moves" (1 where nothing moves)."""
        total = 0.0  # summed in order, not with sum(): Python 3.12's sum() rounds differently
        for s_d in self._frame_scales(train, S).tolist():
            total += s_d
        return total / S if total > 0 else 1.0

    @torch.no_grad()
    def _frame_scales(self, train: Trajectories, S: int) -> torch.Tensor:
        """``s_d (S,)`` float64, ``d = 1..S``: the mean of ``|x(t_s + d) - x(t_s)|^2`` over
        trajectories, every start ``s`` of a window of ``S`` intervals, and nodes: the loss of
        standing still at frame ``d`` of a window (cached per horizon; ``train`` is the
        training split the trainer passes)."""
        key = (S, train.pos.data_ptr(), tuple(train.pos.shape))
        if key not in self._loss_scales:
            n_start = train.n_frames - S
            self._loss_scales[key] = torch.tensor([
                float(((train.pos[:, d:d + n_start] - train.pos[:, :n_start]).double() ** 2)
                      .sum(-1).mean()) for d in range(1, S + 1)], dtype=torch.float64)
        return self._loss_scales[key]

    def windows(self, data, samples, generator=None):
        """``(traj (n,), start (n,), S)``: the trajectory and first frame of each window that
        ``samples (n,)`` names (``n_training_samples``), on ``data``'s device, and the windows'
        intervals ``S`` (``horizon``); the random offsets of multiple shooting and the windows
        moved to the release (``release_fraction``) drawn from ``generator``."""
        n_int = data.n_frames - 1
        S = self.horizon(n_int)
        n_w = n_int // S
        samples = samples.to("cpu")
        traj, start = samples // n_w, (samples % n_w) * S
        if S < n_int:
            dt = data.t[1:] - data.t[:-1]
            if not torch.allclose(dt, dt[0].expand_as(dt), rtol=1e-3, atol=0):
                raise ValueError("multiple shooting (shooting > 0) needs uniformly spaced "
                                 "frames; set shooting=0 for this data")
            start = start + torch.randint(0, n_int - n_w * S + 1, (len(samples),),
                                          generator=generator)
            k = release_count(self.config.release_fraction, len(samples), generator)
            if k:  # the batch's order is already random: its first k windows
                start[:k] = 0
        dev = data.pos.device
        return traj.to(dev), start.to(dev), S

    def frame_weights(self, data: Trajectories, S: int) -> torch.Tensor:
        """``W (S,)`` float64: the ``mse`` loss of windows of ``S`` intervals
        (``training_loss``) as the sum over windows, frames ``d`` and nodes of
        ``W_d |x_pred - x_true|^2``, over the number of windows times the number of nodes:
        ``W_d = 1 / (S scale)`` (``_loss_scale``), or with ``frame_weight = p``
        ``s_d^-p / (S mean(s_d^(1-p)))``. A sum over nodes splits over patches
        (``meshodenet.subdomain.PatchTraining``)."""
        p = self.config.frame_weight
        if not p:
            return torch.full((S,), 1.0 / (S * self._loss_scale(data, S)), dtype=torch.float64)
        s_d = self._frame_scales(data, S).clamp_min(1e-30)  # a frame that never moves
        w = s_d.pow(-p)
        return w / (S * float((s_d * w).mean()))

    def training_loss(self, data, samples, generator=None):
        """Mean over windows, predicted frames and nodes of ``|x_pred - x_true|^2``, divided by
        the same mean for the no-motion prediction on the training split (``_loss_scale``).
        With ``frame_weight = p > 0``: the mean over the window's frames ``d`` of their mean
        square error times ``s_d^-p`` (``_frame_scales``), divided by the mean of
        ``s_d^(1-p)``, its value for standing still.

        With ``loss="rms"``: the mean over windows of the root of each window's mean square
        error relative to standing still (``frame_weight`` 0).

        This is the paper's loss (its eq. for ``L(theta)``: squared position error summed over
        nodes, averaged over samples and frames) divided by a constant, so that standing still
        scores 1 whatever the case's units or the shooting horizon, and the size of the
        gradients relative to Adam's coupled weight decay does not depend on them either.
        """
        traj, start, S = self.windows(data, samples, generator)
        dev = data.pos.device
        frames = start[:, None] + torch.arange(S + 1, device=dev)
        t = data.t[: S + 1] - data.t[0]
        pred, _ = self.rollout(data.pos[traj, start], data.vel[traj, start],
                               data.youngs[traj], t)  # (n, S+1, N, 3)
        sq = ((pred[:, 1:] - data.pos[traj[:, None], frames[:, 1:]]) ** 2).sum(-1)
        p = self.config.frame_weight
        if getattr(self.config, "loss", "mse") == "rms":  # (ImexConfig has none)
            loss = (sq.mean(dim=(1, 2)) / self._loss_scale(data, S)).sqrt().mean()
        elif not p:
            loss = sq.mean() / self._loss_scale(data, S)
        else:
            s_d = self._frame_scales(data, S).clamp_min(1e-30)  # a frame that never moves
            w = s_d.pow(-p)
            loss = (sq.mean(dim=(0, 2)) * w.to(sq.device, sq.dtype)).mean() \
                / float((s_d * w).mean())
        lam = self.config.release_weight
        if lam:
            loss = loss + lam * self._release_loss(data, traj)
        return loss

    def _release_loss(self, data: Trajectories, traj: torch.Tensor) -> torch.Tensor:
        """Mean square position error of one step from frame 0 of trajectories ``traj``, over
        the batch and nodes, divided by that of standing still on the training split
        (``release_weight``; 1 for standing still)."""
        pred, _ = self.rollout(data.pos[traj, 0], data.vel[traj, 0], data.youngs[traj],
                               data.t[:2] - data.t[0])
        sq = ((pred[:, 1] - data.pos[traj, 1]) ** 2).sum(-1).mean()
        return sq / self.release_scale(data)

    @torch.no_grad()
    def release_scale(self, data: Trajectories) -> float:
        """The mean of ``|x_1 - x_0|^2`` over trajectories and nodes of the training split
        ``data``: the release loss of standing still (cached; at least 1e-30)."""
        key = ("release", data.pos.data_ptr(), tuple(data.pos.shape))
        if key not in self._loss_scales:
            self._loss_scales[key] = float(
                ((data.pos[:, 1] - data.pos[:, 0]).double() ** 2).sum(-1).mean())
        return max(self._loss_scales[key], 1e-30)
