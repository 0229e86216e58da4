r"""Implicit-Energy: a learned elastic energy stepped by backward Euler at the sampling interval;
its config, presets and model.

The mechanics the case's mesh already states (lumped masses ``m``, loads ``f``, linear drag
``c``) is kept, and only the internal elastic energy ``U_theta(x)`` is learned
(``meshodenet.energy.core``: a sum over edges, rod hinges and the dihedral hinges of triangle
meshes of functions of rotation- and translation-invariant strains)::

    m x'' = f - c x' - dU_theta/dx.

Each saved interval ``h`` is one backward-Euler step, the minimisation

.. math::
    x_{k+1} = \arg\min_x \; \sum_i \frac{m_i}{2h^2} |x_i - x_{k,i} - h v_{k,i}|^2
        + \frac{c_i}{2h} |x_i - x_{k,i}|^2 - f_i \cdot x_i + U_\theta(x),
    \qquad v_{k+1} = (x_{k+1} - x_k) / h,

solved by Newton's method with the Hessian ``diag(m/h^2 + c/h) + d2U/dx2`` (symmetric;
Cholesky, with an LU fallback): banded, per trajectory, in rollouts without gradients
(``SOLVERS``), dense otherwise. L-stable at any stiffness: the plate's ``omega h`` of 19-34 and
the rod's drag rate ``c h / m`` of 2.6e5 cost nothing. Clamped nodes stay where they are.
A planar mesh loaded in its plane (rest ``z`` constant, ``f_z = 0``) started in its plane stays
there exactly (the energy is even in ``z``), so only the in-plane coordinates are solved for,
and it has no bending term (its dihedral angles never leave zero). Any other triangle mesh
(``plate_hanging``: gravity through the thickness) is solved in 3-D with the dihedral bending
term, without which a flat sheet has no out-of-plane stiffness.

``integrator = "newmark"`` (``INTEGRATORS``; opt-in) steps by Newmark's average acceleration
instead, ``x_{k+1} = x_k + h v_k + h^2 (a_k + a_{k+1}) / 4``, ``v_{k+1} = 2 (x_{k+1} - x_k) / h
- v_k``, ``a`` from the equation of motion at each state: the same minimisation with ``h / 2``
and the velocity ``2 v_k + h a_k / 2 + h c v_k / (2 m)`` (``_implicit_form``). Second order
(from rest it moves a node ``h^2 a / 2``, backward Euler ``h^2 a``), A- but not L-stable: stiff
modes ring rather than decay. Its training frames take the stored velocities.

Gradients: at the converged ``x*`` one more Newton step ``x* - A^{-1} r(x*)`` is taken with the
residual ``r`` on the autograd graph and the matrix ``A`` detached; its derivative is the
implicit-function derivative ``-A^{-1} dr/d(theta, x_k, v_k)``, never back-propagated through
Newton's iterations.

Training: ``shooting = 0`` (quick) minimises the one-step error linearised at the ground truth,
``|A^{-1} r(x_{k+1})|^2`` with ``A`` at the true next frame (no Newton), over all (trajectory,
frame) pairs, normalised by the mean squared one-step motion (training split); the velocity of
a frame is the backward difference of the positions, as in a rollout; its gradient holds ``A``
fixed unless ``exact_loss_gradient``. ``shooting = S > 0`` trains on windows of ``S`` exact
steps from a true frame instead.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from torch import nn

from meshodenet.energy import linalg as la
from meshodenet.energy.band import BandPattern
from meshodenet.energy.config import INTEGRATORS, SOLVERS, STIFFNESS_PRIORS, EnergyConfig
from meshodenet.energy.core import (
    BatchedEnergy,
    ElementEnergy,
    EnergySystem,
    static_features,
)
from meshodenet.energy.planar import PlanarLineEnergy
from meshodenet.energy.start import LeastSquaresStart
from meshodenet.energy.transfer import EnergyTransfer, element_kinds
from meshodenet.integrators.implicit import NewtonError
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.training.presets import preset_configs
from meshodenet.training.train import TrainConfig


class ImplicitEnergy(LeastSquaresStart, EnergyTransfer, TrajectoryModel):
    """See the module docstring. Shapes as ``TrajectoryModel``. ``solver`` (an attribute, a
    key of ``SOLVERS``, default ``batched``) chooses how rollouts without gradients step;
    rollouts with gradients and training always take the reference steps."""

    name = "implicit_energy"
    integrator_id = "backward_euler"
    grad_mode_id = "implicit"
    solver = "batched"
    on_newton_failure = "raise"
    rollout_settings = ("solver", "on_newton_failure")
    #: the batched solver evaluates a planar rod's energy in numpy (``_batched_energy``)
    line_numpy = True
    #: the batched solver's first guess adds the previous interval's Newton correction
    #: (scaled by ``h^2``) to ``x_k + h v_k`` (``_newton_batched``)
    newton_predictor = True

    def __init__(self, mesh: Mesh, config: EnergyConfig, train: Trajectories | None = None):
        super().__init__(mesh, config)
        self.integrator_id = config.integrator
        feats = static_features(mesh)
        self.planar, self.kinds = element_kinds(mesh, feats)
        # float64 throughout: Newton resolves stiff springs' stretches of 1e-5
        self.terms = nn.ModuleDict({k: ElementEnergy(k, config.hidden, config.layers)
                                    for k in self.kinds}).double()
        f64 = dict(dtype=torch.float64)
        x0 = torch.as_tensor(mesh.rest_pos, **f64)
        for k in self.kinds:
            nodes, static, rest = feats[k]
            nodes = torch.as_tensor(nodes)
            l0 = (x0[nodes[:, 1]] - x0[nodes[:, 0]]).norm(dim=-1) if k == "edge" \
                else torch.ones(len(nodes), **f64)
            self.register_buffer(f"{k}_nodes", nodes)
            self.register_buffer(f"{k}_static", torch.as_tensor(static, **f64))
            self.register_buffer(f"{k}_rest", torch.as_tensor(rest, **f64))
            self.register_buffer(f"{k}_l0", l0)
            self.register_buffer(f"{k}_sigma", torch.ones((), **f64))
            if config.stiffness_prior == "features":  # the fixed factor kappa_e per element
                self.register_buffer(f"{k}_prior", torch.ones(len(nodes), **f64))
            if config.clamp_q:  # the training frames' range of qhat (its MLP's input)
                self.register_buffer(f"{k}_qrange", torch.tensor([-math.inf, math.inf], **f64))
        for name in ("mass", "damping"):
            self.register_buffer(name, torch.as_tensor(getattr(mesh, name), **f64))
        self.register_buffer("force", torch.as_tensor(mesh.force, **f64))
        self.register_buffer("free", torch.as_tensor(mesh.node_type == 0))
        # Ybar, mean and std of log Y, mean squared one-step motion (training split)
        self.register_buffer("ystats", torch.ones(4, **f64))
        edges = np.asarray(mesh.edges)
        self.length = float(np.linalg.norm(mesh.rest_pos[edges[:, 1]]
                                           - mesh.rest_pos[edges[:, 0]], axis=1).mean())
        if train is not None:  # on the buffers' device (the model is moved after it is built)
            train = train.to(device=self.ystats.device)
            self._statistics(train)
            self._fit_log_stiffness(train)

    # --- the system ---------------------------------------------------------------------------
    def _elems(self):
        return {k: (getattr(self, f"{k}_nodes"), getattr(self, f"{k}_static"),
                    getattr(self, f"{k}_rest"), getattr(self, f"{k}_l0")) for k in self.kinds}

    def _prior(self) -> dict | None:
        """Per kind each element's stiffness factor ``kappa_e`` (``stiffness_prior``)."""
        if self.config.stiffness_prior == "uniform":
            return None
        return {k: getattr(self, f"{k}_prior") for k in self.kinds}

    def system(self, youngs: torch.Tensor) -> EnergySystem:
        s = self.ystats
        return EnergySystem(self.terms, self._elems(),
                            {k: getattr(self, f"{k}_sigma") for k in self.kinds},
                            youngs, float(s[0]), (float(s[1]), float(s[2])),
                            analytic=self.solver != "reference", prior=self._prior(),
                            qrange={k: getattr(self, f"{k}_qrange") for k in self.kinds}
                            if self.config.clamp_q else None)

    def _active(self, x0, v0) -> torch.Tensor:
        """Indices into the ``3N`` coordinates that Newton solves for."""
        dims = 3
        if self.planar and torch.all(x0[..., 2] == float(self.mesh.rest_pos[0, 2])) \
                and not torch.any(v0[..., 2]):
            dims = 2
        nodes = torch.nonzero(self.free).reshape(-1)
        return (3 * nodes[:, None] + torch.arange(dims, device=nodes.device)).reshape(-1)

    def _residual(self, sys, x, xk, vk, h, create_graph=False, geo=None):
        """``r (B, 3N)``: the gradient of the step's objective at ``x``."""
        m, c = self.mass[:, None], self.damping[:, None]
        r = m / h**2 * (x - xk - h * vk) + c / h * (x - xk) - self.force \
            + sys.gradient(x, create_graph, geo)
        return r.reshape(len(x), -1)

    def _acceleration(self, sys, x, v, create_graph: bool = False) -> torch.Tensor:
        """``a = (f - c v - dU/dx) / m`` at ``(x, v)`` (zero on clamped nodes)."""
        m, c = self.mass[:, None], self.damping[:, None]
        return (self.force - c * v - sys.gradient(x, create_graph)) / m * self.free[:, None]

    def _implicit_form(self, vk, ak, h):
        """``(v', h')`` with which the backward-Euler step's equations (``_residual``) are the
        configured step's from ``(x_k, v_k, a_k)`` over ``h``: backward Euler ``(v_k, h)``;
        Newmark's with ``gamma`` and ``beta = gamma^2`` (``x_{k+1} = p + beta h^2 a_{k+1}``,
        ``p = x_k + h v_k + (1/2 - beta) h^2 a_k``; ``v_{k+1} = q + gamma h a_{k+1}``, ``q = v_k
        + (1 - gamma) h a_k``; ``m a_{k+1} = f - c v_{k+1} - dU/dx``) ``((p - x_k) / h' - h' K /
        m, h' = gamma h)`` with ``K = c (q - (p - x_k) / h')``: the predictor and the constant
        drag force folded into one velocity (``gamma = 1/2``: ``2 v_k + h a_k / 2 + h c v_k /
        (2 m)``)."""
        if self.config.integrator == "backward_euler":
            return vk, h
        g = self.config.newmark_gamma
        m, c = self.mass[:, None], self.damping[:, None]
        p, q = h * vk + (0.5 - g * g) * h * h * ak, vk + (1 - g) * h * ak  # p - x_k
        hp = g * h
        return (p / hp - hp * c * (q - p / hp) / m) * self.free[:, None], hp

    def _advance(self, sys, xk, vk, ak, xn, h):
        """``(v_{k+1}, a_{k+1})`` after the step from ``(x_k, v_k, a_k)`` to ``xn`` (``a``:
        None for backward Euler, Newmark's from the equation of motion at the new state)."""
        if self.config.integrator == "backward_euler":
            return (xn - xk) / h, None
        g = self.config.newmark_gamma
        a = (xn - xk - h * vk - (0.5 - g * g) * h * h * ak) / (g * g * h * h)
        vn = (vk + (1 - g) * h * ak + g * h * a) * self.free[:, None]
        return vn, self._acceleration(sys, xn, vn, torch.is_grad_enabled())

    def _start(self, sys, x, v):
        """The acceleration a step from ``(x, v)`` needs (Newmark's; None for backward Euler)."""
        if self.config.integrator == "backward_euler":
            return None
        return self._acceleration(sys, x, v, torch.is_grad_enabled())

    def _matrix(self, sys, x, h, act, geo=None, xk=None, create_graph: bool = False):
        """The Newton matrix ``diag(m/h^2 + c/h) + d2U/dx2`` on the coordinates ``act``
        (``xk``, the step's start, is for a subclass whose damping depends on it; with
        ``create_graph`` differentiable in the parameters)."""
        A = sys.hessian(x.detach(), geo, act, create_graph)
        d = (self.mass / h**2 + self.damping / h).repeat_interleave(3)[act]
        return A + torch.diag(d)

    def _band_matrix(self, sys, x, h, pat: BandPattern, geo=None, xk=None,
                     create_graph: bool = False):
        """``_matrix`` on ``pat``'s unknowns in its band storage ``(B, width + 1, n)``."""
        d = (self.mass / h**2 + self.damping / h)[pat.unknowns // 3]
        return sys.hessian_band(x.detach(), pat, geo, create_graph, diag=d)

    def _pattern(self, sys, act) -> BandPattern:
        """The band pattern of the coordinates ``act`` on this model's mesh (kept per mesh
        and ``act``: a copy of the model on another mesh makes its own)."""
        key = tuple(act.tolist())
        mesh, cache = self.__dict__.get("_patterns", (None, None))
        if mesh is not self.mesh:
            cache = {}
            self.__dict__["_patterns"] = (self.mesh, cache)
        if key not in cache:
            cache[key] = BandPattern(sys, act, self.mesh.n_nodes)
        return cache[key]

    def _solve(self, A, b):
        return la.substitute(la.factor(A), b)

    def _objective(self, sys, x, xk, vk, h):
        """The step's objective per graph ``(B,)`` (its gradient is ``_residual``)."""
        m, c = self.mass[:, None], self.damping[:, None]
        phi = m / (2 * h**2) * (x - xk - h * vk) ** 2 + c / (2 * h) * (x - xk) ** 2 \
            - self.force * x
        return phi.sum((1, 2)) + sys.energy(x)

    def _newton(self, sys, xk, vk, h, act, where: str, chord: bool = False):
        """``x_{k+1}`` (no graph) and the last Newton matrix: Newton with a backtracking line
        search on the objective. ``chord``: keep the factorised matrix while each step shrinks
        at least threefold (the returned matrix is then not the one at ``x_{k+1}``)."""
        xk, vk = xk.detach(), vk.detach()
        x = xk.clone()
        flat = x.reshape(len(x), -1)
        flat[:, act] += h * vk.reshape(len(x), -1)[:, act]
        tol = self.config.newton_rtol * self.length
        factor, prev = None, math.inf
        done = 0
        while done < self.config.newton_max_iter:
            done += 1
            geo = sys.geometry(x, second=factor is None)
            r = self._residual(sys, x, xk, vk, h, geo=geo)[:, act]
            if factor is None:
                A = self._matrix(sys, x, h, act, geo, xk)
                factor = la.factor(A)
            dx = la.substitute(factor, -r)
            if factor[0] == "lu" and bool(((r * dx).sum(1) >= 0).any()):
                # not a descent direction (the objective is not convex here): convexify
                factor = la.factor(A, convexify=True)
                dx = la.substitute(factor, -r)
            step = float(dx.abs().max())
            if not math.isfinite(step):
                break
            if step <= tol:
                x.reshape(len(x), -1)[:, act] += dx
                return x, A
            if not chord or step > prev / 3:
                factor = None
            prev = step
            x = self._line_search(sys, x, xk, vk, h, act, dx, r)
        raise NewtonError(f"{self.name}: Newton did not converge at {where}, h = {h:.4g} s: "
                          f"last step {step:.3g} m > {tol:.3g} m after {done} iterations "
                          f"(largest residual {float(r.abs().max()):.3g} N)")

    def _line_search(self, sys, x, xk, vk, h, act, dx, r, halvings: int = 12):
        """``x + alpha dx`` per graph, ``alpha`` halved from 1 until the objective decreases
        (Armijo); the full step where none does (Newton then reports)."""
        phi0 = self._objective(sys, x, xk, vk, h)
        slope = (r * dx).sum(1)
        alpha = torch.ones(len(x), dtype=x.dtype, device=x.device)
        done = torch.zeros(len(x), dtype=torch.bool, device=x.device)
        for _ in range(halvings):
            trial = x.clone()
            trial.reshape(len(x), -1)[:, act] += alpha[:, None] * dx
            ok = self._objective(sys, trial, xk, vk, h) <= phi0 + 1e-4 * alpha * slope
            done = done | ok
            if bool(done.all()):
                break
            alpha = torch.where(done, alpha, alpha / 2)
        alpha = torch.where(done, alpha, torch.ones_like(alpha))
        out = x.clone()
        out.reshape(len(x), -1)[:, act] += alpha[:, None] * dx
        return out

    def step(self, sys, xk, vk, h, act, where: str = "a step"):
        """One step in backward-Euler form (``vk``, ``h``: ``_implicit_form``'s): ``x_{k+1}``,
        differentiable by the implicit function."""
        grad = torch.is_grad_enabled()
        with torch.no_grad():
            x, A = self._newton(sys, xk, vk, h, act, where, chord=not grad)
        if not grad:
            return x
        r = self._residual(sys, x, xk, vk, h, create_graph=True)[:, act]
        out = x.reshape(len(x), -1).clone()
        out[:, act] = out[:, act] - self._solve(A, r)
        return out.reshape(x.shape)

    # --- rollouts -----------------------------------------------------------------------------
    def rollout(self, x0, v0, youngs, t):
        """As ``TrajectoryModel.rollout``. A step whose Newton does not converge raises
        ``NewtonError``; with ``on_newton_failure = "nan"`` (an attribute; the suite's test and
        long-horizon evaluation set it) a rollout without gradients instead rolls each
        trajectory of the batch alone, and one that fails keeps its frames up to the failing
        interval and NaN after it, as a rollout that diverged."""
        if self.on_newton_failure not in ("raise", "nan"):
            raise ValueError("ImplicitEnergy.on_newton_failure must be 'raise' or 'nan', got "
                             f"{self.on_newton_failure!r}")
        pos, vel = [], []
        try:
            return self._rollout(x0, v0, youngs, t, pos, vel)
        except NewtonError as e:
            if self.on_newton_failure == "raise" or torch.is_grad_enabled():
                raise
            if len(x0) > 1:
                parts = [self.rollout(x0[i:i + 1], v0[i:i + 1], youngs[i:i + 1], t)
                         for i in range(len(x0))]
                return torch.cat([p for p, _ in parts]), torch.cat([v for _, v in parts])
            warnings.warn(f"{e}; its frames from there on are NaN", RuntimeWarning, stacklevel=2)
            gone = torch.full_like(pos[0], math.nan)
            pos += [gone] * (len(t) - len(pos))
            vel += [gone] * (len(t) - len(vel))
            return torch.stack(pos, 1).to(x0.dtype), torch.stack(vel, 1).to(x0.dtype)

    def _rollout(self, x0, v0, youngs, t, pos: list, vel: list):
        """The rollout; its frames are appended to ``pos`` and ``vel`` as they are found."""
        if self.solver not in SOLVERS:
            raise ValueError(f"ImplicitEnergy.solver must be one of {', '.join(SOLVERS)}, got "
                             f"{self.solver!r}")
        dtype = x0.dtype
        x = x0.to(torch.float64)
        v = v0.to(torch.float64) * self.free[:, None]
        t = t.to(torch.float64)
        sys = self.system(youngs)
        act = self._active(x, v)
        if self.solver == "batched" and not torch.is_grad_enabled():
            unknowns = self._batched_energy(sys, act)
            step = lambda x, v, h, where: self._newton_batched(unknowns, x, v, h, where)  # noqa: E731
        else:
            step = lambda x, v, h, where: self.step(sys, x, v, h, act, where)  # noqa: E731
        pos.append(x)
        vel.append(v)
        a = self._start(sys, x, v)
        times = t.tolist()
        for k in range(len(t) - 1):
            x, v, a = self._interval(step, sys, x, v, a, times[k + 1] - times[k],
                                     f"interval {k} (t = {times[k]:.4g} s)")
            pos.append(x)
            vel.append(v)
        return torch.stack(pos, 1).to(dtype), torch.stack(vel, 1).to(dtype)

    def _interval(self, step, sys, x, v, a, h, where: str, depth: int = 0):
        """``(x, v, a)`` after an interval ``h``: one step, or where its Newton fails two steps
        of ``h / 2``, up to ``max_halvings`` times over (then ``NewtonError``)."""
        try:
            xn = step(x, *self._implicit_form(v, a, h), where)
        except NewtonError:
            if depth >= self.config.max_halvings:
                raise
            x, v, a = self._interval(step, sys, x, v, a, h / 2, f"{where}, first half", depth + 1)
            return self._interval(step, sys, x, v, a, h / 2, f"{where}, second half", depth + 1)
        return (xn, *self._advance(sys, x, v, a, xn, h))

    # --- the batched solver (rollouts without gradients) --------------------------------------
    def _batched_energy(self, sys, act):
        """The batched solver's energy: ``BatchedEnergy``, or its numpy evaluation
        ``PlanarLineEnergy`` where that applies (a planar rod solved in its plane on the CPU;
        a subclass whose objective adds torch terms keeps ``line_numpy = False``)."""
        be = BatchedEnergy(sys, act, self.mesh.n_nodes, self._pattern(sys, act))
        return PlanarLineEnergy(be) if self.line_numpy and PlanarLineEnergy.applies(be) else be

    @torch.no_grad()
    def _newton_batched(self, be, xk, vk, h, where: str):
        """``x_{k+1} (B, N, 3)`` of every trajectory by its own Newton (as ``_newton`` with
        ``chord``: its own factorisation, chord and line-search decisions), the batch's
        energies evaluated together and converged trajectories dropping out. Works on the
        unknowns ``be.unknowns`` (banded order), the objective relative to ``x_k`` (the
        constant ``f . x_k`` and the fixed coordinates left out); the iteration on numpy
        arrays (the energy's evaluation in torch for a ``BatchedEnergy``). The first guess
        ``x_k + h v_k`` plus the previous interval's correction (``newton_predictor``); where
        Newton does not converge from it, it starts again from ``x_k + h v_k``."""
        B = len(xk)
        evaluate = self._batched_objective(be, xk, vk, h)
        if not getattr(be, "numpy", False):
            evaluate = la.on_numpy(evaluate, xk.device)
        cols = be.cols
        xkf = xk.reshape(B, -1).cpu().numpy()
        guess = xkf[:, cols] + h * vk.reshape(B, -1).cpu().numpy()[:, cols]
        last = getattr(be, "last_correction", None) if self.newton_predictor else None
        out = None
        if last is not None and last[0].shape == guess.shape:  # the previous correction
            try:
                out = self._iterate(evaluate, guess + (h / last[1]) ** 2 * last[0], h, where)
            except NewtonError:
                out = None
        if out is None:
            out = self._iterate(evaluate, guess, h, where)
        be.last_correction = (out - guess, h)
        xn = xkf.copy()  # xkf shares xk's memory
        xn[:, cols] = out
        return torch.from_numpy(xn).to(xk.device).reshape(xk.shape)

    def _iterate(self, evaluate, y, h, where: str) -> np.ndarray:
        """``_newton_batched``'s Newton iterations from the unknowns ``y (B, n)``: the
        converged unknowns, or ``NewtonError``."""
        B = len(y)
        tol = self.config.newton_rtol * self.length
        idx = np.arange(B)
        phi, r, ab = evaluate(y, idx, 2)
        facs = [la.band_factor(a) for a in ab]
        prev = np.full(B, math.inf)
        out = np.empty_like(y)
        for done in range(1, self.config.newton_max_iter + 1):
            dx = la.band_solve(facs, r)
            step = np.abs(dx).max(1)
            conv = step <= tol
            if conv.all():  # the whole (remaining) batch
                out[idx] = y + dx
                return out
            if done == self.config.newton_max_iter or not np.isfinite(step).all():
                break
            if conv.any():
                out[idx[conv]] = y[conv] + dx[conv]
                live = np.flatnonzero(~conv)
                idx, y, dx, r, phi, step = (idx[live], y[live], dx[live], r[live], phi[live],
                                            step[live])
                facs, prev = [facs[j] for j in live], prev[live]
            refactor = step > prev / 3
            prev = step
            if refactor.any():
                y, phi, r, ab = la.armijo_search(evaluate, idx, y, dx, r, phi, 2)
                for j in np.flatnonzero(refactor):
                    facs[j] = la.band_factor(ab[j])
            else:
                y, phi, r, _ = la.armijo_search(evaluate, idx, y, dx, r, phi, 1)
        worst = int(np.nan_to_num(step, nan=math.inf).argmax())
        raise NewtonError(f"{self.name}: Newton did not converge at {where}, h = {h:.4g} s, "
                          f"trajectory {int(idx[worst])} of the batch: last step "
                          f"{float(step[worst]):.3g} m > {tol:.3g} m after {done} iterations "
                          f"(largest residual {float(np.abs(r[worst]).max()):.3g} N)")

    def _batched_objective(self, be, xk, vk, h):
        """``evaluate(y, idx, order) -> (phi, r, ab)``: the step's objective relative to
        ``x_k``, its gradient and (``order`` 2) its Hessian in band storage, of the
        trajectories ``idx`` at unknowns ``y (b, n)`` (``_newton_batched``); on numpy arrays
        for a numpy ``be`` (``PlanarLineEnergy``), else on tensors."""
        B = len(xk)
        arr = (lambda t: t.cpu().numpy()) if getattr(be, "numpy", False) else (lambda t: t)
        cols = be.unknowns
        xkf = arr(xk.reshape(B, -1))
        yk, hv = xkf[:, cols], h * arr(vk.reshape(B, -1))[:, cols]
        terms = be.__dict__.setdefault("objective_terms", {})  # per h, for the rollout
        if h not in terms:
            node = cols // 3
            mh, ch = arr(self.mass / h**2)[node], arr(self.damping / h)[node]
            terms[h] = (0.5 * mh, 0.5 * ch, arr(self.force.reshape(-1))[cols], mh + ch)
        hm, hc, f, diag = terms[h]

        def evaluate(y, idx, order):
            """``(phi, r, ab)`` of the trajectories ``idx`` at unknowns ``y``."""
            full = len(idx) == B  # all of them, in order (trajectories only drop out)
            x = xkf[idx]  # a copy (advanced indexing)
            x[:, cols] = y
            U, dU, ab = be.evaluate(x.reshape(len(idx), -1, 3), idx, order)
            d = y - (yk if full else yk[idx])
            a = d - (hv if full else hv[idx])
            ma, hcd = hm * a, hc * d  # m a / 2, c d / 2
            cd = hcd - f
            phi = (ma * a + cd * d).sum(1) + U
            if dU is None:
                return phi, None, ab
            dU += ma
            dU += ma
            dU += hcd
            dU += cd
            if ab is not None:
                ab[:, 0] += diag
            return phi, dU, ab
        return evaluate

    # --- training -----------------------------------------------------------------------------
    def n_training_samples(self, data: Trajectories) -> int:
        if self.config.shooting:
            return len(data) * max((data.n_frames - 1) // self.config.shooting, 1)
        return len(data) * (data.n_frames - 1)

    def training_loss(self, data, samples, generator=None):
        if self.config.shooting:
            return self._window_loss(data, samples, generator)
        d, _ = self.one_step_errors(data, samples)
        n = len(self.free.nonzero())
        return (d**2).sum() / (len(samples) * n * float(self.ystats[3]))

    def one_step_errors(self, data, samples, nodes=None):
        """``(d (S, n), unknowns (n,))``: the one-step error linearised at the true next frame,
        ``d = A^{-1} r(x_{k+1})`` (module doc), of the samples ``samples (S,)`` on the
        coordinates ``unknowns`` (flat ``3 node + axis``, in the band's order) that Newton
        solves for; with ``nodes`` (global ids) the frames at those nodes only."""
        traj, xk, vk, x1, h = self._frames(data, samples, nodes)
        sys = self.system(data.youngs[traj])
        act = self._active(xk, vk)
        vk, h = self._implicit_form(vk, self._start(sys, xk, vk), h)
        geo = sys.geometry(x1)
        pat = self._pattern(sys, act)
        A = self._band_matrix(sys, x1, h, pat, geo, xk,
                              create_graph=self.config.exact_loss_gradient)
        r = self._residual(sys, x1, xk, vk, h, create_graph=True, geo=geo)[:, pat.unknowns]
        return la.BandSolve.apply(A, r), pat.unknowns

    def _window_loss(self, data, samples, generator):
        S = self.config.shooting
        T = data.n_frames
        per = max((T - 1) // S, 1)
        traj = samples // per
        off = int(torch.randint(0, max(T - 1 - per * S, 0) + 1, (), generator=generator))
        start = (samples % per) * S + off
        # the window's first frame and velocity as the one-step loss takes them
        _, xk, vk, _, h = self._frames(data, traj * (T - 1) + start)
        sys = self.system(data.youngs[traj])
        act = self._active(xk, vk)
        ak = self._start(sys, xk, vk)
        loss = 0.0
        for s in range(S):
            end = (start + s + 1).clamp(max=T - 1)
            xn = self.step(sys, xk, *self._implicit_form(vk, ak, h), act, f"window step {s}")
            (vk, ak), xk = self._advance(sys, xk, vk, ak, xn, h), xn
            loss = loss + ((xk - data.pos[traj, end].to(torch.float64))[:, self.free] ** 2) \
                .sum(-1).mean()
        return loss / (S * float(self.ystats[3]))


# --- presets ----------------------------------------------------------------------------------
#: ``quick`` per mesh kind: ``(TrainConfig fields, EnergyConfig fields)`` over the paper's
#: optimiser (chosen on validation, docs/TRAINING.md "Implicit-Energy").
QUICK = {
    "line": (dict(epochs=4, lr=1e-2, lr_milestones=(3,), batch_size=32, max_batches=25,
                  weight_decay=0.0, grad_clip=1.0), dict()),
    # so that no seed fails: the per-element least-squares stiffness, then lr 3e-3 (chosen
    # on validation over 5 seeds against 1e-2 and 1e-3, docs/ENERGY.md "No bad seed")
    "triangle": (dict(epochs=6, lr=3e-3, lr_milestones=(5,), batch_size=32, max_batches=50,
                      weight_decay=0.0, grad_clip=1.0), dict(stiffness_prior="features")),
}


def energy_presets(preset: str, kind: str) -> tuple[TrainConfig, EnergyConfig]:
    """``(TrainConfig, EnergyConfig)``: ``paper`` the paper's optimiser and schedule with
    the default model; ``quick`` with ``QUICK``; ``smoke`` a tiny model, 2 epochs of 3 steps."""
    return preset_configs(preset, kind, QUICK, EnergyConfig, dict(hidden=8, layers=1))


__all__ = ["EnergyConfig", "INTEGRATORS", "ImplicitEnergy", "STIFFNESS_PRIORS", "energy_presets"]
