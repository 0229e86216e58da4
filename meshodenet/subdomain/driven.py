r"""MeshODENet's training window on a patch whose halo is driven by the ground truth.

A window of ``S`` steps of an ``s``-stage Runge-Kutta method reads ``layers x s x S`` hops
(each stage reads the previous stage's states of the neighbours), so no patch of a few hops is
exact. A driven patch (``graph_patches`` grown by ``buffer + halo_depth`` hops) splits its
nodes in two: the **solved** nodes, within ``buffer`` hops of the part (its own nodes and
``buffer`` rings), evolve by the network; the **driven** nodes beyond them (``halo_depth``
hops, the stencil of one evaluation at a solved node) follow the ground truth. The patch's
ODE is non-autonomous,

.. math::
    \dot z_S = f_S\big(z_S, z_H(t)\big), \qquad z_H(t) = [X(t), \dot X(t)],

with ``X`` the cubic Hermite interpolant of the stored frames' positions and velocities
(``Hermite``), and a fixed-step explicit Runge-Kutta method integrates it as any
non-autonomous ODE: stage ``i`` of a step from ``t`` evaluates the network at time
``t + c_i h`` on the stage's solved states and the halo's ``z_H(t + c_i h)``.

In the code the halo stays in the state ``z (2, M, 3)`` of the patch: each evaluation
overwrites the halo's entries by the interpolant before the network reads them, and returns
the interpolant's derivative ``[X', X'']`` there (``DrivenField``). The solver, its gradient
modes and the network then run unchanged on the patch. Overwriting makes the halo's states at
the stages the interpolant's whatever the scheme's stage weights; the derivative keeps the
halo's states at the step ends on the interpolant too (the 3/8 rule integrates the
quadratic ``X'`` and linear ``X''`` exactly), and the halo carries no gradient.

Only fixed-step explicit schemes (``ExplicitRK``: ``euler``, ``midpoint``, ``rk4``): an adaptive
scheme (``dopri5``) chooses its steps from an error norm over all nodes, a reduction over the
whole mesh, and an implicit one solves every step over all nodes. The ``rms`` loss takes the
root of a window's mean over all nodes, which does not split into patches; ``mse`` (with
``frame_weight``) and the release term are sums over nodes and do.
"""

from __future__ import annotations

import bisect

import numpy as np
import torch

from meshodenet.gnn import fast, reference
from meshodenet.gnn.features import graph_context
from meshodenet.gnn.network import FastField
from meshodenet.integrators.explicit import INTEGRATORS, ExplicitRK, odesolve

#: The explicit fixed-step integrators a driven patch integrates with.
DRIVEN_INTEGRATORS = tuple(k for k, v in INTEGRATORS.items() if isinstance(v, ExplicitRK))


def check_driven(config) -> None:
    """``ValueError`` naming the field unless MeshODENet's ``config`` can train on driven
    patches: a fixed-step explicit ``integrator`` and the ``mse`` loss."""
    scheme = INTEGRATORS[config.integrator]
    if not isinstance(scheme, ExplicitRK):
        why = ("adaptive: its step control reduces an error norm over every node of the batch, "
               "so a patch would take other steps than the whole mesh"
               if getattr(scheme, "adaptive", False) else
               "implicit: every step solves a system over every node of the batch")
        raise ValueError(f"MeshODENetConfig.integrator={config.integrator!r} cannot train on "
                         f"patches with a driven halo ({why}); choose one of "
                         f"{', '.join(DRIVEN_INTEGRATORS)}")
    if getattr(config, "loss", "mse") != "mse":
        raise ValueError(f"MeshODENetConfig.loss={config.loss!r} cannot train on patches: the "
                         "root of each window's mean over every node does not split into "
                         "sums over patches; choose loss='mse' (or train on the whole mesh, "
                         "patch_nodes = 0)")


class Hermite:
    """The cubic Hermite interpolant of frames at times ``t (T,)`` (s, increasing) with
    positions and velocities ``x, v (n, T, m, 3)``: per interval
    ``X(s) = x_j + h01(s) (x_{j+1} - x_j) + dt (h10(s) v_j + h11(s) v_{j+1})``,
    ``s = (t - t_j) / dt``, with the Hermite basis ``h01 = 3s^2 - 2s^3``,
    ``h10 = s^3 - 2s^2 + s``, ``h11 = s^3 - s^2`` (``h00 = 1 - h01`` folded into the
    difference, which keeps the digits of small displacements). Its error is
    ``O(dt^4)`` in ``X``, ``O(dt^3)`` in ``X'``."""

    def __init__(self, t: torch.Tensor, x: torch.Tensor, v: torch.Tensor):
        self.t = [float(s) for s in t.detach().cpu()]
        self.x, self.v = x, v
        self.dx = x[:, 1:] - x[:, :-1]

    def __call__(self, t: float):
        """``(X, X', X'')`` at time ``t``, each ``(n, m, 3)``; ``t`` outside the frames'
        times extrapolates the first or last interval's cubic."""
        j = min(max(bisect.bisect_right(self.t, t) - 1, 0), len(self.t) - 2)
        dt = self.t[j + 1] - self.t[j]
        s = (t - self.t[j]) / dt
        x0, dx, v0, v1 = self.x[:, j], self.dx[:, j], self.v[:, j], self.v[:, j + 1]
        X = x0 + (3 * s**2 - 2 * s**3) * dx + dt * ((s**3 - 2 * s**2 + s) * v0
                                                    + (s**3 - s**2) * v1)
        V = (6 * s - 6 * s**2) / dt * dx + (3 * s**2 - 4 * s + 1) * v0 + (3 * s**2 - 2 * s) * v1
        A = (6 - 12 * s) / dt**2 * dx + ((6 * s - 4) * v0 + (6 * s - 2) * v1) / dt
        return X, V, A


class DrivenField:
    """``f(t, z)`` of a driven patch (module doc): MeshODENet ``model``'s field on the
    context ``ctx`` of the patch's batch, the entries of the nodes ``driven (M,)`` (bool)
    overwritten by ``frames`` (a ``Hermite`` of the batch's ``(n, T, m, 3)`` frames,
    ``M = n m``) before the network reads them and their derivative the interpolant's.
    ``params``: the tensors it differentiates (for the checkpoint and adjoint modes)."""

    def __init__(self, model, ctx, driven: torch.Tensor, frames: Hermite):
        self.model, self.frames = model, frames
        self.free = ctx.batch.free
        self.mask = driven.reshape(1, -1, 1) if bool(driven.any()) else None
        if model.engine == "reference":
            self._f = lambda z: reference.vector_field(model, z, ctx)
            self.params = tuple(model.parameters())
        else:
            field = FastField(model, ctx)
            self._f = lambda z: fast.evaluate(field, z)
            self.params = tuple(field.sources)

    def __call__(self, t, z):
        self.model.nfe += 1
        if self.mask is None:
            return self._f(z)
        X, V, A = (y.reshape(-1, 3) for y in self.frames(float(t)))
        dz = self._f(torch.where(self.mask, torch.stack([X, V]), z))
        return torch.where(self.mask, torch.stack([V, A]) * self.free, dz)


def window_frames(data, traj, start, S: int, nodes: np.ndarray):
    """Positions and velocities ``(n, S + 1, m, 3)`` of the windows of ``S`` intervals from
    frames ``start (n,)`` of trajectories ``traj (n,)``, at the ``m`` nodes ``nodes`` only."""
    dev = data.pos.device
    frames = (start[:, None] + torch.arange(S + 1, device=dev))[:, :, None]
    at = (traj[:, None, None], frames, torch.as_tensor(nodes, device=dev)[None, None])
    return data.pos[at], data.vel[at]


def driven_windows(model, topology, driven: np.ndarray, data, traj, start, S: int,
                   nodes: np.ndarray):
    """``(pred, true)``, positions ``(n, S + 1, m, 3)``: MeshODENet ``model`` integrated with
    its integrator and gradient mode over windows of ``S`` intervals from the true frames
    ``start (n,)`` of trajectories ``traj (n,)`` on the patch of nodes ``nodes (m,)`` with the
    graph ``topology``, the nodes ``driven (m,)`` (bool) following the truth (module doc);
    and the truth there. The frames' times are ``data.t[:S + 1] - data.t[0]``, as
    ``MeshODENet.training_loss`` takes them."""
    x, v = window_frames(data, traj, start, S, nodes)
    n, m = x.shape[0], x.shape[2]
    t = (data.t[: S + 1] - data.t[0]).to(x.dtype)
    ctx = graph_context(model.stats, topology, data.youngs[traj], x.dtype)
    mask = torch.as_tensor(driven, device=x.device).repeat(n)
    f = DrivenField(model, ctx, mask, Hermite(t, x, v))
    z0 = torch.stack([x[:, 0].reshape(-1, 3), v[:, 0].reshape(-1, 3) * ctx.batch.free])
    c = model.config
    zs = odesolve(f, z0, t, c.integrator, c.grad_mode, c.substeps,
                  checkpoint_every=c.checkpoint_every, seminorm=c.seminorm, params=f.params)
    return zs[:, 0].reshape(S + 1, n, m, 3).transpose(0, 1), x
