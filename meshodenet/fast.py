"""The fast path of MeshODENet: its vector field, fixed-step Runge-Kutta rollouts and their
gradients, computed with hand-written forward and backward passes on plain tensors.

Same numbers as ``meshodenet.reference`` (today's module-by-module implementation) up to float
round-off, tested in float64 (``tests/test_fast.py``). Why it is faster (docs/TRAINING.md has
the profile):

- Everything that does not depend on the state is built once per rollout (``FastField``): the
  graph's index tensors; the normalised static features are folded into the first layers of
  the encoders (``W [s | f] + b = W_d f + c`` with the per-row constant ``c = W_s s + b``), the
  acceleration de-normalisation into the decoder's last layer.
- Concatenations are replaced by split weight matrices: the edge MLP's first layer on
  ``[e, h_i, h_j]`` becomes ``W_e e + (W_s h)_i + (W_r h)_j``, with ``W_s h`` and ``W_r h``
  computed on the nodes (fewer rows than edges) and gathered with one index; the node MLP's on
  ``[h, sum e]`` becomes ``W_h h + W_a sum e``.
- No autograd bookkeeping per evaluation: a rollout is one ``torch.autograd.Function`` whose
  forward runs without a graph and keeps the state at every saved interval; its backward
  recomputes each interval's stages, keeping their activations, and applies the hand-written
  vector-Jacobian product of the field and of the Runge-Kutta step, accumulating the weight
  gradients in preallocated buffers. The effective weights are differentiable functions of the
  module parameters built once per rollout, so autograd maps their gradients back.

Used by ``MeshODENet`` (``engine = "fast"``, the default) for fixed-step integrators with the
``direct`` and ``checkpoint`` gradient modes (same gradient as those, memory of one interval's
activations) and for rollouts without gradients; ``adjoint`` and ``dopri5`` use the reference
solvers with this field.
"""

from __future__ import annotations

import torch

from meshodenet.features import NODE_STATIC


# --- activations ------------------------------------------------------------------------------
def _act_fwd(name: str, pre: torch.Tensor):
    """``(out, saved)``: the activation and what its backward needs."""
    if name == "relu":
        out = torch.relu_(pre)
        return out, out
    if name == "tanh":
        out = torch.tanh_(pre)
        return out, out
    return torch.nn.functional.silu(pre), pre


def _act_bwd(name: str, g: torch.Tensor, saved: torch.Tensor) -> torch.Tensor:
    if name == "relu":
        return torch.ops.aten.threshold_backward(g, saved, 0)
    if name == "tanh":
        return g * (1 - saved * saved)
    s = torch.sigmoid(saved)
    return g * (s * (1 + saved * (1 - s)))


def _linears(seq) -> list:
    return [m for m in seq if isinstance(m, torch.nn.Linear)]


class FastField:
    """The vector field of ``model`` on one ``GraphContext``, ready to be evaluated many times.

    ``params`` is the list of effective weights (differentiable functions of the model's
    parameters when autograd records); ``layout`` says where each MLP's weights sit in it.
    """

    def __init__(self, model, ctx):
        gnn = model.gnn
        self.act = model.config.activation
        b = ctx.batch
        self.kind = ctx.kind
        self.M, self.D = b.n_nodes, len(b.senders)
        self.free, self.force, self.damping = b.free, b.force, b.damping
        self.senders, self.receivers = b.senders, b.receivers
        M = self.M
        self.idx_sr = torch.cat([2 * b.senders, 2 * b.receivers + 1])
        self.hinge_all = b.hinges.t().reshape(-1) if self.kind == "line" else None
        self.hinge_mid = b.hinges[:, 1] if self.kind == "line" else None
        self.H = len(b.hinges) if self.kind == "line" else 0
        dtype, dev = ctx.node_static.dtype, ctx.node_static.device
        if self.kind == "line":
            base = torch.zeros(M, 2, dtype=dtype, device=dev)
            base[:, 0] = 1.0
            self.cs_base = base
            rot = torch.zeros(3, 6, dtype=dtype, device=dev)  # e2 -> [e2, (e2_y, -e2_x, 0)]
            rot[0, 0] = rot[1, 1] = rot[2, 2] = 1.0
            rot[1, 3], rot[0, 4] = 1.0, -1.0
            self.rot = rot
        P: list = []

        def add(t):
            P.append(t)
            return len(P) - 1

        def mlp(seq, first=None, last=None):
            lins = _linears(seq)
            out = []
            for k, lin in enumerate(lins):
                W, bias = lin.weight, lin.bias
                if k == 0 and first is not None:
                    W, bias = first(W, bias)
                    out.append((add(W), add(bias)))
                    continue
                if k == len(lins) - 1 and last is not None:
                    W, bias = last(W, bias)
                    out.append((add(W), add(bias)))
                    continue
                out.append((add(W.t()), add(bias)))
            return out

        s = NODE_STATIC[self.kind]

        def fold(static, n_static):
            def first(W, bias):
                return W[:, n_static:].t(), static @ W[:, :n_static].t() + bias
            return first

        def dec_last(W, bias):
            return (W * ctx.acc_std[:, None]).t(), bias * ctx.acc_std + ctx.acc_mean

        self.node_enc = mlp(gnn.node_encoder, fold(ctx.node_static, s))
        self.edge_enc = mlp(gnn.edge_encoder, fold(ctx.edge_static, ctx.edge_static.shape[1]))
        self.node_mean, self.node_std = ctx.node_mean, ctx.node_std
        self.edge_mean, self.edge_std = ctx.edge_mean, ctx.edge_std
        self.layers = []
        for layer in gnn.processor:
            el, nl = _linears(layer.edge_mlp), _linears(layer.node_mlp)
            d = el[0].weight.shape[0]
            W1, b1 = el[0].weight, el[0].bias
            e_first = (add(W1[:, :d].t()), add(torch.cat([W1[:, d:2 * d], W1[:, 2 * d:]]).t()),
                       add(torch.cat([b1, torch.zeros_like(b1)])))
            Wn = nl[0].weight
            n_first = (add(Wn[:, :d].t()), add(Wn[:, d:].t()), add(nl[0].bias))
            rest_e = [(add(m.weight.t()), add(m.bias)) for m in el[1:]]
            rest_n = [(add(m.weight.t()), add(m.bias)) for m in nl[1:]]
            self.layers.append((e_first, rest_e, n_first, rest_n, d))
        self.decoder = mlp(gnn.decoder, last=dec_last)
        self.params = P

    # --- forward ----------------------------------------------------------------------------
    def _mlp_fwd(self, P, layers, x, pre0, tape):
        """Layers ``layers`` from input ``x`` (or from the first pre-activation ``pre0``)."""
        n = len(layers)
        for k, (w, b) in enumerate(layers):
            if k == 0 and pre0 is not None:
                pre = pre0
            else:
                if tape is not None:
                    tape.append(x)
                pre = torch.addmm(P[b], x, P[w])
            if k < n - 1:
                x, saved = _act_fwd(self.act, pre)
                if tape is not None:
                    tape.append(saved)
            else:
                x = pre
        return x

    def _features(self, x, vf, tape):
        fext = torch.addcmul(self.force, self.damping, vf, value=-1.0)
        if self.kind == "line":
            if self.H:
                xh = x.index_select(0, self.hinge_all).view(3, self.H, 3)
                e = xh[1:] - xh[:-1]  # (2, H, 3): e1, e2
                n = e.norm(dim=-1)  # (2, H)
                r = (n[0] * n[1]).clamp_min(1e-30)
                e2r = torch.mm(e[1], self.rot).view(self.H, 2, 3)
                num = (e[0].unsqueeze(1) * e2r).sum(-1)  # (H, 2): dot, cross_z
                cs_h = num / r.unsqueeze(1)
                cs = self.cs_base.index_copy(0, self.hinge_mid, cs_h)
                if tape is not None:
                    tape += [e, n, r, e2r, cs_h]
            else:
                cs = self.cs_base
            F = torch.cat([vf, cs, fext], 1)
        else:
            F = torch.cat([vf, fext], 1)
        vec = x.index_select(0, self.receivers) - x.index_select(0, self.senders)
        length = vec.norm(dim=-1, keepdim=True)
        lc = length.clamp_min(1e-30)
        Fe = torch.cat([length, vec / lc], 1)
        if tape is not None:
            tape += [length, lc, Fe]
        # normalised as in GraphContext.inputs (the means are not folded into the weights:
        # in float32 that cancels digits when a feature's mean is large against its std)
        return (F - self.node_mean) / self.node_std, (Fe - self.edge_mean) / self.edge_std

    def forward(self, P, z, tape=None):
        """``dz/dt`` ``(2, M, 3)`` for ``z = [x, v]``; when ``tape`` (a list) is given, what the
        backward pass needs is appended to it."""
        x, v = z[0], z[1]
        vf = v * self.free
        F, Fe = self._features(x, vf, tape)
        h = self._mlp_fwd(P, self.node_enc, F, None, tape)
        e = self._mlp_fwd(P, self.edge_enc, Fe, None, tape)
        M = self.M
        for e_first, rest_e, n_first, rest_n, d in self.layers:
            we, wsr, bsr = e_first
            hsr = torch.addmm(P[bsr], h, P[wsr]).view(2 * M, d)
            g = hsr.index_select(0, self.idx_sr).view(2, -1, d)
            pre = torch.addmm(g[0] + g[1], e, P[we])
            if tape is not None:
                tape += [h, e]
            m = self._mlp_fwd(P, [(None, None)] + rest_e, None, pre, tape)
            e = e + m
            agg = e.new_zeros(M, d).index_add_(0, self.receivers, e)
            wh, wa, bn = n_first
            pre = torch.addmm(torch.addmm(P[bn], h, P[wh]), agg, P[wa])
            if tape is not None:
                tape.append(agg)
            h = h + self._mlp_fwd(P, [(None, None)] + rest_n, None, pre, tape)
        a = self._mlp_fwd(P, self.decoder, h, None, tape) * self.free
        return torch.stack([vf, a])

    # --- backward ---------------------------------------------------------------------------
    def _mlp_bwd(self, P, G, layers, tape, g, first_given):
        """Backward through ``layers`` (pops ``tape``); returns the gradient of the input, or
        of the first pre-activation when ``first_given``."""
        n = len(layers)
        for k in range(n - 1, -1, -1):
            if k < n - 1:
                g = _act_bwd(self.act, g, tape.pop())
            if k == 0 and first_given:
                return g
            w, b = layers[k]
            x = tape.pop()
            G[w].addmm_(x.t(), g)
            if G[b].dim() == 1:
                G[b].add_(g.sum(0))
            else:
                G[b].add_(g)
            g = torch.mm(g, P[w].t())
        return g

    def backward(self, P, G, tape, gz):
        """Vector-Jacobian product of ``forward`` (consumes ``tape``): returns ``g_z`` and adds
        the weight gradients into ``G`` (one buffer per entry of ``P``)."""
        M = self.M
        g_vf = gz[0].clone()
        g_a = gz[1] * self.free
        g_h = self._mlp_bwd(P, G, self.decoder, tape, g_a, False)
        g_e = None
        for e_first, rest_e, n_first, rest_n, d in reversed(self.layers):
            # h_out = h + node_mlp(pre_n), pre_n = bn + h Wh + agg Wa
            g_pre = self._mlp_bwd(P, G, [(None, None)] + rest_n, tape, g_h, True)
            agg = tape.pop()
            wh, wa, bn = n_first
            G[wa].addmm_(agg.t(), g_pre)
            G[bn].add_(g_pre.sum(0))
            g_agg = torch.mm(g_pre, P[wa].t())
            g_hin = g_h + torch.mm(g_pre, P[wh].t())
            g_pre_n = g_pre
            # e_out = e_in + m; agg = scatter(e_out); gradient of e_out:
            g_eout = g_agg.index_select(0, self.receivers)
            if g_e is not None:
                g_eout = g_eout + g_e
            g_pre = self._mlp_bwd(P, G, [(None, None)] + rest_e, tape, g_eout, True)
            e_in, h_in = tape.pop(), tape.pop()
            G[wh].addmm_(h_in.t(), g_pre_n)
            we, wsr, bsr = e_first
            G[we].addmm_(e_in.t(), g_pre)
            g_e = g_eout + torch.mm(g_pre, P[we].t())
            g_hsr = g_pre.new_zeros(2 * M, d).index_add_(
                0, self.idx_sr, g_pre.unsqueeze(0).expand(2, -1, -1).reshape(-1, d)).view(M, 2 * d)
            G[wsr].addmm_(h_in.t(), g_hsr)
            G[bsr].add_(g_hsr.sum(0))
            g_h = g_hin + torch.mm(g_hsr, P[wsr].t())
        if g_e is None:
            g_e = torch.zeros(self.D, P[self.edge_enc[-1][0]].shape[1], dtype=gz.dtype,
                              device=gz.device)
        g_Fe = self._mlp_bwd(P, G, self.edge_enc, tape, g_e, False) / self.edge_std
        g_F = self._mlp_bwd(P, G, self.node_enc, tape, g_h, False) / self.node_std
        g_x = self._features_bwd(tape, g_F, g_Fe, g_vf)
        return torch.stack([g_x, g_vf * self.free])

    def _features_bwd(self, tape, g_F, g_Fe, g_vf):
        """Gradient w.r.t. ``x`` of the features; adds the velocity part into ``g_vf``."""
        Fe, lc, length = tape.pop(), tape.pop(), tape.pop()
        d = Fe[:, 1:]
        g_d = g_Fe[:, 1:]
        # length = |vec|, d = vec / max(length, 1e-30)
        g_vec = (g_Fe[:, :1] * (length > 0)) * d \
            + (g_d - (g_d * d).sum(-1, keepdim=True) * d * (length > 1e-30)) / lc
        g_x = torch.zeros_like(g_vf)
        g_x.index_add_(0, self.receivers, g_vec).index_add_(0, self.senders, -g_vec)
        # node features: [vf, cs, fext] (line) or [vf, fext]; fext = force - damping vf
        g_vf.add_(g_F[:, :3])
        g_vf.addcmul_(self.damping, g_F[:, -3:], value=-1.0)
        if self.kind == "line" and self.H:
            cs_h, e2r, r, n, e = tape.pop(), tape.pop(), tape.pop(), tape.pop(), tape.pop()
            g_cs = g_F.index_select(0, self.hinge_mid)[:, 3:5]  # (H, 2)
            g_num = g_cs / r.unsqueeze(1)
            g_r = -(g_cs * cs_h).sum(-1) / r * (r > 1e-30)
            e1, e2 = e[0], e[1]
            # num = [e1.e2, e1.rot(e2)], rot(e2) = (e2_y, -e2_x, 0)
            g_e1 = (g_num.unsqueeze(-1) * e2r).sum(1)
            ge_rot = g_num[:, 1:2] * e1  # gradient w.r.t. rot(e2), mapped back by rot^T
            g_e2 = g_num[:, :1] * e1 + torch.mm(ge_rot, self.rot[:, 3:].t())
            # r = n1 n2, dn/de = e / n
            n1, n2 = n[0].clamp_min(1e-300), n[1].clamp_min(1e-300)
            g_e1 = g_e1 + (g_r * n[1] / n1).unsqueeze(1) * e1
            g_e2 = g_e2 + (g_r * n[0] / n2).unsqueeze(1) * e2
            ge = torch.stack([-g_e1, g_e1 - g_e2, g_e2]).view(-1, 3)
            g_x.index_add_(0, self.hinge_all, ge)
        return g_x


# --- autograd wrappers ------------------------------------------------------------------------
class _FieldFn(torch.autograd.Function):
    """One evaluation ``f(z)`` with the hand-written backward."""

    @staticmethod
    def forward(ctx, field, z, *P):
        tape: list = []
        out = field.forward(P, z, tape)
        ctx.field, ctx.tape = field, tape
        ctx.save_for_backward(*P)
        return out

    @staticmethod
    def backward(ctx, g):
        P = ctx.saved_tensors
        G = [torch.zeros_like(p) for p in P]
        gz = ctx.field.backward(P, G, list(ctx.tape), g.contiguous())
        return (None, gz, *G)


def evaluate(field: FastField, z: torch.Tensor) -> torch.Tensor:
    """``f(z)``, differentiable w.r.t. ``z`` and the parameters when autograd records."""
    if torch.is_grad_enabled() and (z.requires_grad or any(p.requires_grad
                                                           for p in field.params)):
        return _FieldFn.apply(field, z, *field.params)
    with torch.no_grad():
        return field.forward(field.params, z)


def _rk_forward(field, P, scheme, z, h):
    """One explicit Runge-Kutta step without a tape."""
    ks = []
    for a in scheme.a:
        zs = z
        for a_r, k in zip(a, ks, strict=True):
            if a_r:
                zs = zs + (h * a_r) * k
        ks.append(field.forward(P, zs))
    dz = None
    for b, k in zip(scheme.b, ks, strict=True):
        if b:
            dz = b * k if dz is None else dz + b * k
    return z + h * dz


def _rk_backward(field, P, G, scheme, z, h, gz_next):
    """Recompute one step from ``z`` with tapes and return the gradient w.r.t. ``z``."""
    ks, tapes = [], []
    for a in scheme.a:
        zs = z
        for a_r, k in zip(a, ks, strict=True):
            if a_r:
                zs = zs + (h * a_r) * k
        tape: list = []
        ks.append(field.forward(P, zs, tape))
        tapes.append(tape)
    S = len(ks)
    g_k = [gz_next * (h * b) if b else None for b in scheme.b]
    gz = gz_next.clone()
    for s in range(S - 1, -1, -1):
        if g_k[s] is None:
            continue
        g_zs = field.backward(P, G, tapes[s], g_k[s])
        gz.add_(g_zs)
        for r, a_r in enumerate(scheme.a[s]):
            if a_r:
                upd = g_zs * (h * a_r)
                g_k[r] = upd if g_k[r] is None else g_k[r] + upd
    return gz


class _RolloutFn(torch.autograd.Function):
    """A fixed-step rollout ``(T, 2, M, 3)``: forward without a graph, keeping the states at
    the saved times; backward recomputes each interval with tapes."""

    @staticmethod
    def forward(ctx, field, scheme, t, substeps, z0, *P):
        zs = [z0]
        z = z0
        hs = []
        for k in range(len(t) - 1):
            h = float((t[k + 1] - t[k]) / substeps)
            hs.append(h)
            for _ in range(substeps):
                z = _rk_forward(field, P, scheme, z, h)
            zs.append(z)
        out = torch.stack(zs)
        ctx.field, ctx.scheme, ctx.hs, ctx.substeps = field, scheme, hs, substeps
        ctx.save_for_backward(out, *P)
        return out

    @staticmethod
    def backward(ctx, g_out):
        out, *P = ctx.saved_tensors
        field, scheme, substeps = ctx.field, ctx.scheme, ctx.substeps
        G = [torch.zeros_like(p) for p in P]
        gz = g_out[-1].clone()
        for k in range(len(ctx.hs) - 1, -1, -1):
            h = ctx.hs[k]
            if substeps == 1:
                gz = _rk_backward(field, P, G, scheme, out[k], h, gz)
            else:
                subs = [out[k]]
                for _ in range(substeps - 1):
                    subs.append(_rk_forward(field, P, scheme, subs[-1], h))
                for zk in reversed(subs):
                    gz = _rk_backward(field, P, G, scheme, zk, h, gz)
            gz = gz + g_out[k]
        return (None, None, None, None, gz, *G)


def rollout(field: FastField, scheme, z0: torch.Tensor, t: torch.Tensor,
            substeps: int = 1) -> torch.Tensor:
    """States ``(T, 2, M, 3)`` at times ``t`` of the fixed-step ``scheme``
    (``meshodenet.integrators.ExplicitRK``), differentiable when autograd records."""
    if torch.is_grad_enabled() and (z0.requires_grad or any(p.requires_grad
                                                            for p in field.params)):
        return _RolloutFn.apply(field, scheme, t, substeps, z0, *field.params)
    with torch.no_grad():
        return _RolloutFn.forward(_NoCtx(), field, scheme, t, substeps, z0, *field.params)


class _NoCtx:
    """A stand-in for the autograd context when no gradient is recorded."""

    def save_for_backward(self, *a):
        pass
