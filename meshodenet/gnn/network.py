"""The encode-process-decode network of MeshODENet and MeshGraphNet on plain tensors: its
dynamic features (``Features``, rod angles in ``RodAngles``), its forward pass and, for
MeshODENet's vector field, its hand-written backward pass (``FastField``); MeshGraphNet's step
(``FastGNN``) runs the same features and weight layout under autograd.

The definition is the module-by-module code (``meshodenet.gnn.layers``, ``meshodenet.gnn.features``,
``meshodenet.gnn.reference``: the ``reference`` engine); this is the same function, rearranged
so that it runs faster, with the same numbers up to float round-off (tested in float64,
``tests/test_fast.py``; docs/TRAINING.md has the profile):

- Everything that does not depend on the state is built once per graph context: the graph's
  index tensors; the normalised static features are folded into the first layers of the
  encoders (``W [s | f] + b = W_d f + c`` with the per-row constant ``c = W_s s + b``), the
  acceleration de-normalisation into the decoder's last layer (``FastField``).
- Concatenations are replaced by split weight matrices: the edge MLP's first layer on
  ``[e, h_i, h_j]`` becomes ``W_e e + (W_s h)_i + (W_r h)_j``, with ``W_s h`` and ``W_r h``
  computed on the nodes (fewer rows than edges) and gathered with one index; the node MLP's on
  ``[h, sum e]`` becomes ``W_h h + W_a sum e``.

``meshodenet.gnn.fast`` steps ``FastField`` through Runge-Kutta rollouts and their gradients.
"""

from __future__ import annotations

import contextlib

import torch


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


# --- features ---------------------------------------------------------------------------------
class RodAngles:
    """``[cos a, sin a]`` per node ``(M, 2)`` of rods (line meshes) at positions ``x (M, 3)``:
    the signed turning angle ``a`` at every hinge ``p -> i -> q``, ``cos a = e1.e2 / (|e1||e2|)``,
    ``sin a = (e1 x e2).z / (|e1||e2|)``, ``e1 = x_i - x_p``, ``e2 = x_q - x_i``; ``(1, 0)`` off
    hinges (``meshodenet.gnn.features``). Its forward is differentiated by autograd (MeshGraphNet,
    the module code) or by ``backward`` (MeshODENet's field). The only code of the network
    that knows mesh kinds."""

    def __init__(self, hinges: torch.Tensor, n_nodes: int, dtype, device):
        self.p, self.i, self.q = hinges[:, 0], hinges[:, 1], hinges[:, 2]
        self.all = hinges.t().reshape(-1)
        base = torch.zeros(n_nodes, 2, dtype=dtype, device=device)
        base[:, 0] = 1.0
        self.base = base
        rot = torch.zeros(3, 6, dtype=dtype, device=device)  # e2 -> [e2, (e2_y, -e2_x, 0)]
        rot[0, 0] = rot[1, 1] = rot[2, 2] = 1.0
        rot[1, 3], rot[0, 4] = 1.0, -1.0
        self.rot = rot

    def forward(self, x, tape=None):
        p, i, q = self.p, self.i, self.q
        e1, e2 = x[i] - x[p], x[q] - x[i]
        n1, n2 = e1.norm(dim=-1), e2.norm(dim=-1)
        r = (n1 * n2).clamp_min(1e-30)
        cos = (e1 * e2).sum(-1) / r
        sin = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / r
        cs_h = torch.stack([cos, sin], dim=-1)
        if tape is not None:
            tape += [e1, e2, n1, n2, r, cs_h]
        return self.base.index_copy(0, i, cs_h)

    def backward(self, tape, g_cs, g_x) -> None:
        """Adds into ``g_x`` the gradient w.r.t. ``x`` of the angles whose gradient is
        ``g_cs (M, 2)`` (pops what ``forward`` put on ``tape``)."""
        cs_h, r, n2, n1, e2, e1 = (tape.pop() for _ in range(6))
        H = len(cs_h)
        g_cs = g_cs.index_select(0, self.i)  # (H, 2)
        g_num = g_cs / r.unsqueeze(1)
        g_r = -(g_cs * cs_h).sum(-1) / r  # (hinges with |e1||e2| < 1e-30: not masked)
        # num = [e1.e2, e1.rot(e2)], rot(e2) = (e2_y, -e2_x, 0)
        e2r = torch.mm(e2, self.rot).view(H, 2, 3)
        g_e1 = (g_num.unsqueeze(-1) * e2r).sum(1)
        ge_rot = g_num[:, 1:2] * e1  # gradient w.r.t. rot(e2), mapped back by rot^T
        g_e2 = g_num[:, :1] * e1 + torch.mm(ge_rot, self.rot[:, 3:].t())
        # r = n1 n2, dn/de = e / n
        g_e1 = g_e1 + (g_r * n2 / n1.clamp_min(1e-300)).unsqueeze(1) * e1
        g_e2 = g_e2 + (g_r * n1 / n2.clamp_min(1e-300)).unsqueeze(1) * e2
        ge = torch.stack([-g_e1, g_e1 - g_e2, g_e2]).view(-1, 3)
        g_x.index_add_(0, self.all, ge)


class Features:
    """The normalised dynamic node and edge features of a ``GraphContext`` (layout in
    ``meshodenet.gnn.features``) at positions ``x`` and velocities ``v`` ``(M, 3)``, and their
    backward pass.

    ``fused_load``: the load ``force - damping v`` with one fused multiply-add (MeshODENet's
    field) or as the module code computes it (MeshGraphNet): the two round differently, and
    each model keeps the numbers it was measured with.
    """

    def __init__(self, ctx, fused_load: bool = True):
        b = ctx.batch
        self.force, self.damping = b.force, b.damping
        self.senders, self.receivers = b.senders, b.receivers
        self.fused_load = fused_load
        dtype, dev = ctx.node_static.dtype, ctx.node_static.device
        self.angles = RodAngles(b.hinges, b.n_nodes, dtype, dev) if ctx.kind == "line" else None
        self.node_mean, self.node_std = ctx.node_mean, ctx.node_std
        self.edge_mean, self.edge_std = ctx.edge_mean, ctx.edge_std
        self.authors_nodes, self.authors_edges = ctx.authors_nodes, ctx.authors_edges

    def forward(self, x, v, tape=None):
        """``(node (M, n_dyn), edge (D, 4))``; when ``tape`` (a list) is given, what
        ``backward`` needs is appended to it."""
        if self.authors_nodes:  # [v]
            F = v
        else:
            if self.fused_load:
                fext = torch.addcmul(self.force, self.damping, v, value=-1.0)
            else:
                fext = self.force - self.damping * v
            if self.angles is None:
                F = torch.cat([v, fext], 1)
            else:
                F = torch.cat([v, self.angles.forward(x, tape), fext], 1)
        vec = x.index_select(0, self.receivers) - x.index_select(0, self.senders)
        length = vec.norm(dim=-1, keepdim=True)
        lc = length.clamp_min(1e-30)
        Fe = torch.cat([length, vec if self.authors_edges else vec / lc], 1)
        if tape is not None:
            tape += [lc, Fe]
        # normalised as in GraphContext.inputs (the means are not folded into the weights:
        # in float32 that cancels digits when a feature's mean is large against its std)
        return (F - self.node_mean) / self.node_std, (Fe - self.edge_mean) / self.edge_std

    def backward(self, tape, g_F, g_Fe, g_v):
        """Gradient w.r.t. ``x`` from those of the normalised features ``g_F, g_Fe``; adds the
        velocity part into ``g_v`` (pops ``tape``)."""
        g_F, g_Fe = g_F / self.node_std, g_Fe / self.edge_std
        Fe, lc = tape.pop(), tape.pop()
        g_d = g_Fe[:, 1:]
        if self.authors_edges:  # [length, vec]: d|vec|/dvec = vec / |vec|
            g_vec = torch.addcdiv(g_d, g_Fe[:, :1] * Fe[:, 1:], lc)
        else:
            d = Fe[:, 1:]
            # length = |vec|, d = vec / max(length, 1e-30). For an edge of zero length (vec =
            # 0, so d = 0) this is autograd's subgradient too; only lengths in (0, 1e-30) differ.
            g_vec = torch.addcdiv(g_Fe[:, :1] * d, g_d - (g_d * d).sum(-1, keepdim=True) * d, lc)
        g_x = torch.zeros_like(g_v)
        g_x.index_add_(0, self.receivers, g_vec).index_add_(0, self.senders, -g_vec)
        if self.authors_nodes:  # node features: [v]
            g_v.add_(g_F)
            return g_x
        # node features: [v, cs, fext] (line) or [v, fext]; fext = force - damping v
        g_v.add_(g_F[:, :3])
        g_v.addcmul_(self.damping, g_F[:, -3:], value=-1.0)
        if self.angles is not None:
            self.angles.backward(tape, g_F[:, 3:5], g_x)
        return g_x


# --- the network -------------------------------------------------------------------------------
class SumAtReceivers(torch.autograd.Function):
    """``zeros(M, d).index_add_(0, receivers, m)`` under autograd, keeping only ``receivers``
    for the backward pass. Autograd's own ``index_add`` keeps its source alive until then,
    though its gradient is ``g[receivers]`` alone: in MeshGraphNet's training step that was
    one ``(edges, hidden)`` activation per block (109 of the 678 MB a plate step keeps). The
    same forward and the same gradient, bit for bit."""

    @staticmethod
    def forward(ctx, m, receivers, n_nodes: int):
        ctx.save_for_backward(receivers)
        return m.new_zeros(n_nodes, m.shape[1]).index_add_(0, receivers, m)

    @staticmethod
    def backward(ctx, g):
        (receivers,) = ctx.saved_tensors
        return g.index_select(0, receivers), None, None


class Network:
    """``EncodeProcessDecode`` ``gnn`` (``meshodenet.gnn.layers``; its ``GraphNetBlock`` and
    LayerNorm variant for MeshGraphNet) on one ``GraphContext``: the features and the
    forward pass on effective weights built once.

    ``params`` is the list of effective weights; ``node_enc``, ``edge_enc``, ``decoder`` (lists
    of ``(w, b)`` indices into it) and ``layers`` say where each MLP's weights sit.
    ``output``: ``(std, mean)`` folded into the decoder's last layer (``y std + mean``), or
    ``None``. ``detach``: the weights detached from the module's parameters (a hand-written
    backward maps their gradients back, ``sources``) or differentiable functions of them
    (autograd). ``fused_load``: as ``Features``.
    """

    def __init__(self, gnn, ctx, activation: str, *, output=None, detach: bool = True,
                 fused_load: bool = True):
        self.act = activation
        b = ctx.batch
        self.M, self.D = b.n_nodes, len(b.senders)
        self.free = b.free
        self.senders, self.receivers = b.senders, b.receivers
        self.idx_sr = torch.cat([2 * b.senders, 2 * b.receivers + 1])
        self.features = Features(ctx, fused_load)
        self.aggregate_updated = [getattr(layer, "aggregate_updated_edges", True)
                                  for layer in gnn.processor]
        ln = lambda seq: seq[-1] if isinstance(seq[-1], torch.nn.LayerNorm) else None
        self.node_enc_ln, self.edge_enc_ln = ln(gnn.node_encoder), ln(gnn.edge_encoder)
        self.layer_norms = [(ln(layer.edge_mlp), ln(layer.node_mlp)) for layer in gnn.processor]
        P: list = []
        self.sources: list = []  # the module tensors the effective weights are made of
        maps: list = []  # (source index, fn(G) -> its gradient)
        D = (lambda t: t.detach()) if detach else (lambda t: t)

        def add(t):
            P.append(t)
            return len(P) - 1

        def src(t):
            self.sources.append(t)
            return len(self.sources) - 1

        def plain(lin):
            w, b = add(D(lin.weight).t()), add(D(lin.bias))
            maps.append((src(lin.weight), lambda G, w=w: G[w].t()))
            maps.append((src(lin.bias), lambda G, b=b: G[b]))
            return w, b

        def folded(lin, static, first: bool):
            """A first layer on ``[static | dynamic]`` (``first``) or ``[dynamic | static]``:
            ``W_d f + c``, ``c = W_s static + b`` (a per-row bias)."""
            W, bias = D(lin.weight), D(lin.bias)
            k = static.shape[1] if first else W.shape[1] - static.shape[1]  # the split column
            Wd, Ws = (W[:, k:], W[:, :k]) if first else (W[:, :k], W[:, k:])
            w, c = add(Wd.t()), add(torch.addmm(bias, static, Ws.t()))

            def weight_grad(G):
                gs, gd = G[c].t() @ static, G[w].t()
                return torch.cat([gs, gd] if first else [gd, gs], 1)

            maps.append((src(lin.weight), weight_grad))
            maps.append((src(lin.bias), lambda G: G[c].sum(0)))
            return w, c

        def encoder(seq, static):
            """First layer on ``[static | dynamic]``: ``W_d f + c``, ``c = W_s static + b``."""
            lins = _linears(seq)
            return [folded(lins[0], static, True)] + [plain(lin) for lin in lins[1:]]

        def decoder(seq, static=None):
            """Last layer followed by the de-normalisation ``y s + m`` (with ``output``); with
            ``static`` (the authors' layout) the first layer on ``[h | static]`` folded."""
            lins = _linears(seq)
            first = [] if static is None else [folded(lins[0], static, False)]
            lins = lins[len(first):]
            if output is None:
                return first + [plain(lin) for lin in lins]
            out = first + [plain(lin) for lin in lins[:-1]]
            s_, m_ = output
            W, bias = D(lins[-1].weight), D(lins[-1].bias)
            w, b = add((W * s_[:, None]).t()), add(bias * s_ + m_)
            maps.append((src(lins[-1].weight), lambda G: G[w].t() * s_[:, None]))
            maps.append((src(lins[-1].bias), lambda G: G[b] * s_))
            return out + [(w, b)]

        dec_static = ctx.decoder_static
        enc_static = ctx.node_static if dec_static is None else ctx.node_static[:, :0]
        with torch.no_grad() if detach else contextlib.nullcontext():
            self.node_enc = encoder(gnn.node_encoder, enc_static)
            self.edge_enc = encoder(gnn.edge_encoder, ctx.edge_static)
            self.layers = []
            for layer in gnn.processor:
                el, nl = _linears(layer.edge_mlp), _linears(layer.node_mlp)
                d = el[0].weight.shape[0]
                W1, b1 = D(el[0].weight), D(el[0].bias)
                we, wsr = add(W1[:, :d].t()), add(torch.cat([W1[:, d:2 * d], W1[:, 2 * d:]]).t())
                bsr = add(torch.cat([b1, torch.zeros_like(b1)]))
                maps.append((src(el[0].weight), lambda G, we=we, wsr=wsr, d=d: torch.cat(
                    [G[we].t(), G[wsr].t()[:d], G[wsr].t()[d:]], 1)))
                maps.append((src(el[0].bias), lambda G, bsr=bsr, d=d: G[bsr][:d]))
                Wn = D(nl[0].weight)
                wh, wa, bn = add(Wn[:, :d].t()), add(Wn[:, d:].t()), add(D(nl[0].bias))
                maps.append((src(nl[0].weight),
                             lambda G, wh=wh, wa=wa: torch.cat([G[wh].t(), G[wa].t()], 1)))
                maps.append((src(nl[0].bias), lambda G, bn=bn: G[bn]))
                rest_e = [plain(m) for m in el[1:]]
                rest_n = [plain(m) for m in nl[1:]]
                self.layers.append(((we, wsr, bsr), rest_e, (wh, wa, bn), rest_n, d))
            self.decoder = decoder(gnn.decoder, dec_static)
            self.params = P
        self._maps = maps

    def _mlp_fwd(self, P, layers, x, pre0, tape, ln=None):
        """Layers ``layers`` from input ``x`` (or from the first pre-activation ``pre0``),
        then the LayerNorm ``ln`` when given."""
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
        if ln is not None:
            x = torch.nn.functional.layer_norm(x, ln.normalized_shape, ln.weight, ln.bias, ln.eps)
        return x

    def network(self, P, F, Fe, tape=None):
        """Decoder output ``(M, d_out)`` from the normalised dynamic features ``F, Fe``
        (``Features.forward``); when ``tape`` (a list) is given, what the backward pass needs
        is appended to it."""
        h = self._mlp_fwd(P, self.node_enc, F, None, tape, self.node_enc_ln)
        e = self._mlp_fwd(P, self.edge_enc, Fe, None, tape, self.edge_enc_ln)
        M = self.M
        for k, (e_first, rest_e, n_first, rest_n, d) in enumerate(self.layers):
            ln_e, ln_n = self.layer_norms[k]
            we, wsr, bsr = e_first
            hsr = torch.addmm(P[bsr], h, P[wsr]).view(2 * M, d)
            g = hsr.index_select(0, self.idx_sr).view(2, -1, d)
            pre = torch.addmm(g[0] + g[1], e, P[we])
            if tape is not None:
                tape += [h, e]
            m = self._mlp_fwd(P, [(None, None)] + rest_e, None, pre, tape, ln_e)
            if self.aggregate_updated[k]:  # the nodes sum e + m (InteractionLayer)
                e = e + m
                agg = e.new_zeros(M, d).index_add_(0, self.receivers, e)
            elif m.requires_grad and torch.is_grad_enabled():  # the nodes sum m (GraphNetBlock)
                agg = SumAtReceivers.apply(m, self.receivers, M)
            else:
                agg = m.new_zeros(M, d).index_add_(0, self.receivers, m)
            wh, wa, bn = n_first
            pre = torch.addmm(torch.addmm(P[bn], h, P[wh]), agg, P[wa])
            if tape is not None:
                tape.append(agg)
            h = h + self._mlp_fwd(P, [(None, None)] + rest_n, None, pre, tape, ln_n)
            if not self.aggregate_updated[k]:
                e = e + m
        return self._mlp_fwd(P, self.decoder, h, None, tape)


# --- MeshODENet's vector field -----------------------------------------------------------------
class FastField(Network):
    """The vector field of MeshODENet ``model`` on one ``GraphContext``, ready to be evaluated
    many times, with its hand-written backward pass (``Network`` with the acceleration
    de-normalisation folded into the decoder and detached weights)."""

    def __init__(self, model, ctx):
        super().__init__(model.gnn, ctx, model.config.activation,
                         output=(ctx.acc_std, ctx.acc_mean))
        # the backward pass is written for InteractionLayers without LayerNorm
        assert all(self.aggregate_updated) and self.node_enc_ln is None
        self.model = model
        self.PT = [p.t() if p.dim() == 2 else None for p in self.params]
        self._pending: dict = {}

    def requires_grad(self) -> bool:
        return any(t.requires_grad for t in self.sources)

    def new_grads(self) -> list:
        self._G = [torch.zeros_like(p) for p in self.params]
        return self._G

    def source_grads(self, G) -> list:
        """Gradients of ``sources`` from those of the effective weights ``G``."""
        self.flush(G)
        out = [None] * len(self.sources)
        for i, fn in self._maps:
            out[i] = fn(G)
        return out

    def _wgrad(self, w, b, x, g) -> None:
        """Defer ``G[w] += x^T g`` (and ``G[b] += sum g``): ``flush`` does them as one matmul
        per weight over many evaluations, which runs nearer the machine's peak than many
        matmuls with a short inner dimension."""
        if x.shape[0] >= DEFER_MAX_ROWS:  # already an efficient matmul: no copies
            G = self._G
            G[w].addmm_(x.t(), g)
            if b is not None:
                G[b].add_(g.sum(0) if G[b].dim() == 1 else g)
            return
        entry = self._pending.get(w)
        if entry is None:
            self._pending[w] = (b, [x], [g])
        else:
            entry[1].append(x)
            entry[2].append(g)

    def flush(self, G) -> None:
        for w, (b, xs, gs) in self._pending.items():
            X = xs[0] if len(xs) == 1 else torch.cat(xs)
            Gm = gs[0] if len(gs) == 1 else torch.cat(gs)
            G[w].addmm_(X.t(), Gm)
            if b is not None:
                if G[b].dim() == 1:
                    G[b].add_(Gm.sum(0))
                else:
                    G[b].add_(Gm.view(len(gs), -1, Gm.shape[1]).sum(0))
        self._pending = {}

    # --- forward ----------------------------------------------------------------------------
    def forward(self, P, z, tape=None):
        """``dz/dt`` ``(2, M, 3)`` for ``z = [x, v]``; when ``tape`` (a list) is given, what the
        backward pass needs is appended to it."""
        x, v = z[0], z[1]
        vf = v * self.free
        F, Fe = self.features.forward(x, vf, tape)
        a = self.network(P, F, Fe, tape) * self.free
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
            self._wgrad(w, b, tape.pop(), g)
            g = torch.mm(g, self.PT[w])
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
            self._wgrad(wa, bn, agg, g_pre)
            g_agg = torch.mm(g_pre, self.PT[wa])
            g_hin = torch.addmm(g_h, g_pre, self.PT[wh])
            g_pre_n = g_pre
            # e_out = e_in + m; agg = scatter(e_out); gradient of e_out:
            g_eout = g_agg.index_select(0, self.receivers)
            if g_e is not None:
                g_eout = g_eout + g_e
            g_pre = self._mlp_bwd(P, G, [(None, None)] + rest_e, tape, g_eout, True)
            e_in, h_in = tape.pop(), tape.pop()
            self._wgrad(wh, None, h_in, g_pre_n)
            we, wsr, bsr = e_first
            self._wgrad(we, None, e_in, g_pre)
            g_e = torch.addmm(g_eout, g_pre, self.PT[we])
            g_hsr = g_pre.new_zeros(2 * M, d).index_add_(
                0, self.idx_sr, g_pre.unsqueeze(0).expand(2, -1, -1).reshape(-1, d)).view(M, 2 * d)
            self._wgrad(wsr, bsr, h_in, g_hsr)
            g_h = torch.addmm(g_hin, g_hsr, self.PT[wsr])
        if g_e is None:
            g_e = torch.zeros(self.D, P[self.edge_enc[-1][0]].shape[1], dtype=gz.dtype,
                              device=gz.device)
        g_Fe = self._mlp_bwd(P, G, self.edge_enc, tape, g_e, False)
        g_F = self._mlp_bwd(P, G, self.node_enc, tape, g_h, False)
        g_x = self.features.backward(tape, g_F, g_Fe, g_vf)
        return torch.stack([g_x, g_vf * self.free])


#: Weight gradients of layers with at least this many rows (nodes or edges of the batch) are
#: not deferred: their matmuls are efficient already, and the copies would cost memory.
DEFER_MAX_ROWS = 256


# --- MeshGraphNet's step ---------------------------------------------------------------------
class FastGNN(Network):
    """MeshGraphNet's network (``GraphNetBlock``s, LayerNorm) on one ``GraphContext``,
    evaluated with autograd: its one-step training needs few evaluations of large batches, so
    the backward pass is left to autograd. The weights are differentiable functions of the
    module's parameters: build it once per context and set of parameter values."""

    def __init__(self, gnn, ctx, activation: str):
        super().__init__(gnn, ctx, activation, detach=False, fused_load=False)

    def __call__(self, x, v):
        """Decoder output ``(M, d_out)`` at positions ``x`` and velocities ``v`` ``(M, 3)``."""
        return self.network(self.params, *self.features.forward(x, v))
