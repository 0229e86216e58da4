"""ODE integrators and gradient modes for ``dz/dt = f(t, z)``.

``INTEGRATORS`` maps a stable id to an integrator: explicit Runge-Kutta schemes on a fixed
grid (``euler``, ``midpoint``, ``rk4``), each interval between saved times split into
``substeps`` equal steps (1 = the paper's step equal to the sampling interval), and the adaptive
Dormand-Prince pair ``dopri5`` (torchdiffeq) controlled by ``rtol``/``atol``. ``rk4`` is the
3/8-rule variant, the one torchdiffeq (and so the paper) calls ``rk4``. The adjoint mode runs
torchdiffeq's own schemes on the same grid, so its forward solution equals that of the other
modes to rounding. The implicit schemes ``backward_euler`` and ``sdirk2``
(``meshodenet.integrators.implicit``) solve every step by Newton's method and always differentiate it
implicitly (one transposed linear solve per stage), whatever the gradient mode.

``GRADIENT_MODES``:

- ``direct``: backpropagate through every solver operation (memory grows with the number of
  evaluations times the graph size).
- ``checkpoint``: the rollout is cut into segments of ``checkpoint_every`` saved intervals; the
  forward pass keeps only the states at segment ends, and each segment is recomputed, with its
  graph, during the backward pass. Same gradient as ``direct`` (same operations), about one
  extra forward solve of cost, memory of one segment's graph. ``f`` may depend on tensors that
  require grad only through ``z`` and ``params`` (as for the adjoint).
- ``adjoint``: torchdiffeq's ``odeint_adjoint`` (the paper's method), solving the adjoint ODE
  backwards with the same scheme; ``seminorm`` drops the parameter-adjoint from the adaptive
  error norm. Its gradient equals the others up to the discretisation error of that backward
  solve (exact in the limit of small steps, not to float tolerance at coarse steps).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from meshodenet.integrators.implicit import IMPLICIT


@dataclass(frozen=True)
class ExplicitRK:
    """An explicit Runge-Kutta scheme by its Butcher tableau ``(c, a, b)``:
    ``k_s = f(t + c_s h, z + h sum_r a_sr k_r)``, ``z_{n+1} = z + h sum_s b_s k_s``."""

    id: str
    order: int
    c: tuple
    a: tuple
    b: tuple
    adaptive = False

    def step(self, f, t, h, z):
        ks = []
        for c, a in zip(self.c, self.a, strict=True):
            zs = z
            for a_r, k in zip(a, ks, strict=True):
                if a_r:
                    zs = zs + (h * a_r) * k
            ks.append(f(t + c * h, zs))
        dz = sum(b * k for b, k in zip(self.b, ks, strict=True) if b)
        return z + h * dz

    def solve(self, f, z0, t, substeps: int = 1, **_):
        """States at the times ``t (T,)``: ``(T, *z0.shape)``."""
        zs, z = [z0], z0
        for k in range(len(t) - 1):
            h = (t[k + 1] - t[k]) / substeps
            for s in range(substeps):
                z = self.step(f, t[k] + s * h, h, z)
            zs.append(z)
        return torch.stack(zs)

    def torchdiffeq_options(self, substeps: int) -> tuple[str, dict]:
        return _TDQ_NAMES[self.id], {"grid_constructor": _subdivide(substeps)}


@dataclass(frozen=True)
class Adaptive:
    """An adaptive torchdiffeq solver (``dopri5``) with error control ``rtol``/``atol``."""

    id: str
    order: int
    adaptive = True

    def solve(self, f, z0, t, rtol: float = 1e-4, atol: float = 1e-7, **_):
        from torchdiffeq import odeint

        return capped(lambda opts: odeint(f, z0, t, rtol=rtol, atol=atol, method=self.id,
                                          options=opts), z0, t, self.id)

    def torchdiffeq_options(self, substeps: int) -> tuple[str, dict]:
        return self.id, {}


#: An adaptive solve gives up after this many accepted steps per output interval (a learned
#: field can be arbitrarily stiff early in training; uncapped, dopri5 would crawl for hours).
MAX_STEPS_PER_INTERVAL = 1000


def capped(solve, z0: torch.Tensor, t: torch.Tensor, name: str) -> torch.Tensor:
    """Run ``solve(options)`` with torchdiffeq's ``max_num_steps`` cap; past the cap, warn and
    return NaN for every output (the trainer skips such a step, a rollout scores inf)."""
    import warnings

    cap = MAX_STEPS_PER_INTERVAL * max(1, len(t) - 1)
    try:
        return solve({"max_num_steps": cap})
    except AssertionError as e:
        if "max_num_steps" not in str(e):
            raise
        warnings.warn(f"{name}: more than {cap} steps for {len(t) - 1} intervals (the vector "
                      "field is too stiff for rtol/atol); the result is NaN. Loosen "
                      "model.rtol/model.atol or use a fixed-step integrator.", RuntimeWarning,
                      stacklevel=2)
        return torch.full((len(t), *z0.shape), float("nan"), dtype=z0.dtype, device=z0.device)


def _subdivide(substeps: int):
    """A torchdiffeq ``grid_constructor`` that splits every interval of ``t`` in ``substeps``."""

    def grid(func, y0, t):
        if substeps == 1:
            return t
        frac = torch.arange(substeps, dtype=t.dtype, device=t.device) / substeps
        inner = (t[:-1, None] + (t[1:] - t[:-1])[:, None] * frac).reshape(-1)
        return torch.cat([inner, t[-1:]])

    return grid


_TDQ_NAMES = {"euler": "euler", "midpoint": "midpoint", "rk4": "rk4"}
_3 = 1.0 / 3.0

INTEGRATORS = {
    "euler": ExplicitRK("euler", 1, (0.0,), ((),), (1.0,)),
    "midpoint": ExplicitRK("midpoint", 2, (0.0, 0.5), ((), (0.5,)), (0.0, 1.0)),
    "rk4": ExplicitRK("rk4", 4, (0.0, _3, 2 * _3, 1.0),
                      ((), (_3,), (-_3, 1.0), (1.0, -1.0, 1.0)),
                      (0.125, 0.375, 0.375, 0.125)),
    "dopri5": Adaptive("dopri5", 5),
    **IMPLICIT,
}
GRADIENT_MODES = ("direct", "checkpoint", "adjoint")


def get_integrator(name: str):
    try:
        return INTEGRATORS[name]
    except KeyError:
        raise ValueError(f"unknown integrator {name!r}; valid: "
                         f"{', '.join(sorted(INTEGRATORS))}") from None


def odesolve(f, z0: torch.Tensor, t: torch.Tensor, method: str = "rk4",
             grad_mode: str = "direct", substeps: int = 1, rtol: float = 1e-4,
             atol: float = 1e-7, checkpoint_every: int = 1, seminorm: bool = True,
             params=None) -> torch.Tensor:
    """Integrate ``dz/dt = f(t, z)`` from ``z(t[0]) = z0``; ``z`` at ``t``: ``(T, *z0.shape)``.

    ``f`` is called as ``f(t, z)``; for ``grad_mode="adjoint"`` or ``"checkpoint"`` it must be an
    ``nn.Module`` or ``params`` must list the tensors it differentiates (default: its
    parameters). ``rtol``/``atol`` are used by adaptive methods
    only, ``substeps`` by fixed-step methods only. Implicit methods ignore ``grad_mode``:
    their gradient is always the implicit one (``meshodenet.integrators.implicit``).
    """
    integ = get_integrator(method)
    kw = {"substeps": substeps, "rtol": rtol, "atol": atol}
    if grad_mode not in GRADIENT_MODES:
        raise ValueError(f"unknown gradient mode {grad_mode!r}; valid: "
                         f"{', '.join(GRADIENT_MODES)}")
    if getattr(integ, "implicit", False):  # gradients by implicit differentiation, any mode
        return integ.solve(f, z0, t, substeps=substeps, params=params)
    if grad_mode == "direct" or not torch.is_grad_enabled():
        return integ.solve(f, z0, t, **kw)
    if grad_mode == "checkpoint":
        params = tuple(f.parameters()) if params is None else tuple(params)
        return _solve_checkpointed(integ, f, z0, t, checkpoint_every, kw, params)
    if grad_mode == "adjoint":
        from torchdiffeq import odeint_adjoint

        name, opts = integ.torchdiffeq_options(substeps)
        adj_opts = dict(opts, norm="seminorm") if seminorm else dict(opts)
        tol = {"rtol": rtol, "atol": atol} if integ.adaptive else {}
        params = tuple(f.parameters()) if params is None else tuple(params)
        if not integ.adaptive:
            return odeint_adjoint(f, z0, t, method=name, options=opts or None,
                                  adjoint_options=adj_opts, adjoint_params=params, **tol)
        return capped(lambda o: odeint_adjoint(f, z0, t, method=name, options=o,
                                               adjoint_options=dict(adj_opts, **o),
                                               adjoint_params=params, **tol), z0, t, name)


def _solve_checkpointed(integ, f, z0, t, every: int, kw: dict, params) -> torch.Tensor:
    params = tuple(p for p in params if p.requires_grad)
    out, z = [z0[None]], z0
    for k in range(0, len(t) - 1, every):
        seg = t[k:k + every + 1]
        zs = _Recompute.apply(lambda z_, seg_=seg: integ.solve(f, z_, seg_, **kw)[1:], z,
                              *params)
        out.append(zs)
        z = zs[-1]
    return torch.cat(out)


class _Recompute(torch.autograd.Function):
    """One checkpointed segment: ``run(z)`` without a graph in the forward pass, run again with
    a graph in the backward pass to get the vector-Jacobian products for ``z`` and ``params``.

    ``run`` may depend on tensors that require grad only through ``z`` and ``params`` (as for the
    adjoint). Unlike ``torch.utils.checkpoint`` this installs no per-tensor hooks, whose Python
    overhead more than doubled the cost of small graphs.
    """

    @staticmethod
    def forward(ctx, run, z, *params):
        ctx.run = run
        ctx.save_for_backward(z, *params)
        return run(z)

    @staticmethod
    def backward(ctx, grad_out):
        z, *params = ctx.saved_tensors
        with torch.enable_grad():
            z_in = z.detach().requires_grad_(z.requires_grad)
            out = ctx.run(z_in)
        inputs = ([z_in] if z.requires_grad else []) + params
        grads = list(torch.autograd.grad(out, inputs, grad_out, allow_unused=True))
        gz = grads.pop(0) if z.requires_grad else None
        return (None, gz, *grads)
