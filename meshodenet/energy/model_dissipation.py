r"""Implicit-Energy told less: the learned elastic energy of ``implicit_energy`` with a learned
dissipation in place of the case's drag; only the masses ``m`` and loads ``f`` are given.

.. math::
    m x'' = f - dU_\theta/dx - dD_\theta/dv, \qquad
    D_\theta(v; x) = \tfrac12 v^T C_\theta(x) v \ge 0

(``meshodenet.energy.dissipation``: a drag ``1/2 beta_i |v_i|^2`` per node and an internal friction
``1/2 alpha_e eps_dot_e^2`` per edge, positive coefficients learned from invariant static
features). Each saved interval is one backward-Euler step with the damping matrix at the
step's start ``x_k`` (its edge directions lagged, as an implicit solver's Rayleigh damping),
the minimisation

.. math::
    x_{k+1} = \arg\min_x \; \sum_i \frac{m_i}{2h^2} |x_i - x_{k,i} - h v_{k,i}|^2
        + h D_\theta\big((x - x_k)/h;\, x_k\big) - f \cdot x + U_\theta(x),

whose gradient is the residual ``m (x - x_k - h v_k)/h^2 + C v - f + dU/dx`` (``v = (x -
x_k)/h``) and whose Hessian is ``diag(m/h^2) + C/h + d2U/dx2``: symmetric, and positive
definite wherever ``U`` is convex, so the Newton solves, line search, banded Cholesky and
implicit gradients of ``implicit_energy`` apply unchanged. ``h D >= 0`` and ``dD/dv . v = 2 D
>= 0``: the step cannot gain energy from the damping.

The start: the least-squares fit of the training frames' momentum balance ``m a - f + dU/dx
+ C v = 0`` with ``g = 1`` gives the stiffnesses and the damping coefficients together (per
term one rate, or with ``stiffness_prior = "features"`` each element's coefficient linear in
its static features, floored at 1e-3 of the term's largest); on a body without clamped nodes
the drag first and alone, exactly, from the total momentum (``_fit_drag``). Then training as
``implicit_energy``, moving what ``damping_train`` says (``DAMPING_TRAIN``) at the relative
step ``damping_step``; ``quick`` trains the plate's drag rate only and the rod's drag not at
all (docs/ENERGY.md "Told less").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from meshodenet.energy.core import BatchedEnergy
from meshodenet.energy.dissipation import (
    DAMPING_TERMS,
    DAMPING_TRAIN,
    N_FEATURES,
    Damping,
    DampingCoefficient,
    node_features,
)
from meshodenet.energy.model import QUICK, EnergyConfig, ImplicitEnergy
from meshodenet.energy.transfer import fitted_factor
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.training.presets import check_int, preset_configs


@dataclass(frozen=True)
class DissipationConfig(EnergyConfig):
    """``EnergyConfig`` and: ``damping_terms``, the terms of the learned dissipation (keys of
    ``DAMPING_TERMS``, at least one); ``damping_hidden``, ``damping_layers``: width and hidden
    layers of each term's coefficient MLP; ``damping_step``: the factor on the coefficients'
    parameters (``DampingCoefficient.step``: below 1 an optimiser's step moves them less);
    ``damping_train``: which of them training moves (a key of ``DAMPING_TRAIN``)."""

    damping_terms: tuple = ("node", "edge")
    damping_hidden: int = 16
    damping_layers: int = 1
    damping_step: float = 1.0
    damping_train: str = "all"

    def __post_init__(self):
        super().__post_init__()
        check_int(self, "damping_hidden", 1)
        check_int(self, "damping_layers", 0)
        v = self.damping_step
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < math.inf:
            raise ValueError(f"DissipationConfig.damping_step must be a finite number > 0, "
                             f"got {v!r}")
        if self.integrator != "backward_euler":  # its learned drag is backward Euler's
            raise ValueError(f"DissipationConfig.integrator must be 'backward_euler' (the "
                             f"learned dissipation steps by backward Euler only), got "
                             f"{self.integrator!r}")
        if self.damping_train not in DAMPING_TRAIN:
            raise ValueError(f"DissipationConfig.damping_train must be one of "
                             f"{', '.join(DAMPING_TRAIN)}, got {self.damping_train!r}")
        terms = self.damping_terms
        if not isinstance(terms, tuple) or not terms or len(set(terms)) != len(terms) \
                or any(t not in DAMPING_TERMS for t in terms):
            raise ValueError(f"DissipationConfig.damping_terms must be a non-empty tuple of "
                             f"distinct terms of {', '.join(DAMPING_TERMS)}, got {terms!r}")


class ImplicitEnergyDissipation(ImplicitEnergy):
    """See the module docstring. Shapes as ``TrajectoryModel``; ``solver`` as
    ``ImplicitEnergy``. The mesh's ``damping`` is never read."""

    name = "implicit_energy_dissipation"
    line_numpy = False  # its batched objective adds the learned drag's terms in torch

    def __init__(self, mesh: Mesh, config: DissipationConfig, train: Trajectories | None = None):
        super().__init__(mesh, config, None)
        # not given: the parent's drag terms vanish exactly (a new buffer: the old one shares
        # the mesh's array)
        self.damping = torch.zeros_like(self.damping)
        self.dterms = nn.ModuleDict({t: DampingCoefficient(N_FEATURES[t], config.damping_hidden,
                                                           config.damping_layers,
                                                           config.damping_step,
                                                           config.damping_train)
                                     for t in config.damping_terms}).double()
        self.register_buffer("node_dstatic", torch.as_tensor(node_features(mesh),
                                                             dtype=torch.float64))
        if config.stiffness_prior == "features":  # each element's fixed factor kappa
            for t, n in (("node", mesh.n_nodes), ("edge", len(mesh.edges))):
                if t in config.damping_terms:
                    self.register_buffer(f"{t}_dprior", torch.ones(n, dtype=torch.float64))
        if train is not None:
            train = train.to(device=self.ystats.device)
            self._statistics(train)
            self._fit_log_stiffness(train)

    # --- the damping ------------------------------------------------------------------------
    def _dstatic(self, term: str) -> torch.Tensor:
        return self.node_dstatic if term == "node" else self.edge_static

    def coefficients(self, yhat: torch.Tensor) -> dict:
        """Per term its coefficients ``(B, n)`` (``beta`` of nodes, ``alpha`` of edges) for
        the normalised log-moduli ``yhat (B,)`` (differentiable in the parameters)."""
        return {t: m(self._dstatic(t), yhat, getattr(self, f"{t}_dprior", 1.0))
                for t, m in self.dterms.items()}

    def _damping(self, sys, xk, create_graph: bool = False, only: str | None = None) -> Damping:
        """The step's damping matrix at its start ``xk (B, N, 3)``, on the parameters'
        graph with ``create_graph``; with ``only`` of that term alone."""
        with torch.set_grad_enabled(create_graph and torch.is_grad_enabled()):
            c = self.coefficients(sys.yhat)
            if only is not None:
                c = {only: c[only]}
            x = xk if create_graph else xk.detach()
            return Damping.at(x, c.get("node"), c.get("edge"), self.edge_nodes, self.edge_l0)

    def _residual(self, sys, x, xk, vk, h, create_graph=False, geo=None):
        r = super()._residual(sys, x, xk, vk, h, create_graph, geo)
        C = self._damping(sys, xk, create_graph)
        return r + C.force((x - xk) / h).reshape(len(x), -1)

    def _matrix(self, sys, x, h, act, geo=None, xk=None, create_graph: bool = False):
        assert xk is not None, "the learned damping's matrix needs the step's start"
        A = super()._matrix(sys, x, h, act, geo, create_graph=create_graph)
        return A + self._damping(sys, xk).matrix(act, self.mesh.n_nodes) / h

    def _band_matrix(self, sys, x, h, pat, geo=None, xk=None, create_graph: bool = False):
        assert xk is not None, "the learned damping's matrix needs the step's start"
        A = super()._band_matrix(sys, x, h, pat, geo, create_graph=create_graph)
        return A + self._damping(sys, xk).band(pat) / h

    def _objective(self, sys, x, xk, vk, h):
        phi = super()._objective(sys, x, xk, vk, h)
        return phi + h * self._damping(sys, xk).dissipation((x - xk) / h)

    def _batched_objective(self, be: BatchedEnergy, xk, vk, h):
        base = super()._batched_objective(be, xk, vk, h)
        B, cols = len(xk), be.unknowns
        yk = xk.reshape(B, -1)[:, cols]
        C = self._damping(be.sys, xk)
        beta = None if C.beta is None else C.beta[:, cols // 3] / h           # (B, n)
        alpha = None if C.alpha is None else C.alpha / h                     # (B, E)
        g_at, g_to, h_at, h_to = be.maps["edge"]
        dq = C.dq

        def evaluate(y, idx, order):
            phi, r, ab = base(y, idx, order)
            d = y - yk[idx]                                                  # h v
            if beta is not None:
                bh = beta[idx]
                phi = phi + 0.5 * (bh * d * d).sum(1)
                r = None if r is None else r + bh * d
                if ab is not None:
                    ab[:, 0] += bh
            if alpha is None:
                return phi, r, ab
            b, E = len(idx), alpha.shape[1]
            de = d.new_zeros(b, E * 6)
            de[:, g_at] = d[:, g_to]
            q = dq[idx]
            rate = (q * de.reshape(b, E, 6)).sum(-1)                         # h eps_dot
            ah = alpha[idx]
            phi = phi + 0.5 * (ah * rate * rate).sum(1)
            if r is not None:
                r = r.index_add(1, g_to, ((ah * rate)[..., None] * q).reshape(b, -1)[:, g_at])
            if ab is not None:
                he = ah[..., None, None] * q[..., :, None] * q[..., None, :]
                ab = ab.reshape(b, -1).index_add_(1, h_to, he.reshape(b, -1)[:, h_at]) \
                    .reshape(ab.shape)
            return phi, r, ab

        return evaluate

    # --- the least-squares start -------------------------------------------------------------
    @torch.no_grad()
    def _fit_log_stiffness(self, train: Trajectories, every: int = 5) -> None:
        """The stiffnesses (``ImplicitEnergy._set_stiffness``) and the damping coefficients
        (``_set_damping``) from one least-squares fit of the training frames' momentum
        balance ``m a - f + dU/dx + C v = 0`` with ``g = 1`` (free nodes)."""
        T = train.n_frames
        samples = torch.arange(0, len(train) * (T - 1), every)
        traj, xk, vk, x1, h = self._frames(train, samples)
        lhs, owner = self._balance_columns(train.youngs[traj], x1)
        rhs = -(self.mass[:, None] / h**2 * (x1 - xk - h * vk) - self.force)[:, self.free]
        scale = float(self.mass[self.free].mean()) / h
        free_body = "node" in self.dterms and bool(self.free.all())
        if free_body:  # the drag from the total momentum, where no energy enters
            s, owner_node = self._fit_drag(train, samples)
            self._set_damping(s, owner_node, scale, ("node",))
            rhs = rhs - self._damping(self.system(train.youngs[traj]), xk, only="node") \
                .force((x1 - xk) / h)[:, self.free]
        cols, downer = self._damping_columns(xk, x1, h, () if not free_body else ("node",))
        G = torch.stack(lhs + cols, 1)
        s = torch.linalg.lstsq(G, rhs.reshape(-1, 1)).solution[:, 0]
        self._set_stiffness(s[:len(lhs)], owner)
        self._set_damping(s[len(lhs):], downer, scale,
                          tuple(t for t in self.dterms if not (free_body and t == "node")))

    def _fit_drag(self, train: Trajectories, samples: torch.Tensor) -> tuple:
        """The node term's least-squares coefficients ``(s, owner)`` of a mesh without clamped
        nodes from its total momentum over each interval, ``sum_i m_i (v_i(t_{k+1}) -
        v_i(t_k)) + sum_i beta_i (x_{k+1,i} - x_{k,i}) = h sum_i f_i`` (stored velocities):
        the internal forces, elastic and dissipative, sum to zero (translation invariance),
        and a linear drag integrates to ``beta dx`` whatever the data's time steps, so the
        balance is exact for data with a drag linear in the features."""
        T = train.n_frames
        samples = samples.to(train.pos.device)
        traj, k = samples // (T - 1), samples % (T - 1)
        pos, vel = train.pos.to(torch.float64), train.vel.to(torch.float64)
        h = (train.t[k + 1] - train.t[k]).to(torch.float64)[:, None]
        dx = pos[traj, k + 1] - pos[traj, k]
        rhs = h * self.force.sum(0) - (self.mass[:, None] * (vel[traj, k + 1] - vel[traj, k])).sum(1)
        basis = self._damping_basis("node")
        G = torch.stack([(phi[:, None] * dx).sum(1).reshape(-1) for phi in basis], 1)
        s = torch.linalg.lstsq(G, rhs.reshape(-1, 1)).solution[:, 0]
        return s, [("node", phi) for phi in basis]

    def _damping_basis(self, term: str) -> list:
        """The functions ``(n,)`` a term's least-squares coefficient is made of: ones, and with
        ``features`` each static feature that is not a linear combination of those before it
        (on the free nodes for the node term: a triangle mesh's masses are its nodes' areas,
        and dependent columns make the fit's split between them depend on round-off)."""
        static = self._dstatic(term)
        return [torch.ones_like(static[:, 0])] + [static[:, j]
                                                  for j in self._damping_basis_columns(term)]

    def _damping_basis_columns(self, term: str) -> list:
        """The static features (columns) of ``_damping_basis``."""
        static = self._dstatic(term)
        basis, cols = [torch.ones_like(static[:, 0])], []
        if self.config.stiffness_prior == "uniform":
            return cols
        rows = self.free if term == "node" else slice(None)
        for j in range(static.shape[1]):
            trial = torch.stack(basis + [static[:, j]], 1)[rows]
            if int(torch.linalg.matrix_rank(trial, rtol=1e-9)) == len(basis) + 1:
                basis.append(static[:, j])
                cols.append(j)
        return cols

    # --- other meshes (TrajectoryModel.on_mesh) -----------------------------------------------
    def mesh_state_keys(self) -> set:
        """``ImplicitEnergy``'s, the nodes' static features and the damping factors."""
        return super().mesh_state_keys() | {"node_dstatic"} | {
            f"{t}_dprior" for t in self.dterms}

    @torch.no_grad()
    def transfer(self, mesh: Mesh, what: str = "data") -> ImplicitEnergyDissipation:
        """``ImplicitEnergy.transfer``, and the dissipation as the energy: a node's drag and an
        edge's friction are shares of a density per unit length (rods) or area (plates), so
        each term's rate ``b_0`` gains ``d log rho``; the nodes' static features standardised
        with the training mesh's statistics; ``kappa`` fitted in its basis
        (``_damping_basis``) and evaluated on the new nodes and edges."""
        new = super().transfer(mesh, what)
        rho = mesh.length_scale / self.mesh.length_scale
        d = 1 if mesh.kind == "line" else 2
        new.node_dstatic.copy_(torch.as_tensor(node_features(mesh, reference=self.mesh)))
        for t, coef in new.dterms.items():
            coef.log_rate0 = self.dterms[t].log_rate0 + d * math.log(rho)
            if self.config.stiffness_prior == "features":
                getattr(new, f"{t}_dprior").copy_(fitted_factor(
                    self._dstatic(t), getattr(self, f"{t}_dprior"), new._dstatic(t),
                    self._damping_basis_columns(t)))
        return new

    def _damping_columns(self, xk, x1, h, skip: tuple = ()) -> tuple[list, list]:
        """The fit's damping columns: the forces ``C_j v`` on the free nodes of each basis
        function ``j`` of each term (but those in ``skip``) as its coefficients, ``v = (x1 -
        xk) / h``; and per column ``(term, basis function)``."""
        v = (x1 - xk) / h
        ones = torch.ones(len(xk), len(self.edge_nodes), dtype=v.dtype, device=v.device)
        geo = Damping.at(xk, None, ones, self.edge_nodes, self.edge_l0)
        lhs, owner = [], []
        for term in self.dterms:
            if term in skip:
                continue
            for phi in self._damping_basis(term):
                c = phi.expand(len(xk), -1)
                one = Damping(c, None, None, geo.dofs) if term == "node" else \
                    Damping(None, c, geo.dq, geo.dofs)
                lhs.append(one.force(v)[:, self.free].reshape(-1))
                owner.append((term, phi))
        return lhs, owner

    def _set_damping(self, s: torch.Tensor, owner: list, scale: float, terms: tuple) -> None:
        """Each term's ``b_0`` (``log_rate0``) and, with ``features``, ``kappa`` from the fit's
        coefficients ``s``: the elements' coefficients ``sum_j s_j phi_j`` floored at 1e-3 of
        the term's largest and at 1e-6 of the scale ``m/h`` (``scale``, N s/m; edges times
        the mean rest length squared), so a term the data do not show starts small, not at
        zero. Only the ``terms`` named."""
        for term in terms:
            ke = sum(float(sj) * phi for (t, phi), sj in zip(owner, s) if t == term)
            unit = scale * (1.0 if term == "node" else float(self.edge_l0.mean()) ** 2)
            ke = ke.clamp(min=max(1e-3 * float(ke.max()), 1e-6 * unit))
            self.dterms[term].log_rate0.fill_(math.log(float(ke.mean())))
            if self.config.stiffness_prior == "features":
                getattr(self, f"{term}_dprior").copy_(ke / ke.mean())


# --- presets ----------------------------------------------------------------------------------
#: ``quick`` per mesh kind: ``implicit_energy``'s optimiser and schedule; the per-element
#: least-squares start on both kinds of mesh (the rod's drag is not uniform: its heavy node has
#: 50 times the others'; its edges' and hinges' features are constant, so its energy's start
#: is ``uniform``'s); the node drag alone (the data have no internal friction; with the edge
#: term too the plate's step 350 is 1.45 times Implicit-Energy's, 0.94 without); the drag's
#: shape over the nodes kept at its start,
#: the rate trained at a hundredth of the energy's step on the plate and not at all on the
#: rod, whose drag the total momentum gives exactly (docs/ENERGY.md "Told less": a drag off
#: by 0.7 % makes the plate's step 350 ten times worse).
QUICK_DISSIPATION = {
    kind: (train, {**model, "stiffness_prior": "features", "damping_terms": ("node",),
                   "damping_step": 0.01,
                   "damping_train": "none" if kind == "line" else "rate"})
    for kind, (train, model) in QUICK.items()}


def dissipation_presets(preset: str, kind: str) -> tuple:
    """``(TrainConfig, DissipationConfig)``: as ``energy_presets``, ``quick`` with
    ``QUICK_DISSIPATION``, ``smoke`` with small MLPs."""
    return preset_configs(preset, kind, QUICK_DISSIPATION, DissipationConfig,
                          dict(hidden=8, layers=1, damping_hidden=8))


__all__ = ["DissipationConfig", "ImplicitEnergyDissipation", "dissipation_presets"]
