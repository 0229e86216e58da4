r"""Implicit (stiffly stable) integrators for learned fields ``dz/dt = f(t, z)``.

Every implicit stage solves ``Y = c + g f(t_s, Y)`` (``g = gamma h``) by Newton's method on
``R(Y) = Y - c - g f(t_s, Y)``, with the Newton matrix ``A = I - g J``, ``J = df/dz`` at the
current iterate. Schemes (``IMPLICIT``), each saved interval split into ``substeps`` steps:

- ``backward_euler``: one stage, ``c = z_n``, ``g = h``; order 1, L-stable.
- ``sdirk2``: Alexander's two-stage, stiffly accurate SDIRK, ``gamma = 1 - 1/sqrt(2)``:
  ``Y1 = z_n + gamma h f(Y1)``, ``Y2 = z_n + (1 - gamma) h K1 + gamma h f(Y2)`` with
  ``K1 = (Y1 - z_n) / (gamma h)``, ``z_{n+1} = Y2``; order 2, L-stable.

Why SDIRK2 as the second-order scheme: the state ``z = (x, v)`` of a mechanical system has stiff
elastic modes (``omega h`` up to ~34 on the plate) and over-damped drag / elastic relaxation
rates (``lambda h`` up to 1e5 on the rod) that must be damped, not carried: L-stability
(``R(inf) = 0``) rules out implicit midpoint / trapezoid (``|R(inf)| = 1``: stiff modes ring
undamped). BDF2 is L-stable too but needs a history, and training windows start from any
ground-truth frame without one; TR-BDF2 starts with a trapezoid stage. SDIRK2 is one-step
(self-starting), stiffly accurate (the last stage is the step, so the stiff limit is exact),
and both stages share ``gamma`` and so the form of the Newton matrix.

Jacobian strategies (``JACOBIANS``):

- ``coloured``: the sparse ``J`` from forward-mode AD. A field computed by ``K`` message-passing
  layers on features of ``x_j - x_i`` along edges (and rod hinges) couples a node only to nodes
  within ``K + 1`` hops (``MeshCoupling``); two columns may share one JVP when their nodes are
  more than ``2 (K + 1)`` hops apart, so the distance-``2(K + 1)`` graph is coloured greedily
  and every colour and state component costs one ``torch.func.jvp``. ``A`` is factorised by
  scipy's sparse LU (float64). Without a coupling (a generic ``f``) ``J`` is dense
  (``torch.func.jacfwd``).
- ``krylov``: matrix-free Newton-Krylov: GMRES on ``A`` with one JVP per iteration; the
  transposed solve of the backward pass uses VJPs.

Gradients (``ImplicitStage``): the forward pass runs Newton without a graph; the backward pass
solves ``A^T lambda = g_Y`` at the converged ``Y`` and back-propagates once through
``g f(t_s, Y)`` for the parameters (``dL/dc = lambda``), never through Newton's iterations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch


class NewtonError(RuntimeError):
    """Newton's method did not converge within ``MAX_NEWTON`` iterations on one step."""


#: Newton iterations per stage before ``NewtonError``.
MAX_NEWTON = 25


def newton_rtol(dtype) -> float:
    """Relative tolerance of a stage's residual (``Stage.newton``) and of the transposed
    solves: 100 machine epsilons of ``dtype``."""
    return 100 * torch.finfo(dtype).eps


# --- sparsity of the field -----------------------------------------------------------------
class MeshCoupling:
    """Which nodes a field couples: node ``i`` of copy ``b`` depends on nodes of copy ``b``
    within ``hops`` edges of it. States are ``(S, n_graphs * n_nodes, C)`` with node
    ``b * n_nodes + i`` at axis 1. ``colour (n_nodes,)``: a greedy colouring of the
    distance-``2 hops`` graph (nodes of one colour share no row of ``J``)."""

    def __init__(self, senders, receivers, n_nodes: int, hops: int, n_graphs: int = 1):
        self.n_nodes, self.n_graphs, self.hops = n_nodes, n_graphs, hops
        adj = sp.coo_matrix((np.ones(len(senders)), (np.asarray(senders),
                                                     np.asarray(receivers))),
                            shape=(n_nodes, n_nodes)).tocsr()
        step = ((adj + adj.T + sp.identity(n_nodes)) > 0).astype(np.float64)
        reach = sp.identity(n_nodes, format="csr")
        for _ in range(hops):
            reach = ((reach @ step) > 0).astype(np.float64)
        self.pattern = reach.tocoo()  # (i, j): J_ij may be nonzero
        self.colour = greedy_colouring(((reach @ reach) > 0).tocsr())
        self.n_colours = int(self.colour.max()) + 1 if n_nodes else 0


def greedy_colouring(conflict: sp.csr_matrix) -> np.ndarray:
    """Colours ``(n,)``: each node the smallest colour none of its conflict-neighbours has,
    nodes in order of decreasing degree (Welsh-Powell)."""
    n = conflict.shape[0]
    colour = np.full(n, -1, np.int64)
    for i in np.argsort(-np.diff(conflict.indptr), kind="stable"):
        used = set(colour[conflict.indices[conflict.indptr[i]:conflict.indptr[i + 1]]])
        c = 0
        while c in used:
            c += 1
        colour[i] = c
    return colour


#: JVPs per vectorised call of ``coloured_jacobian`` (bounds its memory).
JVP_CHUNK = 64


@torch.no_grad()
def coloured_jacobian(fz, Y: torch.Tensor, cp: MeshCoupling) -> sp.csr_matrix:
    """``J = dfz/dz`` at ``Y (S, M, C)`` as a scipy CSR ``(S M C, S M C)``: one forward-mode
    JVP per colour and state component (``torch.func.vmap`` over them), entries placed by
    the coupling pattern."""
    S, M, C = Y.shape
    N, B = cp.n_nodes, cp.n_graphs
    col = torch.as_tensor(np.tile(cp.colour, B), device=Y.device)
    seeds = (col[None] == torch.arange(cp.n_colours, device=Y.device)[:, None]).to(Y.dtype)
    tangents = torch.zeros((cp.n_colours, S, C, S, M, C), dtype=Y.dtype, device=Y.device)
    for s in range(S):
        for c in range(C):
            tangents[:, s, c, s, :, c] = seeds
    # all JVPs in one vectorised call: an order of magnitude faster than a loop of them
    jvp = lambda u: torch.func.jvp(fz, (Y,), (u,))[1]
    outs = torch.func.vmap(jvp, chunk_size=JVP_CHUNK)(tangents.reshape(-1, S, M, C))
    outs = outs.reshape(cp.n_colours, S, C, S, M, C).double().cpu()
    i = (cp.pattern.row[None] + N * np.arange(B)[:, None]).reshape(-1)
    j = (cp.pattern.col[None] + N * np.arange(B)[:, None]).reshape(-1)
    vals = outs[torch.as_tensor(np.tile(cp.colour, B)[j]), :, :, :, torch.as_tensor(i), :]
    # vals (nnz, s, c, s', c'): J[(s', i, c'), (s, j, c)]
    s_, c_, s2, c2 = np.meshgrid(np.arange(S), np.arange(C), np.arange(S), np.arange(C),
                                 indexing="ij")
    rows = (s2[None] * M + i[:, None, None, None, None]) * C + c2[None]
    cols = (s_[None] * M + j[:, None, None, None, None]) * C + c_[None]
    n = S * M * C
    return sp.csr_matrix((vals.numpy().reshape(-1), (rows.reshape(-1), cols.reshape(-1))),
                         shape=(n, n))


# --- linear solvers for A = I - g J --------------------------------------------------------
class DirectSystem:
    """``A = I - g J`` with ``J`` assembled (coloured sparse, or dense without a coupling)
    and factorised once; ``solve`` and ``solve_t`` (transposed) in ``Y``'s dtype."""

    def __init__(self, fz, Y: torch.Tensor, g: float, coupling: MeshCoupling | None):
        self.shape, self.dtype = Y.shape, Y.dtype
        n = Y.numel()
        if coupling is not None and Y.dim() == 3:
            A = sp.identity(n, format="csc") - g * coloured_jacobian(fz, Y, coupling).tocsc()
            self.lu = spla.splu(A.tocsc())
            self.dense = None
        else:
            with torch.no_grad():
                J = torch.func.jacfwd(lambda y: fz(y.reshape(Y.shape)).reshape(-1))(
                    Y.detach().reshape(-1))
            self.dense = torch.eye(n, dtype=torch.float64) - g * J.double().cpu()
            self.lu = None

    def _solve(self, b: torch.Tensor, trans: bool) -> torch.Tensor:
        rhs = b.detach().reshape(-1).double().cpu()
        if self.lu is not None:
            x = torch.from_numpy(self.lu.solve(rhs.numpy(), trans="T" if trans else "N"))
        else:
            x = torch.linalg.solve(self.dense.T if trans else self.dense, rhs)
        return x.to(device=b.device, dtype=self.dtype).reshape(self.shape)

    def solve(self, b):
        return self._solve(b, False)

    def solve_t(self, b):
        return self._solve(b, True)


class KrylovSystem:
    """``A = I - g J`` matrix-free: GMRES with one JVP (``solve``) or VJP (``solve_t``) per
    iteration, to relative residual ``rtol``."""

    def __init__(self, fz, Y: torch.Tensor, g: float, rtol: float):
        self.fz, self.Y, self.g, self.rtol = fz, Y.detach(), g, rtol

    @torch.no_grad()
    def solve(self, b):
        jvp = lambda u: u - self.g * torch.func.jvp(self.fz, (self.Y,), (u,))[1]
        return gmres(jvp, b.detach(), self.rtol)

    @torch.no_grad()
    def solve_t(self, b):
        _, vjp_fn = torch.func.vjp(self.fz, self.Y)
        return gmres(lambda u: u - self.g * vjp_fn(u)[0], b.detach(), self.rtol)


def gmres(op, b: torch.Tensor, rtol: float, restart: int = 60, max_restarts: int = 10):
    """``x`` with ``|op(x) - b| <= rtol |b|`` by restarted GMRES (modified Gram-Schmidt,
    the small least-squares problem solved afresh in float64 each iteration)."""
    x = torch.zeros_like(b)
    bnorm = float(b.norm())
    if bnorm == 0:
        return x
    for _ in range(max_restarts):
        r = b - op(x)
        beta = float(r.norm())
        if beta <= rtol * bnorm:
            return x
        V, H = [r / beta], torch.zeros(restart + 1, restart, dtype=torch.float64)
        e1 = torch.zeros(restart + 1, dtype=torch.float64)
        e1[0] = beta
        for j in range(restart):
            w = op(V[j])
            for i in range(j + 1):
                H[i, j] = float((w * V[i]).sum())
                w = w - float(H[i, j]) * V[i]
            H[j + 1, j] = float(w.norm())
            y = torch.linalg.lstsq(H[:j + 2, :j + 1], e1[:j + 2, None]).solution[:, 0]
            res = float((H[:j + 2, :j + 1] @ y - e1[:j + 2]).norm())
            if res <= rtol * bnorm or H[j + 1, j] <= 1e-300:
                break
            V.append(w / H[j + 1, j])
        x = x + sum(float(y[i]) * V[i] for i in range(len(y)))
    return x


JACOBIANS = ("coloured", "krylov")


def linear_system(fz, Y, g: float, jacobian: str, coupling, rtol: float):
    if jacobian == "coloured":
        return DirectSystem(fz, Y, g, coupling)
    if jacobian == "krylov":
        return KrylovSystem(fz, Y, g, rtol)
    raise ValueError(f"unknown jacobian {jacobian!r}; valid: {', '.join(JACOBIANS)}")


# --- one implicit stage --------------------------------------------------------------------
@dataclass
class Stage:
    """The stage equation ``Y = c + g f(t, Y)`` of step ``step`` (saved interval, substep) of
    scheme ``name``; ``coupling`` and ``jacobian`` choose the linear solver."""

    f: object
    t: float
    g: float
    name: str
    step: tuple
    jacobian: str
    coupling: MeshCoupling | None

    def fz(self, y):
        return self.f(self.t, y)

    def system(self, Y, rtol):
        return linear_system(self.fz, Y, self.g, self.jacobian, self.coupling, rtol)

    @torch.no_grad()
    def newton(self, c: torch.Tensor, guess: torch.Tensor) -> torch.Tensor:
        """The converged ``Y``; ``NewtonError`` after ``MAX_NEWTON`` iterations or on a
        non-finite residual.

        Newton runs on the increment ``D = Y - c``, ``R = D - g f(c + D)``, so that the
        tolerance is relative to the step's change (``|D| + g |f|``), not to the state (a
        plate's positions are 1e4 times its motion per step). Converged: ``|R|`` below
        ``newton_rtol``; or below ``sqrt`` of it and no longer halving (the float round-off
        of ``f(c + D)`` is then the limit, e.g. a stiff field in float32)."""
        c = c.detach()
        D = guess.detach() - c
        rtol = newton_rtol(c.dtype)
        r_prev = math.inf
        for _ in range(MAX_NEWTON + 1):
            Y = c + D
            F = self.fz(Y)
            R = D - self.g * F
            scale = float(D.abs().max()) + self.g * float(F.abs().max())
            r = float(R.abs().max())
            if not math.isfinite(r):
                break
            if r <= rtol * scale or (r <= math.sqrt(rtol) * scale and r > 0.5 * r_prev):
                return Y
            D = D - self.system(Y, math.sqrt(rtol)).solve(R)
            r_prev = r
        raise self.error(R, rtol * scale)

    def error(self, R: torch.Tensor, tol: float) -> NewtonError:
        k, s = self.step
        B = self.coupling.n_graphs if self.coupling is not None else 1
        per = R.abs().reshape(R.shape[0], B, -1).amax(dim=(0, 2)) if R.dim() == 3 \
            else R.abs().reshape(1, -1).amax(dim=1)
        worst = int(torch.nan_to_num(per, nan=math.inf).argmax())
        return NewtonError(
            f"{self.name}: Newton did not converge on step {k} (substep {s}, stage time "
            f"t={self.t:.6g}) within {MAX_NEWTON} iterations: max |residual| "
            f"{float(R.abs().max()):.3e} > tolerance {tol:.3e}, worst in trajectory {worst} "
            f"of the batch ({float(per[worst]):.3e}); the field is too stiff or not smooth "
            "there: use more substeps or a smaller learning rate")


class ImplicitStage(torch.autograd.Function):
    """``Y`` solving ``Y = c + g f(t, Y)``, differentiable in ``c`` and ``params`` by the
    implicit function theorem: ``dL/dc = lambda`` with ``(I - g J)^T lambda = dL/dY`` and
    ``dL/dparams = (g df/dparams)^T lambda``, one VJP through ``g f(t, Y)``."""

    @staticmethod
    def forward(ctx, stage, c, guess, *params):
        Y = stage.newton(c, guess)
        ctx.stage = stage
        ctx.save_for_backward(Y, *params)
        return Y

    @staticmethod
    def backward(ctx, gY):
        Y, *params = ctx.saved_tensors
        st = ctx.stage
        lam = st.system(Y, newton_rtol(Y.dtype)).solve_t(gY)
        grads = ()
        if params:
            with torch.enable_grad():
                out = st.fz(Y.detach())
            grads = torch.autograd.grad(out, params, st.g * lam, allow_unused=True)
        return (None, lam, None, *grads)


# --- the schemes ---------------------------------------------------------------------------
#: The Jacobian strategy of ``ImplicitScheme.solve`` by default (measured: docs/TRAINING.md).
DEFAULT_JACOBIAN = "krylov"
_GAMMA = 1.0 - 1.0 / math.sqrt(2.0)


@dataclass(frozen=True)
class ImplicitScheme:
    """``backward_euler`` (1 stage) or ``sdirk2`` (2 stages), see the module docstring."""

    id: str
    order: int
    adaptive = False
    implicit = True

    def step(self, f, t: float, h: float, z, params, where: tuple, jacobian, coupling):
        def stage(c, g, ts, guess):
            st = Stage(f, ts, g, self.id, where, jacobian, coupling)
            if params and torch.is_grad_enabled():
                return ImplicitStage.apply(st, c, guess, *params)
            if torch.is_grad_enabled() and c.requires_grad:
                return ImplicitStage.apply(st, c, guess)
            return st.newton(c, guess)

        if self.id == "backward_euler":
            return stage(z, h, t + h, z)
        g = _GAMMA * h
        Y1 = stage(z, g, t + g, z)
        K1 = (Y1 - z) / g
        return stage(z + (h - g) * K1, g, t + h, z + h * K1)

    def solve(self, f, z0, t, substeps: int = 1, params=None, jacobian: str | None = None,
              **_):
        """States at the times ``t (T,)``: ``(T, *z0.shape)``. ``params``: the tensors ``f``
        depends on that get gradients (default: ``f.parameters()`` for a module);
        ``f.coupling()``, when ``f`` has it, gives the ``MeshCoupling``."""
        if params is None:
            params = tuple(f.parameters()) if isinstance(f, torch.nn.Module) else ()
        params = tuple(p for p in params if p.requires_grad)
        coupling = f.coupling() if hasattr(f, "coupling") else None
        jacobian = jacobian or DEFAULT_JACOBIAN
        zs, z = [z0], z0
        for k in range(len(t) - 1):
            h = float(t[k + 1] - t[k]) / substeps
            for s in range(substeps):
                z = self.step(f, float(t[k]) + s * h, h, z, params, (k, s), jacobian, coupling)
            zs.append(z)
        return torch.stack(zs)


IMPLICIT = {"backward_euler": ImplicitScheme("backward_euler", 1),
            "sdirk2": ImplicitScheme("sdirk2", 2)}
