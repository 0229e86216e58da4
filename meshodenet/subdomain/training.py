"""A learner trained on patches of its mesh (``PatchTraining``): every optimizer step sees
patches of a fixed node budget plus their halo, the loss on their inner nodes only, so that a
step's memory depends on the budget, not on the mesh.

One training sample is (the learner's sample, patch): ``n_training_samples`` is the learner's
times the number of patches ``k = ceil(N / patch_nodes)`` (METIS parts of at most about
``patch_nodes`` nodes, ``partition_nodes``). A batch's loss is the learner's loss summed over
the inner nodes of its samples' patches, divided by the number of samples times the mean
number of inner nodes of a patch the learner's loss is a mean over (the free nodes, for
MeshODENet every node, over ``k``: ``node_terms``): a batch that holds every patch of the
same frames gives the whole mesh's loss where the patches are exact, and any batch the mean
of its samples'.

- MeshGraphNet: one step, exact. Its patches are ``graph_patches`` with the halo
  ``halo_depth(model)``; the squared error of the normalised acceleration at the inner nodes
  is the whole mesh's there (the halo rule, ``meshodenet.subdomain``). Training noise is drawn
  per patch: a node gets one draw as an inner node and others where it is in a halo, which
  changes the noise's samples, not its distribution.
- Implicit-Energy (``shooting = 0``): its one-step loss solves the Newton system of every free
  coordinate at once, ``d = A^{-1} r`` (global). On a patch the unknowns are the part's nodes
  and ``rings - 1`` rings around them, and the nodes beyond (the halo) are held at the ground
  truth's next frame: a driven boundary, a Dirichlet condition taken from the data, so the
  solve is ``A_UU^{-1} r_U`` and the loss is at the inner nodes. This is biased against the
  whole mesh's loss (measured in docs/SUBDOMAIN.md); ``loss = "residual"`` is the unbiased
  alternative, the residual ``|r|^2`` at the inner nodes scaled by ``h^2 / m`` into metres
  (exact on ``rings = 1`` patches, no solve), a different loss from the learner's own.
- MeshODENet: its loss integrates the field over a window of ``S`` steps, which reads
  ``layers x stages x S`` hops. On a patch the part's nodes and ``buffer`` rings around them
  are solved and the ``halo_depth`` hops beyond are driven: at every Runge-Kutta stage their
  states are the ground truth's, cubic-Hermite interpolated between the stored frames
  (``meshodenet.subdomain.driven``). Exact for one patch and for a buffer as deep as the
  window's stencil, biased otherwise (measured in docs/SUBDOMAIN.md). Fixed-step explicit
  integrators and the ``mse`` loss only (with ``frame_weight`` and the release term, sums
  over nodes); its mean is over every node, so the divisor counts every node, not the free.

Everything else is the whole mesh's, looked up: the normalisation statistics (the model's,
taken from the whole training split when it was built, never from a patch), node types,
masses, loads, element features (``meshodenet.subdomain.evaluate``). The parameters are the
learner's: ``state_dict`` is the learner's, so ``fit`` writes the learner's checkpoints, which
roll out on the whole mesh unchanged, and validation rolls the learner out on the whole mesh.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch

from meshodenet.energy.model import ImplicitEnergy
from meshodenet.gnn.features import graph_context
from meshodenet.gnn.meshodenet import MeshODENet
from meshodenet.gnn.mgn import MeshGraphNet, StepContext
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Mesh
from meshodenet.subdomain.driven import check_driven, driven_windows
from meshodenet.subdomain.evaluate import energy_elements, halo_depth, patch_topology
from meshodenet.subdomain.partition import Patch, driven_patches, graph_patches, partition_nodes

#: The learners ``PatchTraining`` trains, and why the others cannot be (yet).
PATCH_LEARNERS = (MeshGraphNet, ImplicitEnergy, MeshODENet)
NOT_ON_PATCHES = {
    "meshodenet_imex": "its window is stepped by its own implicit-explicit scheme, not by the "
                       "Runge-Kutta solver that drives MeshODENet's halo (the same driven "
                       "halo would apply: docs/SUBDOMAIN.md, 'MeshODENet')",
    "mgn_unrolled": "its loss rolls out several steps of its own: the halo of the later "
                    "steps is its prediction, not a one-step stencil",
    "implicit_energy_dissipation": "its learned dissipation holds per-node features that a "
                                   "patch view does not restrict yet",
}
#: Implicit-Energy's patch losses.
ENERGY_LOSSES = ("solve", "residual")
#: What ``patch_nodes`` counts: a part's inner nodes (its halo on top: ``k = ceil(N /
#: patch_nodes)``) or the whole patch, halo included (``k`` raised until every patch fits).
PATCH_BUDGETS = ("inner", "total")
#: METIS cuts tried for a ``total`` budget before one fits or it gives up (then a bisection).
MAX_CUTS = 12


def patch_count(n_nodes: int, patch_nodes) -> int:
    """``k = ceil(n_nodes / patch_nodes)``; ``ValueError`` naming ``patch_nodes`` unless it is
    an integer in ``[1, n_nodes]``."""
    if isinstance(patch_nodes, bool) or not isinstance(patch_nodes, (int, np.integer)) \
            or not 1 <= patch_nodes <= n_nodes:
        raise ValueError(f"patch_nodes must be an integer in [1, {n_nodes}] (the mesh's "
                         f"nodes), got {patch_nodes!r}; 0 in TrainConfig trains on the whole "
                         "mesh")
    return math.ceil(n_nodes / int(patch_nodes))


def _check_learner(learner) -> None:
    if type(learner) in PATCH_LEARNERS:
        if isinstance(learner, ImplicitEnergy) and learner.config.shooting:
            raise ValueError("patch training of implicit_energy needs shooting = 0 (the "
                             "one-step loss): a window of exact steps solves Newton on the "
                             "whole mesh at every step")
        if isinstance(learner, MeshODENet):
            check_driven(learner.config)
        return
    why = NOT_ON_PATCHES.get(getattr(learner, "name", ""), "it is not one of them")
    raise TypeError(f"patch training is defined for "
                    f"{', '.join(c.name for c in PATCH_LEARNERS)}; not for "
                    f"{getattr(learner, 'name', type(learner).__name__)!r}: {why}")


def training_patches(learner, patch_nodes: int, halo: int | None = None,
                     budget: str = "inner", buffer: int = 0) -> list[Patch]:
    """The patches ``PatchTraining`` cuts ``learner``'s mesh into: METIS parts grown by
    ``halo`` hops for MeshGraphNet (default ``halo_depth``), by ``buffer + halo`` hops for
    MeshODENet (``buffer`` rings solved, ``halo`` driven, ``meshodenet.subdomain.driven``), or
    into driven patches of ``halo`` element rings for Implicit-Energy (default 1).
    ``budget`` (``PATCH_BUDGETS``): ``inner``
    cuts ``patch_count`` parts; ``total`` cuts the fewest parts (more by the halo's estimated
    size, then a bisection) whose largest patch, halo included, holds at most ``patch_nodes``
    nodes (METIS's parts are not nested, so "fewest" is up to that), and stops with a
    ``ValueError`` where the halo alone is about that large (a deep halo across a wide
    mesh)."""
    _check_learner(learner)
    if budget not in PATCH_BUDGETS:
        raise ValueError(f"patch_budget must be one of {', '.join(PATCH_BUDGETS)}, got "
                         f"{budget!r}")
    mesh, N = learner.mesh, learner.mesh.n_nodes
    if isinstance(learner, ImplicitEnergy):
        elements, rings = energy_elements(learner), 1 if halo is None else halo

        def grow(parts):
            return driven_patches(mesh, elements, parts, rings)
    else:
        hops = (halo_depth(learner) if halo is None else halo) + buffer

        def grow(parts):
            return graph_patches(mesh, parts, hops)

    def cut(k):
        patches = grow(partition_nodes(mesh.edges, N, k))
        return patches, max(p.n_nodes for p in patches)

    k = patch_count(N, patch_nodes)
    patches, largest = cut(k)
    if budget == "inner" or largest <= patch_nodes:
        return patches
    low = k  # the most parts known to leave a patch too large
    for _ in range(MAX_CUTS):
        added = largest - N / k  # about what the halo adds to a part
        if added >= patch_nodes or k == N:
            break
        k = max(k + 1, min(N, math.ceil(N / (patch_nodes - added))))
        patches, largest = cut(k)
        if largest > patch_nodes:
            low = k
            continue
        while k - low > 1:  # the fewest parts whose patches fit: fewer nodes computed twice
            mid = (low + k) // 2
            fewer, size = cut(mid)
            if size <= patch_nodes:
                k, patches = mid, fewer
            else:
                low = mid
        return patches
    raise ValueError(f"patch_nodes = {patch_nodes} with patch_budget = 'total': cut into "
                     f"{k} parts, the largest patch of {learner.mesh.describe()} still holds "
                     f"{largest} nodes, its halo about {largest - N / k:.0f}; raise "
                     "patch_nodes, or count the inner nodes only (patch_budget = 'inner')")


def _sub_mesh(mesh: Mesh, nodes: np.ndarray) -> Mesh:
    """The mesh of ``nodes`` (global ids, increasing): node arrays there, the edges and cells
    whose nodes all lie in it, in local ids."""
    keep = np.zeros(mesh.n_nodes, bool)
    keep[nodes] = True
    local = np.full(mesh.n_nodes, -1, np.int64)
    local[nodes] = np.arange(len(nodes))
    e = mesh.edges[keep[mesh.edges].all(1)]
    c = np.asarray(mesh.cells, np.int64).reshape(-1, 3)
    c = c[keep[c].all(1)]
    return Mesh(edges=local[e], cells=local[c], node_type=mesh.node_type[nodes],
                rest_pos=mesh.rest_pos[nodes], mass=mesh.mass[nodes], force=mesh.force[nodes],
                damping=mesh.damping[nodes], case=mesh.case, case_hash=mesh.case_hash)


def energy_view(model: ImplicitEnergy, patch: Patch, rings: int) -> ImplicitEnergy:
    """``model`` on a driven patch: a shallow copy that shares its parameters and scalar
    buffers, with the per-node buffers (masses, drag, loads) at the patch's nodes, the free
    mask only on the unknowns (``hops`` below the halo's), and the patch's elements, with their
    whole-mesh data, in local ids (``patch`` of ``driven_patches`` with ``rings``). Its
    one-step loss solves for the unknowns with the halo held where the frames put it."""
    view = copy.copy(model)
    view._buffers = dict(model._buffers)
    view.__dict__.pop("_patterns", None)
    nodes = torch.as_tensor(patch.nodes, device=model.free.device)
    solved = torch.as_tensor(patch.hops < rings, device=nodes.device)
    for name in ("mass", "damping", "force"):
        setattr(view, name, getattr(model, name)[nodes])
    view.free = model.free[nodes] & solved
    for kind in model.kinds:
        i = torch.as_tensor(patch.elements[kind], device=nodes.device)
        local = patch.local(getattr(model, f"{kind}_nodes").cpu().numpy()[patch.elements[kind]])
        setattr(view, f"{kind}_nodes", torch.as_tensor(local, device=nodes.device)
                .reshape(len(i), -1))
        for suffix in ("static", "rest", "l0", "prior"):
            if f"{kind}_{suffix}" in model._buffers:
                setattr(view, f"{kind}_{suffix}", getattr(model, f"{kind}_{suffix}")[i])
    view.mesh = _sub_mesh(model.mesh, patch.nodes)
    return view



class PatchTraining(TrajectoryModel):
    """``learner`` (MeshGraphNet, Implicit-Energy with ``shooting = 0``, or MeshODENet with a
    fixed-step explicit integrator and the ``mse`` loss) trained on patches of about
    ``patch_nodes`` nodes plus a halo (module doc), through the ``TrajectoryModel`` interface,
    so ``fit`` trains it as any model. ``halo``: hops (MeshGraphNet; MeshODENet's driven
    halo; default ``halo_depth``) or element rings of the driven halo (Implicit-Energy,
    default 1). ``buffer``: MeshODENet's rings solved beyond the part but not in the loss
    (``meshodenet.subdomain.driven``). ``loss``: Implicit-Energy's patch loss, ``solve`` (its
    one-step loss with the halo driven) or ``residual`` (``ENERGY_LOSSES``). ``budget``: what
    ``patch_nodes`` counts, the inner nodes or the whole patch (``PATCH_BUDGETS``,
    ``training_patches``).

    Its ``name``, ``config``, ``mesh``, parameters and ``state_dict`` are the learner's; its
    rollouts are the learner's on the whole mesh. ``patches`` are built once.
    """

    def __init__(self, learner: TrajectoryModel, patch_nodes: int, halo: int | None = None,
                 loss: str = "solve", budget: str = "inner", buffer: int = 0):
        _check_learner(learner)
        if isinstance(buffer, bool) or not isinstance(buffer, (int, np.integer)) or buffer < 0:
            raise ValueError(f"buffer must be an integer >= 0 (rings), got {buffer!r}")
        if buffer and not isinstance(learner, MeshODENet):
            raise ValueError(f"buffer = {buffer} is MeshODENet's (rings solved beyond the "
                             f"part); {learner.name}'s halo is set by halo")
        if loss not in ENERGY_LOSSES:
            raise ValueError(f"loss must be one of {', '.join(ENERGY_LOSSES)}, got {loss!r}")
        if loss != "solve" and not isinstance(learner, ImplicitEnergy):
            raise ValueError(f"loss = {loss!r} is Implicit-Energy's; {learner.name} has one "
                             "loss")
        super().__init__(learner.mesh, learner.config)
        self.learner = learner
        self.name, self.trainable = learner.name, learner.trainable
        self.patch_nodes, self.loss = int(patch_nodes), loss
        energy = isinstance(learner, ImplicitEnergy)
        self.halo = (1 if energy else halo_depth(learner)) if halo is None else halo
        self.buffer = int(buffer)
        self.patches = training_patches(learner, patch_nodes, self.halo, budget, self.buffer)
        self._cache: dict = {}

    @property
    def k(self) -> int:
        return len(self.patches)

    # --- the learner's, unchanged -------------------------------------------------------------
    def state_dict(self, *args, **kwargs):
        return self.learner.state_dict(*args, **kwargs)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        self._cache.clear()  # energy views hold copies of element buffers
        return self.learner.load_state_dict(state_dict, strict, assign)

    def _apply(self, fn, *args, **kwargs):
        self._cache.clear()
        return super()._apply(fn, *args, **kwargs)

    def rollout(self, x0, v0, youngs, t):
        return self.learner.rollout(x0, v0, youngs, t)

    def start_epoch(self, epoch: int) -> None:
        self.learner.start_epoch(epoch)

    # --- training -------------------------------------------------------------------------
    def n_training_samples(self, data) -> int:
        return self.learner.n_training_samples(data) * self.k

    def every_patch(self, own: torch.Tensor) -> torch.Tensor:
        """The samples ``(n k,)`` of every patch of the learner's samples ``own (n,)``: a
        sample is ``own * k + patch`` (``training_loss`` splits it back); a batch of them gives
        the whole mesh's loss of those samples where the learner is exact on patches."""
        return (own[:, None] * self.k + torch.arange(self.k, device=own.device)).reshape(-1)

    def training_loss(self, data, samples, generator=None):
        """The learner's loss summed over the inner nodes of the samples' patches, over the
        number of samples times the mean number per patch of the nodes the learner's own loss
        averages over (``node_terms``; module doc): a fixed divisor, so the loss of a batch
        is the mean of its samples' and ranks that split a batch evenly average to the
        batch's loss (a divisor counted per batch would weigh each rank's patches by their
        own sizes)."""
        samples = samples.to(data.pos.device)
        own, part = samples // self.k, samples % self.k
        ode = isinstance(self.learner, MeshODENet)
        if ode:  # one draw of the batch's windows, as the learner's own loss draws them
            traj, start, S = self.learner.windows(data, own, generator)
        total = 0.0
        for p in torch.unique(part).tolist():
            at = part == p
            total = total + (self._ode_loss(self.patches[p], data, traj[at], start[at], S)
                             if ode else
                             self.patch_loss(self.patches[p], data, own[at], generator))
        return total / (len(samples) * max(self.node_terms(), 1) / self.k)

    def node_terms(self) -> int:
        """The nodes a sample's loss is the mean over on the whole mesh: the free nodes
        (MeshGraphNet, Implicit-Energy), every node (MeshODENet's mean holds the clamped
        nodes, whose error is 0)."""
        if isinstance(self.learner, MeshODENet):
            return self.learner.mesh.n_nodes
        return int((self.learner.mesh.node_type == 0).sum())

    def patch_loss(self, patch: Patch, data, samples, generator=None):
        """The learner's loss of its samples ``samples`` on ``patch``, summed over the patch's
        inner nodes (``training_loss`` divides the batch's sum by a fixed count)."""
        if isinstance(self.learner, ImplicitEnergy):
            return self._energy_loss(patch, data, samples)
        if isinstance(self.learner, MeshODENet):
            return self._ode_loss(patch, data, *self.learner.windows(data, samples, generator))
        return self._mgn_loss(patch, data, samples, generator)

    def _ode_loss(self, patch, data, traj, start, S):
        """MeshODENet's ``mse`` loss of the windows ``(traj, start)`` of ``S`` intervals on the
        driven ``patch``, summed over its inner nodes (``MeshODENet.frame_weights``), plus
        ``release_weight`` times the release term's sum (one step from frame 0)."""
        m = self.learner
        topo = self._cached(("topology", patch.part), lambda: patch_topology(m, patch))
        driven, inner = patch.hops > self.buffer, torch.as_tensor(patch.inner)

        def sq(tr, st, steps):
            pred, true = driven_windows(m, topo, driven, data, tr, st, steps, patch.nodes)
            return ((pred[:, 1:] - true[:, 1:]) ** 2).sum(-1)[..., inner.to(pred.device)]

        w = m.frame_weights(data, S).to(data.pos.device, data.pos.dtype)
        total = (sq(traj, start, S).sum((0, 2)) * w).sum()
        lam = m.config.release_weight
        if lam:
            total = total + lam * sq(traj, torch.zeros_like(start), 1).sum() / m.release_scale(data)
        return total

    def _mgn_loss(self, patch, data, samples, generator):
        m = self.learner
        m._check_dt(data.t, "training data t")
        topo = self._cached(("topology", patch.part), lambda: patch_topology(m, patch))
        traj, x_prev, x, x_next = m._frames(data, samples, patch.nodes)
        ctx = graph_context(m.stats, topo, data.youngs[traj], x.dtype, StepContext,
                            dt=float(m.dt))
        err = m.node_errors(x_prev, x, x_next, ctx, generator)
        inner = torch.as_tensor(patch.inner, device=x.device, dtype=x.dtype).repeat(len(x))
        return (err * ctx.batch.free * inner[:, None]).sum()

    def _energy_loss(self, patch, data, samples):
        m = self.learner
        view = self._cached(("view", patch.part), lambda: energy_view(m, patch, self.halo))
        inner = torch.as_tensor(patch.inner, device=view.free.device)
        if self.loss == "residual":
            r, unknowns = energy_residual(view, data, samples, patch.nodes)
        else:
            r, unknowns = view.one_step_errors(data, samples, patch.nodes)
        w = inner[unknowns // 3].to(r.dtype)
        return (r**2 * w).sum() / float(m.ystats[3])

    def _cached(self, key, build):
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]


def energy_residual(model: ImplicitEnergy, data, samples, nodes=None):
    """``(r h^2 / m (S, n), unknowns (n,))``: the residual of the step's equations at the true
    next frame (``ImplicitEnergy._residual``) on the free coordinates, scaled by ``h^2 / m``
    (``A^{-1}`` of the mass term alone) into metres: the loss that needs no solve."""
    traj, xk, vk, x1, h = model._frames(data, samples, nodes)
    sys = model.system(data.youngs[traj])
    act = model._active(xk, vk)
    vk, h = model._implicit_form(vk, model._start(sys, xk, vk), h)
    r = model._residual(sys, x1, xk, vk, h, create_graph=True)[:, act]
    return r * (h**2 / model.mass.repeat_interleave(3)[act]), act
