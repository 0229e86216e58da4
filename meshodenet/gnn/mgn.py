"""MeshGraphNet (Pfaff et al. 2021), the paper's autoregressive baseline (its section 3): its
config, presets and model.

A one-step model on the graphs, features and normalisers of MeshODENet
(``meshodenet.mesh.graph``, ``meshodenet.gnn.features``): from the positions of two consecutive frames
it predicts the normalised acceleration of every node and steps

.. math::
    x_{k+1} = 2 x_k - x_{k-1} + a_k \\Delta t^2, \\qquad
    a_k = (x_{k+1} - 2 x_k + x_{k-1}) / \\Delta t^2 \\ (\\mathrm{m/s^2}),

with ``Delta t`` the saved-frame interval of the training data. MeshGraphNets writes the
update in position units (``Delta t = 1``); the acceleration normaliser absorbs the constant
``Delta t^2``, so the normalised target, the quantity the network predicts and is trained on,
is the same. The node features see the backward-difference velocity
``v_k = (x_k - x_{k-1}) / Delta t`` (the only velocity a rollout has) and the external load
``force - damping v_k``. A rollout starts from the initial state alone, with
``x_{-1} = x_0 - v_0 Delta t``; clamped nodes are held.

Network (MeshGraphNets' conventions): encode-process-decode, MLPs of ``mlp_hidden_layers``
hidden layers, LayerNorm after every MLP but the decoder, ``layers`` unshared ``GraphNetBlock``s
with residuals on nodes and edges and sum aggregation.

Training (``training_loss``): one sample is (trajectory, frame k), k = 0 .. T-2, the target the
acceleration from frame k to k+1; the loss is the squared error of the normalised
acceleration, summed over components and averaged over free nodes. Training noise: every
sample gets Gaussian noise ``n`` of std ``noise * step_rms`` on the current positions of its
free nodes (``step_rms``: RMS one-frame displacement of free nodes over the training split,
per component, over the components the data moves in), drawn from the trainer's generator;
the target position becomes ``x_{k+1} + (1 - noise_gamma) n``, so the model learns to undo
the noise: with ``noise_gamma = 1`` all of it in position, with 0 all of it in velocity
(MeshGraphNets: cloth 0.003 m and 0.1). Only directions in which the training data moves
get noise (a planar rod stays planar).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch
from torch import nn

from meshodenet.gnn import network
from meshodenet.gnn.features import (
    EDGE_DYNAMIC,
    EDGE_STATIC,
    FeatureStats,
    GraphContext,
    check_rest_position,
    check_youngs_feature,
    graph_context,
    n_node_features,
)
from meshodenet.gnn.layers import ACTIVATIONS, EncodeProcessDecode, InteractionLayer
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.mesh.graph import GraphTopology
from meshodenet.training.presets import (
    check_choice,
    check_engine,
    check_int,
    check_preset,
    paper_train_config,
)
from meshodenet.training.train import TrainConfig

DT_RTOL = 1e-3  # frames closer than this to uniform spacing count as uniform


@dataclass(frozen=True)
class MeshGraphNetConfig:
    """Architecture and training noise of MeshGraphNet.

    - ``hidden``, ``layers``, ``mlp_hidden_layers``, ``activation``: latent width, number of
      message-passing blocks, hidden layers per MLP, activation (MeshGraphNets: 128, 15, 2,
      ReLU; the paper's depth per mesh kind: ``PAPER_LAYERS``).
    - ``noise``: std of the training noise on positions, as a fraction of ``step_rms`` (the
      RMS one-frame displacement of free nodes in the training data); 0 turns it off
      (docs/MGN.md, "Noise study").
    - ``noise_gamma``: share of the noise the target corrects in position, the rest in
      velocity (MeshGraphNets' cloth: 0.1).
    - ``youngs_feature``, ``rest_position``: as ``MeshODENetConfig``.
    - ``acc_norm``: ``component`` normalises the target acceleration per component; ``vector``
      with one std for the vector (the root mean square of the moving components' stds), so
      that isotropic training noise weighs the same in every direction of the loss.
    - ``engine``, ``message_passing``: how the network is evaluated
      (``meshodenet.training.presets.ENGINES``, ``MESSAGE_PASSING``); not the model itself.
    """

    hidden: int = 128
    layers: int = 15
    mlp_hidden_layers: int = 2
    activation: str = "relu"
    noise: float = 0.0
    noise_gamma: float = 0.1
    youngs_feature: str = "linear"
    rest_position: bool = False
    acc_norm: str = "component"
    engine: str = "fast"
    message_passing: str = "pyg"

    def __post_init__(self):
        check_engine(self)
        if self.acc_norm not in ("component", "vector"):
            raise ValueError(f"MeshGraphNetConfig.acc_norm must be 'component' or 'vector', got "
                             f"{self.acc_norm!r}")
        check_rest_position("MeshGraphNetConfig", self.rest_position)
        check_youngs_feature("MeshGraphNetConfig", self.youngs_feature)
        for name, lo in (("hidden", 1), ("layers", 0), ("mlp_hidden_layers", 0)):
            check_int(self, name, lo)
        check_choice(self, "activation", ACTIVATIONS)
        for name, hi in (("noise", math.inf), ("noise_gamma", 1.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 <= v <= hi \
                    or math.isnan(v):
                raise ValueError(f"MeshGraphNetConfig.{name} must be a number in [0, {hi}], "
                                 f"got {v!r}")


class GraphNetBlock(InteractionLayer):
    r"""MeshGraphNets' message-passing block: the ``InteractionLayer``'s MLPs and residuals,
    but the nodes sum the edge MLP's output, not the residual-updated edge latent:

    .. math::
        m_{ij} = \phi_e([e_{ij}, h_i, h_j]), \quad
        h'_j = h_j + \phi_v\big([h_j, \textstyle\sum_{i \to j} m_{ij}]\big), \quad
        e'_{ij} = e_{ij} + m_{ij}.

    Shapes: as ``InteractionLayer``.
    """

    aggregate_updated_edges = False


class MeshGraphNetwork(EncodeProcessDecode):
    """``EncodeProcessDecode`` with ``GraphNetBlock``s and LayerNorm on every MLP but the
    decoder. Shapes: as ``EncodeProcessDecode``."""

    def __init__(self, d_node: int, d_edge: int, d_out: int, hidden: int, n_layers: int,
                 mlp_hidden_layers: int, activation: str, message_passing: str = "pyg"):
        super().__init__(d_node, d_edge, d_out, hidden, 0, mlp_hidden_layers, activation,
                         layer_norm=True)
        self.processor = nn.ModuleList(
            GraphNetBlock(hidden, mlp_hidden_layers, activation, True, message_passing)
            for _ in range(n_layers))


@dataclass(frozen=True)
class StepContext(GraphContext):
    """A ``GraphContext`` plus the frame interval ``dt`` (s) the model steps."""

    dt: float = 0.0


def frame_interval(t: torch.Tensor, what: str = "t") -> float:
    """The uniform spacing of the times ``t (T,)``; ``ValueError`` if they are not uniform."""
    if len(t) < 2:
        raise ValueError(f"{what} has {len(t)} frame(s); a one-step model needs at least 2")
    d = (t[1:] - t[:-1]).double()
    if not torch.allclose(d, d[0].expand_as(d), rtol=DT_RTOL, atol=0):
        raise ValueError(f"{what}: frames are not uniformly spaced (intervals "
                         f"{float(d.min()):.6g} to {float(d.max()):.6g} s); MeshGraphNet "
                         "steps a fixed interval")
    return float(d.mean())


def backward_difference_velocities(data: Trajectories, dt: float) -> Trajectories:
    """``data`` with ``vel[:, k] = (pos[:, k] - pos[:, k-1]) / dt`` for k >= 1 and the stored
    ``vel[:, 0]``: the velocities MeshGraphNet sees. Fed to ``FeatureStats.compute``, its
    acceleration statistics are exactly those of the one-step targets."""
    vel = data.vel.clone()
    vel[:, 1:] = (data.pos[:, 1:] - data.pos[:, :-1]) / dt
    return Trajectories(data.t, data.pos, vel, data.youngs)


class MeshGraphNet(TrajectoryModel):
    """MeshGraphNet behind the ``TrajectoryModel`` interface (see there for shapes).

    Buffers besides the normalisers (``stats``): ``dt`` the frame interval it was trained on
    (s; a rollout on another interval is refused), ``step_rms`` the noise unit (m),
    ``active`` (3,) the components in which the training data accelerates (1) or that stay
    exactly constant (0, e.g. z of a planar rod: decoded to the training mean, no loss, no
    noise). ``hinges`` overrides the rod hinges found from the mesh (tests relabel nodes).
    After a rollout, ``diverged`` maps each trajectory whose positions became non-finite to
    the first such step.
    """

    name = "mgn"

    def __init__(self, mesh: Mesh, config: MeshGraphNetConfig, train: Trajectories | None = None,
                 hinges=None):
        super().__init__(mesh, config)
        self.topology = GraphTopology(mesh, hinges)
        self.kind = mesh.kind
        self.stats = FeatureStats(self.kind, config.youngs_feature, config.rest_position)
        self.register_buffer("dt", torch.zeros((), dtype=torch.float64))
        self.register_buffer("step_rms", torch.zeros((), dtype=torch.float64))
        self.register_buffer("active", torch.ones(3, dtype=torch.float64))
        if train is not None:
            self._compute_stats(train)
        self.gnn = MeshGraphNetwork(n_node_features(self.kind, config.rest_position),
                                    EDGE_STATIC + EDGE_DYNAMIC, 3,
                                    config.hidden, config.layers, config.mlp_hidden_layers,
                                    config.activation, config.message_passing)
        self.diverged: dict = {}
        self._fast_held = None

    @property
    def engine(self) -> str:
        """The config's ``engine``: ``fast`` (``meshodenet.gnn.network.FastGNN``: split weights, static
        features folded) or ``reference`` (the modules' own forward)."""
        return self.config.engine

    @torch.no_grad()
    def _compute_stats(self, train: Trajectories) -> None:
        dt = frame_interval(train.t, "training data t")
        self.dt.fill_(dt)
        self.stats.compute(self.topology, backward_difference_velocities(train, dt))
        self.active.copy_((self.stats.acc.std > 0).double())
        if self.config.acc_norm == "vector":
            std = self.stats.acc.std
            moving = std > 0
            std[moving] = std[moving].pow(2).mean().sqrt()
        free = torch.as_tensor(self.mesh.node_type == 0, device=train.pos.device)
        # one trajectory at a time into one float64 tensor (the mean over it as before):
        # not the float32 differences, their copy on the free nodes and two float64 copies
        # of the whole split at once
        B, T = train.pos.shape[:2]
        step = torch.empty(B, T - 1, int(free.sum()), 3, dtype=torch.float64,
                           device=train.pos.device)
        for b in range(B):
            step[b] = (train.pos[b, 1:] - train.pos[b, :-1])[:, free]
        sq = step.pow_(2).reshape(-1, 3).mean(0)[self.active > 0]
        self.step_rms.fill_(float(sq.mean().sqrt()) if sq.numel() and step.numel() else 0.0)

    # --- one step -----------------------------------------------------------------------------
    def context(self, youngs: torch.Tensor, dtype=None) -> StepContext:
        """The ``StepContext`` for trajectories of moduli ``youngs (B,)``."""
        return graph_context(self.stats, self.topology, youngs, dtype, StepContext,
                             dt=float(self.dt))

    def forward(self, x: torch.Tensor, x_prev: torch.Tensor, ctx: StepContext,
                gnn: network.FastGNN | None = None) -> torch.Tensor:
        """Normalised acceleration ``(M, 3)`` from positions ``x, x_prev (M, 3)`` of frames
        ``k`` and ``k - 1``. ``gnn``: a ``network.FastGNN`` of ``ctx`` to reuse (a training loss
        that steps several times within one backward pass builds it once)."""
        b = ctx.batch
        v = (x - x_prev) / ctx.dt * b.free
        if self.engine == "reference":
            node_in, edge_in = ctx.inputs(x, v)
            return self.gnn(node_in, edge_in, b.senders, b.receivers)
        if gnn is None:
            gnn = self._fast_gnn(ctx)
        return gnn(x, v)

    def _fast_gnn(self, ctx: StepContext) -> network.FastGNN:
        """``network.FastGNN`` of ``ctx``: the one ``rollout`` built for its context (parameters
        do not change during a rollout), else a new one."""
        held = self._fast_held
        if held is not None and held[0] is ctx and not torch.is_grad_enabled():
            return held[1]
        return network.FastGNN(self.gnn, ctx, self.config.activation)

    def step(self, x: torch.Tensor, x_prev: torch.Tensor, ctx: StepContext,
             gnn: network.FastGNN | None = None) -> torch.Tensor:
        """Positions of frame ``k + 1``: ``2 x - x_prev + a dt^2``, clamped nodes held."""
        a = self(x, x_prev, ctx, gnn) * ctx.acc_std + ctx.acc_mean
        x_next = 2 * x - x_prev + a * ctx.dt ** 2
        return torch.where(ctx.batch.free.bool(), x_next, x)

    # --- TrajectoryModel ------------------------------------------------------------------------
    def _check_dt(self, t: torch.Tensor, what: str) -> float:
        dt = frame_interval(t, what)
        if not math.isclose(dt, float(self.dt), rel_tol=DT_RTOL):
            raise ValueError(f"{what}: frame interval {dt:.6g} s, but this MeshGraphNet was "
                             f"trained to step {float(self.dt):.6g} s; roll out on the "
                             "training data's time grid")
        return dt

    def rollout(self, x0, v0, youngs, t):
        """Autoregressive rollout from ``x0, v0`` over every frame of ``t``; ``vel`` is the
        backward difference. A trajectory whose positions become non-finite at step ``k`` is
        NaN from frame ``k`` on (graphs of a batch are disjoint, so the others go on), is
        recorded in ``diverged`` and raises a ``RuntimeWarning`` naming the step; the loop
        stops once every trajectory has diverged."""
        ctx = self.context(youngs, x0.dtype)
        try:
            if self.engine == "fast" and not torch.is_grad_enabled():
                self._fast_held = (ctx, network.FastGNN(self.gnn, ctx, self.config.activation))
            return self._rollout(x0, v0, t, ctx)
        finally:
            self._fast_held = None

    def _rollout(self, x0, v0, t, ctx):
        B, N, _ = x0.shape
        pos = x0.new_full((B, len(t), N, 3), math.nan)
        vel = torch.full_like(pos, math.nan)
        free = ctx.batch.free
        x = x0.reshape(-1, 3)
        pos[:, 0], vel[:, 0] = x0, (v0.reshape(-1, 3) * free).reshape(B, N, 3)
        self.diverged = {}
        if len(t) < 2:
            return pos, vel
        dt = self._check_dt(t, "rollout t")
        x_prev = x - v0.reshape(-1, 3) * free * dt
        alive = torch.ones(B, dtype=torch.bool, device=x0.device)
        for k in range(1, len(t)):
            x, x_prev = self.step(x, x_prev, ctx), x
            p = x.reshape(B, N, 3)
            ok = torch.isfinite(p).all(dim=-1).all(dim=-1) & alive
            if not torch.equal(ok, alive):
                self._report(alive & ~ok, k, t)
            alive = ok
            pos[alive, k] = p[alive]
            vel[alive, k] = ((x - x_prev) / dt).reshape(B, N, 3)[alive]
            if not alive.any():
                break
        return pos, vel

    def _report(self, new: torch.Tensor, k: int, t) -> None:
        idx = new.nonzero().flatten().tolist()
        for b in idx:
            self.diverged[b] = k
        warnings.warn(f"MeshGraphNet rollout diverged at step {k} (t = {float(t[k]):.6g} s) of "
                      f"{len(t) - 1}: positions of trajectories {idx} of the batch are not "
                      "finite; their frames from this step on are NaN", RuntimeWarning,
                      stacklevel=4)

    @torch.no_grad()
    def one_step(self, data: Trajectories, batch_size: int = 256) -> torch.Tensor:
        """Teacher-forced predictions ``(B, T, N, 3)``: frame ``k + 1`` stepped from the true
        frames ``k`` and ``k - 1`` (``x_{-1}`` from the initial velocity), ``batch_size``
        frames at a time; frame 0 is the truth. ``position_rmse`` of it against ``data.pos``
        is the one-step RMSE."""
        self._check_dt(data.t, "data t")
        out = data.pos.clone()
        n = data.n_frames - 1
        samples = torch.arange(len(data) * n)
        for s in range(0, len(samples), batch_size):
            idx = samples[s:s + batch_size]
            traj, x_prev, x, _ = self._frames(data, idx)
            ctx = self.context(data.youngs[traj], x.dtype)
            x_next = self.step(x.reshape(-1, 3), x_prev.reshape(-1, 3), ctx)
            k = idx.to(traj.device) % n + 1
            out[traj, k] = x_next.reshape(x.shape)
        return out

    def n_training_samples(self, data: Trajectories) -> int:
        return len(data) * (data.n_frames - 1)

    def _frames(self, data: Trajectories, samples: torch.Tensor, nodes=None):
        """Trajectory index and positions ``x_{k-1}, x_k, x_{k+1}`` ``(S, N, 3)`` of samples;
        with ``nodes`` (global ids ``(n,)``) at those nodes only ``(S, n, 3)``, indexed out of
        the frames without taking a whole frame."""
        samples = samples.to(data.pos.device)
        traj, k = samples // (data.n_frames - 1), samples % (data.n_frames - 1)
        if nodes is None:
            at, node_type = slice(None), self.mesh.node_type
        else:
            at, node_type = torch.as_tensor(nodes, device=data.pos.device), \
                self.mesh.node_type[nodes]

        def frame(a, j):
            return a[traj, j] if nodes is None else a[traj[:, None], j[:, None], at]

        x, x_next = frame(data.pos, k), frame(data.pos, k + 1)
        free = torch.as_tensor(node_type == 0, device=x.device)[:, None].to(x.dtype)
        first = x - frame(data.vel, torch.zeros_like(k)) * free * float(self.dt)  # x_{-1}
        x_prev = torch.where((k == 0)[:, None, None], first, frame(data.pos, (k - 1).clamp(min=0)))
        return traj, x_prev, x, x_next

    def _add_noise(self, x, x_next, mask, generator):
        """``x + n, x_next + (1 - noise_gamma) n``: the training noise (module doc) on the
        positions ``x (S, N, 3)`` where ``mask`` (broadcast to ``x``) is 1."""
        c = self.config
        if c.noise <= 0:
            return x, x_next
        g = torch.randn(x.shape, generator=generator, dtype=x.dtype).to(x.device)
        n = g * (c.noise * float(self.step_rms)) * mask
        return x + n, x_next + (1 - c.noise_gamma) * n

    def training_loss(self, data, samples, generator=None):
        """Squared error of the normalised acceleration (free nodes, active components),
        summed over components and averaged over free nodes of the samples (module doc)."""
        self._check_dt(data.t, "training data t")
        traj, x_prev, x, x_next = self._frames(data, samples)
        ctx = self.context(data.youngs[traj], x.dtype)
        err = self.node_errors(x_prev, x, x_next, ctx, generator)
        return (err * ctx.batch.free).sum() / ctx.batch.free.sum().clamp_min(1)

    def node_errors(self, x_prev, x, x_next, ctx: StepContext, generator=None) -> torch.Tensor:
        """Per node the squared error ``(S n, 1)`` of the normalised acceleration, summed over
        the active components, of the frames ``x_prev, x, x_next (S, n, 3)`` on the graph of
        ``ctx`` (the whole mesh, or a patch of it), training noise added on its free nodes."""
        free = ctx.batch.free.reshape(len(x), -1, 1)
        active = self.active.to(x.dtype)
        x, x_next = self._add_noise(x, x_next, free * active, generator)
        target = (x_next - 2 * x + x_prev).reshape(-1, 3) / ctx.dt ** 2
        std = torch.where(active > 0, ctx.acc_std, torch.ones_like(ctx.acc_std))
        target = (target - ctx.acc_mean) / std
        pred = self(x.reshape(-1, 3), x_prev.reshape(-1, 3), ctx)
        return ((pred - target) ** 2 * active).sum(-1, keepdim=True)


# --- presets ------------------------------------------------------------------------------------
#: message-passing blocks of ``paper`` per mesh kind (the paper: 15 for the rod, 30 for the plate)
PAPER_LAYERS = {"line": 15, "triangle": 30}
#: ``quick`` per mesh kind: ``(TrainConfig fields, MeshGraphNetConfig fields)`` over the paper's
#: optimiser; measured and why: docs/MGN.md, "Presets".
QUICK_MGN = {
    "line": (dict(epochs=20, lr=1e-3, lr_milestones=(14,), batch_size=32, max_batches=120),
             dict(hidden=64, layers=15, acc_norm="vector", noise=0.03, youngs_feature="log",
                  rest_position=True)),
    "triangle": (dict(epochs=6, lr=1e-3, lr_milestones=(5,), batch_size=32, max_batches=48,
                      weight_decay=0.0, val_every=3),
                 dict(hidden=32, layers=30, rest_position=True)),
}


def mgn_presets(preset: str, kind: str) -> tuple[TrainConfig, MeshGraphNetConfig]:
    """``(TrainConfig, MeshGraphNetConfig)`` of ``preset`` for a mesh of ``kind``: ``paper``
    latent 128, MLPs of 2 hidden layers, ``PAPER_LAYERS`` blocks, the paper's optimiser and
    schedule, one training frame per optimizer step; ``quick`` with ``QUICK_MGN``; ``smoke``
    a tiny model, 2 epochs of 3 steps, for tests."""
    check_preset(preset)
    if kind not in PAPER_LAYERS:
        raise ValueError(f"no MeshGraphNet preset for mesh kind {kind!r}; valid: "
                         f"{', '.join(PAPER_LAYERS)}")
    base = paper_train_config(kind)
    if preset == "paper":
        return base, MeshGraphNetConfig(layers=PAPER_LAYERS[kind])
    if preset == "quick":
        t, m = QUICK_MGN[kind]
        return replace(base, **t), MeshGraphNetConfig(**m)
    return (replace(base, epochs=2, lr=1e-3, lr_milestones=(), batch_size=8, max_batches=3,
                    val_split="random"),  # as preset_configs: a smoke run checks plumbing
            MeshGraphNetConfig(hidden=16, layers=2, mlp_hidden_layers=1))
