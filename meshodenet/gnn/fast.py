"""The fast path of MeshODENet's rollouts: fixed-step Runge-Kutta rollouts of the network's
vector field (``meshodenet.gnn.network.FastField``) and their gradients, and one evaluation as an
autograd function, all with the hand-written backward pass of ``meshodenet.gnn.network``.

- No autograd bookkeeping per evaluation: a rollout is one ``torch.autograd.Function`` whose
  forward runs without a graph and keeps the state at every saved interval; its backward
  recomputes each interval's stages, keeping their activations, and applies the hand-written
  vector-Jacobian product of the field and of the Runge-Kutta step, accumulating the weight
  gradients in preallocated buffers. The effective weights are differentiable functions of the
  module parameters built once per rollout, so autograd maps their gradients back.

Used by ``MeshODENet`` (config ``engine = "fast"``, the default) for fixed-step integrators with
the ``direct`` and ``checkpoint`` gradient modes (same gradient as those, memory of one
interval's activations) and for rollouts without gradients; ``adjoint`` and ``dopri5`` use the
reference solvers (``meshodenet.gnn.reference.integrate``) with this field. Same numbers as
``meshodenet.gnn.reference`` up to float round-off, tested in float64 (``tests/test_fast.py``).
"""

from __future__ import annotations

import torch

from meshodenet.gnn.network import FastField

# --- autograd wrappers ------------------------------------------------------------------------
#: A training rollout keeps the activations of every evaluation (no recomputation in the
#: backward pass) when they take at most this many bytes on the CPU (``tape_budget``);
#: otherwise it keeps the state at every saved time and recomputes one interval at a time.
#: The gradient is the same either way.
TAPE_BUDGET_BYTES = 384 * 2**20
#: On a GPU, the share of the device's free memory a rollout's activations may take: its
#: memory is the GPU's own (not the shared machine's), and recomputation costs a second
#: forward pass of kernel launches.
TAPE_GPU_FRACTION = 0.25


def tape_budget(device: torch.device) -> int:
    """Bytes of activations a training rollout on ``device`` keeps (see ``TAPE_BUDGET_BYTES``):
    that constant on the CPU, ``TAPE_GPU_FRACTION`` of the free memory on a CUDA device."""
    if device.type != "cuda":
        return TAPE_BUDGET_BYTES
    free, _ = torch.cuda.mem_get_info(device)
    return max(TAPE_BUDGET_BYTES, int(TAPE_GPU_FRACTION * free))
#: Intervals whose deferred weight-gradient products are summed in one matmul.
FLUSH_EVERY = 4


def _tape_bytes(tapes) -> int:
    seen, total = set(), 0
    for tape in tapes:
        for t in tape:
            if id(t) not in seen:
                seen.add(id(t))
                total += t.numel() * t.element_size()
    return total


class _FieldFn(torch.autograd.Function):
    """One evaluation ``f(z)`` with the hand-written backward."""

    @staticmethod
    def forward(ctx, field, z, *sources):
        tape: list = []
        out = field.forward(field.params, z, tape)
        ctx.field, ctx.tape = field, tape
        return out

    @staticmethod
    def backward(ctx, g):
        field = ctx.field
        G = field.new_grads()
        gz = field.backward(field.params, G, list(ctx.tape), g.contiguous())
        return (None, gz, *field.source_grads(G))


def evaluate(field: FastField, z: torch.Tensor) -> torch.Tensor:
    """``f(z)``, differentiable w.r.t. ``z`` and the parameters when autograd records."""
    if torch.is_grad_enabled() and (z.requires_grad or field.requires_grad()):
        return _FieldFn.apply(field, z, *field.sources)
    with torch.no_grad():
        return field.forward(field.params, z)


def _rk_step(field, P, scheme, z, h, tapes=None):
    """One explicit Runge-Kutta step (as ``ExplicitRK.step``); with ``tapes`` (a list), each
    stage's tape is appended to it."""
    field.model.nfe += len(scheme.a)
    ks = []
    for a in scheme.a:
        zs = z
        for a_r, k in zip(a, ks, strict=True):
            if a_r:
                zs = torch.add(zs, k, alpha=h * a_r)
        if tapes is None:
            ks.append(field.forward(P, zs))
        else:
            tape: list = []
            ks.append(field.forward(P, zs, tape))
            tapes.append(tape)
    dz = None
    for b, k in zip(scheme.b, ks, strict=True):
        if b:
            dz = k * b if dz is None else torch.add(dz, k, alpha=b)
    return torch.add(z, dz, alpha=h)


def _rk_vjp(field, P, G, scheme, tapes, h, gz_next):
    """Gradient w.r.t. the start of one step from that w.r.t. its end (consumes ``tapes``)."""
    g_k = [gz_next * (h * b) if b else None for b in scheme.b]
    gz = gz_next.clone()
    for s in range(len(g_k) - 1, -1, -1):
        if g_k[s] is None:
            continue
        g_zs = field.backward(P, G, tapes[s], g_k[s])
        gz.add_(g_zs)
        for r, a_r in enumerate(scheme.a[s]):
            if a_r:
                g_k[r] = g_zs * (h * a_r) if g_k[r] is None else g_k[r].add_(g_zs,
                                                                           alpha=h * a_r)
    return gz


def _steps(t, substeps):
    """Step sizes as Python floats (the reference forms ``h`` as a 0-dim tensor in the dtype of
    ``t``: the same value, rounded to that dtype). Computed from a CPU copy of ``t``: the same
    arithmetic, without a device synchronisation per step on a GPU."""
    t = t.detach().cpu()
    return [float((t[k + 1] - t[k]) / substeps) for k in range(len(t) - 1)]


def _solve(field, scheme, z0, t, substeps, keep_tapes=False):
    """States ``(T, ...)`` at ``t`` and, when ``keep_tapes`` and they fit in
    ``tape_budget``, the tapes of every step (else ``None``)."""
    P = field.params
    zs, z = [z0], z0
    steps = _steps(t, substeps)
    n_steps = len(steps) * substeps
    kept = [] if keep_tapes else None
    budget = tape_budget(z0.device) if keep_tapes else 0
    for h in steps:
        for _ in range(substeps):
            if kept is None:
                z = _rk_step(field, P, scheme, z, h)
                continue
            tapes: list = []
            z = _rk_step(field, P, scheme, z, h, tapes)
            kept.append(tapes)
            if len(kept) == 1 and _tape_bytes(tapes) * n_steps > budget:
                kept = None
        zs.append(z)
    return torch.stack(zs), kept


class _RolloutFn(torch.autograd.Function):
    """A fixed-step rollout ``(T, 2, M, 3)``: forward without an autograd graph, keeping the
    states at the saved times (and the activations when they fit); backward walks the steps in
    reverse with the hand-written vector-Jacobian products."""

    @staticmethod
    def forward(ctx, field, scheme, t, substeps, z0, *sources):
        out, kept = _solve(field, scheme, z0, t, substeps, keep_tapes=True)
        ctx.field, ctx.scheme, ctx.t, ctx.substeps, ctx.kept = field, scheme, t, substeps, kept
        ctx.save_for_backward(out)
        return out

    @staticmethod
    def backward(ctx, g_out):
        (out,) = ctx.saved_tensors
        field, scheme, substeps, kept = ctx.field, ctx.scheme, ctx.substeps, ctx.kept
        ctx.kept = None
        P = field.params
        G = field.new_grads()
        steps = _steps(ctx.t, substeps)
        gz = g_out[-1].clone()
        for k in range(len(steps) - 1, -1, -1):
            h = steps[k]
            if kept is not None:
                for j in range(substeps - 1, -1, -1):
                    tapes, kept[k * substeps + j] = kept[k * substeps + j], None
                    gz = _rk_vjp(field, P, G, scheme, tapes, h, gz)
            else:
                subs = [out[k]]
                for _ in range(substeps - 1):
                    subs.append(_rk_step(field, P, scheme, subs[-1], h))
                for zk in reversed(subs):
                    tapes: list = []
                    _rk_step(field, P, scheme, zk, h, tapes)
                    gz = _rk_vjp(field, P, G, scheme, tapes, h, gz)
            gz = gz + g_out[k]
            if k % FLUSH_EVERY == 0:
                field.flush(G)
        return (None, None, None, None, gz, *field.source_grads(G))


def rollout(field: FastField, scheme, z0: torch.Tensor, t: torch.Tensor,
            substeps: int = 1) -> torch.Tensor:
    """States ``(T, 2, M, 3)`` at times ``t`` of the fixed-step ``scheme``
    (``meshodenet.integrators.explicit.ExplicitRK``), differentiable when autograd records."""
    if torch.is_grad_enabled() and (z0.requires_grad or field.requires_grad()):
        return _RolloutFn.apply(field, scheme, t, substeps, z0, *field.sources)
    with torch.no_grad():
        return _solve(field, scheme, z0, t, substeps)[0]
