"""Node and edge features of the paper (section 2.2.1) and their normalisers.

Node features, ``[static | dynamic]``:

- line meshes (rods):      ``[Y]``            ``| [v (3), cos a, sin a, F_ext (3)]``
- triangle meshes (plates): ``[Y, onehot(type) (2)]`` ``| [v (3), F_ext (3)]``

with ``Y`` the trajectory's Young's modulus (Pa), ``v`` the velocity, ``F_ext = force - damping v``
the external load and ``a`` the signed turning angle at a rod node: for the hinge
``p -> i -> q``, ``cos a = e1.e2 / (|e1||e2|)`` and ``sin a = (e1 x e2).z / (|e1||e2|)`` with
``e1 = x_i - x_p``, ``e2 = x_q - x_i`` (rods lie in the x-y plane, as in the paper). Nodes
without a hinge (rod ends) get ``a = 0``. The paper's angle "formed by the two edges" is
``pi - a``; after normalisation the two carry the same information.

Edge features of the directed edge ``i -> j``: ``[l0, d0 (3)] | [l, d (3)]``, rest and current
length and unit direction of ``x_j - x_i``.

``layout = "authors"`` (``LAYOUTS``; the A/B against their code, docs/AB.md) is the authors' code's: the
node encoder sees the velocity alone (``[] | [v (3)]``), the static node features go to the
decoder beside the latent instead (``EncodeProcessDecode``'s ``decoder_static``), and the edge
features hold the relative position itself, ``[l0, x0_j - x0_i] | [l, x_j - x_i]``;
``authors_nodes`` and ``authors_edges`` take one of the two parts (the A/B's bisection).

Normalisers hold per-feature mean and std computed from training trajectories only, as
buffers, so they travel with the model's ``state_dict``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from meshodenet.gnn.network import RodAngles
from meshodenet.mesh.data import N_NODE_TYPES, Trajectories
from meshodenet.mesh.graph import GraphBatch, GraphTopology

NODE_STATIC = {"line": 1, "triangle": 1 + N_NODE_TYPES}
NODE_DYNAMIC = {"line": 8, "triangle": 6}
EDGE_STATIC, EDGE_DYNAMIC = 4, 4
#: Feature layouts (module docstring): ours, or the authors' code's.
LAYOUTS = ("ours", "authors", "authors_nodes", "authors_edges")


def authors_nodes(layout: str) -> bool:
    """The node part of the authors' layout: velocity-only encoder, static at the decoder."""
    return layout in ("authors", "authors_nodes")


def authors_edges(layout: str) -> bool:
    """The edge part of the authors' layout: relative positions instead of directions."""
    return layout in ("authors", "authors_edges")


def check_layout(owner: str, value) -> None:
    if value not in LAYOUTS:
        raise ValueError(f"{owner}.layout must be one of {', '.join(LAYOUTS)}; got {value!r}")


def n_dynamic(kind: str, layout: str = "ours") -> int:
    """Dynamic node features: ``NODE_DYNAMIC[kind]``, or the velocity alone (``authors``)."""
    return 3 if authors_nodes(layout) else NODE_DYNAMIC[kind]


def n_static(kind: str, rest_position: bool = False) -> int:
    """Static node features: ``NODE_STATIC[kind]``, plus 3 with ``rest_position``."""
    return NODE_STATIC[kind] + 3 * bool(rest_position)


def n_node_features(kind: str, rest_position: bool = False, layout: str = "ours") -> int:
    return n_static(kind, rest_position) + n_dynamic(kind, layout)


def _length_direction(vec: torch.Tensor) -> torch.Tensor:
    """``[|vec|, vec / |vec|]`` per row: ``(D, 3) -> (D, 4)``."""
    length = vec.norm(dim=-1, keepdim=True)
    return torch.cat([length, vec / length.clamp_min(1e-30)], dim=-1)


def turning_angle(x: torch.Tensor, hinges: torch.Tensor) -> torch.Tensor:
    """``[cos a, sin a]`` per node ``(M, 2)`` from positions ``x (M, 3)``; ``(1, 0)`` off hinges
    (``meshodenet.gnn.network.RodAngles``)."""
    return RodAngles(hinges, x.shape[0], x.dtype, x.device).forward(x)


#: How the Young's modulus enters the node features: the paper's ``Y`` itself, or its logarithm
#: (a feature spread evenly over a modulus range of 15:1, where the soft rods, which deform
#: the most, sit in a sliver of the linear range); normalised like every feature.
YOUNGS_FEATURES = {"linear": lambda y: y, "log": torch.log}


def check_youngs_feature(owner: str, value) -> None:
    if value not in YOUNGS_FEATURES:
        raise ValueError(f"{owner}.youngs_feature must be one of "
                         f"{', '.join(YOUNGS_FEATURES)}; got {value!r}")


#: How the decoder's output is de-normalised into an acceleration: ``acceleration`` with the
#: mean and std of the training accelerations (finite differences of the stored velocities over
#: free nodes); ``velocity`` as the authors' code does (docs/AB.md, "What differs"): zero mean and the
#: velocity's std per component in their ODE's time unit of 0.1 per frame, i.e.
#: ``std(v) / (10 dt)`` with ``dt`` the mean sampling interval (on the plate 3.4x / 5.3x the
#: acceleration's std in y / x: the network's output moves the acceleration that much more).
ACC_SCALES = ("acceleration", "velocity")


def check_acc_scale(owner: str, value) -> None:
    if value not in ACC_SCALES:
        raise ValueError(f"{owner}.acc_scale must be one of {', '.join(ACC_SCALES)}; "
                         f"got {value!r}")


#: How the normalisers' statistics are taken (docs/AB.md, "What differs" and "The out-of-plane
#: channel"): ``ours`` (``Normalizer.set_stats``: a constant input is scaled by its mean, a
#: nearly constant vector component is floored at ``VECTOR_FLOOR`` times its vector's largest
#: std, a constant output has std 0, so a planar case stays exactly planar), or ``authors`` as
#: the authors' code: the unbiased std of every feature clamped at ``AUTHORS_STD_MIN`` in their
#: units (metres; velocities per their ODE's time unit of 0.1 per frame; the modulus in MPa),
#: the node-type one-hot not normalised, and the output scale (``acc_scale="velocity"``, which
#: it needs) the velocity's clamped std, not 0. On the in-plane plate that leaves the
#: out-of-plane direction alive: a decoded z output moves the nodes by at most ~1e-7 m, which
#: the loss cannot see, but reaches the encoders as a normalised z velocity and z edge vector of
#: order 1 to 30 over a rollout, a hidden state the network can use.
NORMALIZERS = ("ours", "authors")
AUTHORS_STD_MIN = 1e-8
AUTHORS_FRAME_TIME = 0.1  # their ODE's time per frame
AUTHORS_YOUNGS_UNIT = 1e6  # their modulus feature is Y / 1e6


def check_normalizer(owner: str, value, acc_scale: str) -> None:
    """``value`` one of ``NORMALIZERS``; ``authors`` only with the authors' output scale."""
    if value not in NORMALIZERS:
        raise ValueError(f"{owner}.normalizer must be one of {', '.join(NORMALIZERS)}; "
                         f"got {value!r}")
    if value == "authors" and acc_scale != "velocity":
        raise ValueError(f"{owner}.normalizer='authors' needs acc_scale='velocity' (the "
                         f"authors' output scale), got {acc_scale!r}")


def check_rest_position(owner: str, value) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{owner}.rest_position must be a bool, got {value!r}")


def static_node_features(batch: GraphBatch, youngs: torch.Tensor, kind: str,
                         youngs_feature: str = "linear", rest_position: bool = False
                         ) -> torch.Tensor:
    """``(M, n_static(kind, rest_position))`` from ``youngs (n_graphs,)`` (Pa): the modulus
    (``youngs_feature``), node types (triangle meshes), and with ``rest_position`` the node's
    rest (material) coordinates, which tell a node where on the body it sits (which a
    message-passing network of few layers cannot see beyond its neighbourhood)."""
    y = YOUNGS_FEATURES[youngs_feature](youngs).repeat_interleave(batch.n_per_graph)[:, None]
    out = [y]
    if kind != "line":
        out.append(nn.functional.one_hot(batch.node_type, N_NODE_TYPES).to(y.dtype))
    if rest_position:
        out.append(batch.rest_pos.to(y.dtype))
    return torch.cat(out, dim=-1) if len(out) > 1 else y


def dynamic_node_features(x: torch.Tensor, v: torch.Tensor, batch: GraphBatch,
                          kind: str, layout: str = "ours") -> torch.Tensor:
    """``(M, n_dynamic(kind, layout))`` from positions and velocities ``(M, 3)``."""
    if authors_nodes(layout):
        return v
    f_ext = batch.force - batch.damping * v
    if kind == "line":
        return torch.cat([v, turning_angle(x, batch.hinges), f_ext], dim=-1)
    return torch.cat([v, f_ext], dim=-1)


def _length_vector(vec: torch.Tensor) -> torch.Tensor:
    """``[|vec|, vec]`` per row (the ``authors`` layout)."""
    return torch.cat([vec.norm(dim=-1, keepdim=True), vec], dim=-1)


def static_edge_features(batch: GraphBatch, layout: str = "ours") -> torch.Tensor:
    """``(D, 4)``: rest length and unit direction (``authors``: vector) of every directed
    edge."""
    return (_length_vector if authors_edges(layout) else _length_direction)(batch.rest_vec)


def dynamic_edge_features(x: torch.Tensor, batch: GraphBatch, layout: str = "ours"
                          ) -> torch.Tensor:
    """``(D, 4)``: current length and unit direction (``authors``: vector) of
    ``x_receiver - x_sender``."""
    vec = x[batch.receivers] - x[batch.senders]
    return (_length_vector if authors_edges(layout) else _length_direction)(vec)


class Normalizer(nn.Module):
    """``(x - mean) / std`` per feature, with statistics held as buffers.

    A feature constant over the training data (std below ``1e-8 (1 + |mean|)``, e.g. the z
    components of a planar rod) is not blown up by a tiny std: as an input it is scaled by
    ``|mean|`` (or 1 when the mean is round-off, below 1e-12); as an output
    (``output=True``) its std is 0, so ``inverse`` returns exactly the training mean and a
    planar case stays planar.

    ``vectors`` lists ``(start, stop)`` slices that are components of one vector (velocity,
    force, direction). A component whose std is below ``VECTOR_FLOOR`` times the largest of
    its vector's is floored there: a component that is nearly but not exactly constant (an
    out-of-plane velocity of std 5e-6 m/s against ~1 m/s, solver round-off, in the earlier
    plate that moved in x-z) would otherwise be amplified 10^5 times, so a rollout's tiny
    drift in it would drive the network far outside its training range. The in-plane
    ``plate_cantilever`` moves in x-y with z exactly 0: its z inputs are exactly 0 after
    normalisation whatever their floored std, and its decoded z acceleration is exactly 0.
    """

    VECTOR_FLOOR = 1e-3

    def __init__(self, size: int, output: bool = False, vectors: tuple = ()):
        super().__init__()
        self.output = output
        self.vectors = tuple(vectors)
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("std", torch.ones(size, dtype=torch.float64))

    def set_stats(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        mean, std = mean.double(), std.double().clone()
        const = std <= 1e-8 * (1 + mean.abs())
        for a, b in self.vectors:
            floor = self.VECTOR_FLOOR * std[a:b].max()
            keep = const[a:b] if self.output else torch.zeros_like(const[a:b])
            std[a:b] = torch.where(keep, std[a:b], torch.clamp(std[a:b], min=floor))
        const = std <= 1e-8 * (1 + mean.abs())
        if self.output:
            std = torch.where(const, torch.zeros_like(std), std)
        else:
            fallback = torch.where(mean.abs() > 1e-12, mean.abs(), torch.ones_like(mean))
            std = torch.where(const, fallback, std)
        self.mean.copy_(mean)
        self.std.copy_(std)

    def set_raw(self, mean: torch.Tensor, std: torch.Tensor) -> None:
        """Take ``mean`` and ``std`` as they are (no floor; ``normalizer="authors"``)."""
        self.mean.copy_(mean.double())
        self.std.copy_(std.double())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        return y * self.std.to(y.dtype) + self.mean.to(y.dtype)

    def part(self, start: int, stop: int):
        """``(mean, std)`` of features ``start:stop``, for normalising a slice."""
        return self.mean[start:stop], self.std[start:stop]


class _Moments:
    """Running sum and sum of squares per feature in float64."""

    def __init__(self):
        self.n, self.s, self.s2 = 0, 0.0, 0.0

    def add(self, a: torch.Tensor) -> None:
        a = a.detach().double().reshape(-1, a.shape[-1])
        self.n += a.shape[0]
        self.s = self.s + a.sum(0)
        self.s2 = self.s2 + (a * a).sum(0)

    def result(self, unbiased: bool = False):
        mean = self.s / max(self.n, 1)
        var = (self.s2 / max(self.n, 1) - mean * mean).clamp_min(0.0)
        if unbiased:
            var = var * self.n / max(self.n - 1, 1)
        return mean, var.sqrt()


class FeatureStats(nn.Module):
    """Normalisers of node features, edge features and accelerations (targets of the
    decoder, from finite differences of the stored velocities over free nodes, or with
    ``acc_scale="velocity"`` the authors' scale: ``ACC_SCALES``), taken as ``normalizer`` says
    (``NORMALIZERS``).

    Build it empty (``FeatureStats(kind)``) and either ``compute`` from training trajectories or
    load a ``state_dict``.
    """

    def __init__(self, kind: str, youngs_feature: str = "linear", rest_position: bool = False,
                 acc_scale: str = "acceleration", layout: str = "ours", normalizer: str = "ours"):
        super().__init__()
        check_youngs_feature("FeatureStats", youngs_feature)
        check_acc_scale("FeatureStats", acc_scale)
        check_layout("FeatureStats", layout)
        check_normalizer("FeatureStats", normalizer, acc_scale)
        self.normalizer = normalizer
        self.kind = kind
        self.acc_scale = acc_scale
        self.layout = layout
        self.youngs_feature = youngs_feature
        self.rest_position = bool(rest_position)
        s = n_static(kind, rest_position)
        if authors_nodes(layout):
            node_vectors = ((s, s + 3),)
        elif kind == "line":
            node_vectors = ((s, s + 3), (s + 5, s + 8))
        else:
            node_vectors = ((s, s + 3), (s + 3, s + 6))
        self.node = Normalizer(n_node_features(kind, rest_position, layout), vectors=node_vectors)
        self.edge = Normalizer(EDGE_STATIC + EDGE_DYNAMIC, vectors=((1, 4), (5, 8)))
        self.acc = Normalizer(3, output=True, vectors=((0, 3),))

    @torch.no_grad()
    def compute(self, topology: GraphTopology, train: Trajectories) -> FeatureStats:
        """Statistics over every frame of every trajectory in ``train`` (training split only)."""
        if len(train) == 0:
            raise ValueError("cannot compute normalisation statistics from 0 trajectories")
        node, edge, acc = _Moments(), _Moments(), _Moments()
        T = train.n_frames
        batch = topology.batch(T, train.pos.device, train.pos.dtype)
        free = batch.free.bool().reshape(T, -1)[0]
        dt = (train.t[1:] - train.t[:-1])[:, None, None]
        for b in range(len(train)):
            x, v = train.pos[b].reshape(-1, 3), train.vel[b].reshape(-1, 3)
            y = train.youngs[b].expand(T)
            node.add(torch.cat([static_node_features(batch, y, self.kind, self.youngs_feature,
                                                     self.rest_position),
                                dynamic_node_features(x, v, batch, self.kind, self.layout)], -1))
            edge.add(torch.cat([static_edge_features(batch, self.layout),
                                dynamic_edge_features(x, batch, self.layout)], -1))
            if self.acc_scale == "acceleration":  # (``velocity``: from the node moments)
                acc.add(((train.vel[b, 1:] - train.vel[b, :-1]) / dt)[:, free])
        frame_dt = float(dt.mean())
        if self.normalizer == "authors":
            self._authors_stats(node, edge, frame_dt)
            return self
        node_mean, node_std = node.result()
        if self.acc_scale == "velocity":  # ACC_SCALES: the raw std (0 for a planar case's z)
            s = n_static(self.kind, self.rest_position)
            acc_stats = (torch.zeros(3, dtype=torch.float64),
                         node_std[s:s + 3] / (10 * frame_dt))
        else:
            acc_stats = acc.result()
        self.node.set_stats(node_mean, node_std)
        self.edge.set_stats(*edge.result())
        self.acc.set_stats(*acc_stats)
        return self

    def _authors_stats(self, node: _Moments, edge: _Moments, frame_dt: float) -> None:
        """``normalizer="authors"`` (``NORMALIZERS``): unbiased std clamped at
        ``AUTHORS_STD_MIN`` in the authors' units, the one-hot as it is, and the output
        scale the velocity's clamped std per their time unit."""
        s = n_static(self.kind, self.rest_position)
        to_theirs = frame_dt / AUTHORS_FRAME_TIME  # m/s -> m per their time unit
        mean, std = node.result(unbiased=True)
        unit = torch.ones_like(std)
        unit[0] = AUTHORS_YOUNGS_UNIT if self.youngs_feature == "linear" else 1.0
        unit[s:s + 3] = 1 / to_theirs
        std = torch.maximum(std, AUTHORS_STD_MIN * unit)
        if self.kind != "line":  # the one-hot, not normalised
            mean[1:1 + N_NODE_TYPES], std[1:1 + N_NODE_TYPES] = 0.0, 1.0
        self.node.set_raw(mean, std)
        e_mean, e_std = edge.result(unbiased=True)
        self.edge.set_raw(e_mean, e_std.clamp_min(AUTHORS_STD_MIN))
        self.acc.set_raw(torch.zeros(3, dtype=torch.float64), std[s:s + 3] / (10 * frame_dt))


@dataclass(frozen=True)
class GraphContext:
    """Everything about a batch of trajectories that stays fixed while it is rolled out: the
    graph, the normalised static features, and the normalisers' dynamic slices, all in the
    working dtype. Built by ``FeatureStats.context``; shared by every model."""

    batch: GraphBatch
    kind: str
    node_static: torch.Tensor  # (M, s) normalised
    edge_static: torch.Tensor  # (D, 4) normalised
    node_mean: torch.Tensor
    node_std: torch.Tensor
    edge_mean: torch.Tensor
    edge_std: torch.Tensor
    acc_mean: torch.Tensor
    acc_std: torch.Tensor
    layout: str = "ours"

    def inputs(self, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised node and edge inputs of the GNN at positions ``x`` and velocities ``v``
        ``(M, 3)``: static features followed by the dynamic ones (the node inputs of the
        authors' layout: the dynamic ones only, ``decoder_static`` holds the static)."""
        b, lay = self.batch, self.layout
        node_dyn = (dynamic_node_features(x, v, b, self.kind, lay) - self.node_mean) / self.node_std
        node_in = node_dyn if authors_nodes(lay) else torch.cat([self.node_static, node_dyn], -1)
        edge_in = torch.cat([self.edge_static,
                             (dynamic_edge_features(x, b, lay) - self.edge_mean) / self.edge_std],
                            dim=-1)
        return node_in, edge_in

    @property
    def authors_nodes(self) -> bool:
        """The node half of the authors' layout (``meshodenet.gnn.features.authors_nodes``)."""
        return authors_nodes(self.layout)

    @property
    def authors_edges(self) -> bool:
        """The edge half of the authors' layout (``meshodenet.gnn.features.authors_edges``)."""
        return authors_edges(self.layout)

    @property
    def decoder_static(self) -> torch.Tensor | None:
        """The normalised static node features the decoder sees (``authors`` layout), or
        ``None``."""
        return self.node_static if authors_nodes(self.layout) else None


def graph_context(stats: FeatureStats, topology: GraphTopology, youngs: torch.Tensor,
                  dtype=None, cls=GraphContext, **extra) -> GraphContext:
    """``cls`` (a ``GraphContext``, or a subclass with the fields ``extra``) for trajectories
    of moduli ``youngs (B,)`` on ``topology``, normalised with ``stats``."""
    dtype = dtype or youngs.dtype
    batch = topology.batch(len(youngs), youngs.device, dtype)
    s = n_static(stats.kind, stats.rest_position)
    cast = lambda a: a.to(device=youngs.device, dtype=dtype)
    nm, ns = cast(stats.node.mean), cast(stats.node.std)
    em, es = cast(stats.edge.mean), cast(stats.edge.std)
    node_static = (static_node_features(batch, youngs.to(dtype), stats.kind,
                                        stats.youngs_feature, stats.rest_position)
                   - nm[:s]) / ns[:s]
    edge_static = (static_edge_features(batch, stats.layout) - em[:EDGE_STATIC]) \
        / es[:EDGE_STATIC]
    return cls(batch, stats.kind, node_static, edge_static, nm[s:], ns[s:], em[EDGE_STATIC:],
               es[EDGE_STATIC:], cast(stats.acc.mean), cast(stats.acc.std), stats.layout,
               **extra)
