"""Implicit-Energy's start from the training split (``meshodenet.energy.model``; a base class
of ``ImplicitEnergy``): the statistics its energy is normalised with, the training frames as
its loss reads them, and the least-squares fit of the frames' momentum balance that sets each
element type's stiffness (``_fit_log_stiffness``)."""

from __future__ import annotations

import math

import torch
from torch import nn

from meshodenet.energy.core import EnergySystem, measure
from meshodenet.mesh.data import Trajectories

#: Bytes per activation of the element MLPs in the least-squares start's pass over the
#: training frames (``LeastSquaresStart._balance_columns``), which takes the frames in chunks of
#: this size: a bound on its memory whatever the mesh or the number of frames.
FIT_CHUNK_BYTES = 16 * 2**20
#: Frames per chunk are a multiple of this: every chunk's tensors (frames x elements x ...)
#: then hold a multiple of 64 values, so torch's vectorised loops, whose last few values are
#: computed by scalar code that may round differently (``atan2``, ``exp``), split each chunk
#: where they split the one pass over all frames (a chunk of one frame changed a dihedral
#: hinge's columns by 2e-16 relative).
FIT_CHUNK_ALIGN = 64
#: Bytes (float64) of the start's whole-split tensors above which they are never built: the
#: statistics' gathered measures and motions (``_statistics``) and the least-squares system
#: ``[G | rhs]`` (``_fit_log_stiffness``). Below it (every registered case at r = 1: the
#: plate's system is 0.1 GB) they are built as one tensor each; above it the statistics are
#: summed over chunks of frames and the system is reduced chunk by chunk to its triangular
#: factor (``_reduced_lstsq``), so the start's memory is a chunk's, not the split's (a
#: 9,289-node plate with 5 training trajectories: 6-7 GB in one pass). The same estimators;
#: their round-off differs (``tests/test_memory.py`` holds them to 1e-12 relative; on
#: plate_cantilever's data the stiffness fits agree to 3e-14).
START_WHOLE_BYTES = 256 * 2**20
#: Bytes per chunk of the reduced statistics and least squares.
START_CHUNK_BYTES = 32 * 2**20


class _AtNodes:
    """``a (B, T, N, 3)`` read at the nodes ``at (n,)``: ``[traj, j]`` (``traj (S,)``, ``j``
    ``(S,)`` or an int) is ``(S, n, 3)``, gathered without taking whole frames."""

    def __init__(self, a: torch.Tensor, at: torch.Tensor):
        self.a, self.at = a, at

    def __getitem__(self, key):
        traj, j = key
        j = torch.as_tensor(j, device=traj.device).expand_as(traj)
        return self.a[traj[:, None], j[:, None], self.at]


class _NodeFrames:
    """The times of ``data`` and its positions and velocities at the nodes ``at``
    (``_AtNodes``)."""

    def __init__(self, data: Trajectories, at: torch.Tensor):
        self.t, self.pos, self.vel = data.t, _AtNodes(data.pos, at), _AtNodes(data.vel, at)


class LeastSquaresStart:
    """The statistics, training frames and least-squares start of ``ImplicitEnergy`` (see
    there for the buffers they fill)."""

    @torch.no_grad()
    def _statistics(self, train: Trajectories) -> None:
        """``ystats`` and each type's ``sigma`` (and ``qrange``) over every training frame.
        One trajectory at a time in float64: the squared one-step motions and the measures
        ``q`` of all frames are gathered into one tensor each (their means over the same
        tensors as before, the same bits), never the float64 positions of the whole split or
        their gather onto the elements (``(B, T, n, k, 3)``, 10-30 times the split's size)."""
        y = train.youngs.to(torch.float64)
        ly = torch.log(y)
        sd = float(ly.std()) if len(y) > 1 and float(ly.std()) > 0 else 1.0
        B, T = train.pos.shape[:2]
        f64 = dict(dtype=torch.float64, device=self.ystats.device)
        elems = self._elems()
        n_free = int(self.free.sum())
        whole = 8 * B * T * (n_free + sum(len(e[0]) for e in elems.values()))
        if whole > START_WHOLE_BYTES:
            return self._statistics_reduced(train, float(y.mean()), float(ly.mean()), sd)
        step2 = torch.empty(B, T - 1, n_free, **f64)
        qs = {k: torch.empty(B, T, len(nodes), **f64) for k, (nodes, *_) in elems.items()}
        for b in range(B):
            pos = train.pos[b].to(torch.float64)
            step2[b] = ((pos[1:] - pos[:-1])[:, self.free] ** 2).sum(-1)
            for k, (nodes, _, rest, l0) in elems.items():
                qs[k][b] = measure(k, pos[:, nodes], rest, l0)
        self.ystats.copy_(torch.tensor([float(y.mean()), float(ly.mean()), sd,
                                        float(step2.mean())]))
        del step2
        for k in elems:
            q = qs.pop(k)
            rms = float(torch.sqrt((q**2).mean()))
            getattr(self, f"{k}_sigma").fill_(rms if rms > 0 else 1.0)
            if self.config.clamp_q:
                qh = q / getattr(self, f"{k}_sigma")
                getattr(self, f"{k}_qrange").copy_(torch.stack([qh.min(), qh.max()]))

    @torch.no_grad()
    def _statistics_reduced(self, train: Trajectories, y_mean: float, ly_mean: float,
                            sd: float) -> None:
        """``_statistics`` summed over chunks of frames of one trajectory (``START_CHUNK_BYTES``
        of gathered element positions each): the same means, extremes and buffers, never a
        whole-split tensor (``START_WHOLE_BYTES``)."""
        B, T = train.pos.shape[:2]
        elems = self._elems()
        per = max(len(nodes) * nodes.shape[1] for nodes, *_ in elems.values()) * 3 * 8
        chunk = max(1, START_CHUNK_BYTES // max(per, 1))
        s2, n2 = 0.0, 0
        acc = {k: [0.0, 0, math.inf, -math.inf] for k in elems}  # sum q^2, count, min, max
        for b in range(B):
            for j0 in range(0, T, chunk):
                j1 = min(j0 + chunk, T)
                pos = train.pos[b, j0:min(j1 + 1, T)].to(torch.float64)
                d = ((pos[1:] - pos[:-1])[:, self.free] ** 2).sum(-1)
                s2, n2 = s2 + float(d.sum()), n2 + d.numel()
                for k, (nodes, _, rest, l0) in elems.items():
                    q = measure(k, pos[:j1 - j0][:, nodes], rest, l0)
                    a = acc[k]
                    a[0] += float((q**2).sum())
                    a[1] += q.numel()
                    a[2], a[3] = min(a[2], float(q.min())), max(a[3], float(q.max()))
        self.ystats.copy_(torch.tensor([y_mean, ly_mean, sd, s2 / max(n2, 1)]))
        for k, (sq, n, lo, hi) in acc.items():
            rms = math.sqrt(sq / max(n, 1))
            sigma = getattr(self, f"{k}_sigma").fill_(rms if rms > 0 else 1.0)
            if self.config.clamp_q:  # q / sigma is monotonic in q: its extremes are these
                getattr(self, f"{k}_qrange").copy_(torch.tensor([lo, hi], dtype=sigma.dtype)
                                                   / sigma)

    def _frames(self, data: Trajectories, samples: torch.Tensor, nodes=None):
        """``(traj, x_k, v_k, x_{k+1}, h)`` of samples, float64: ``v_k`` the backward
        difference (the stored ``v_0`` at frame 0) as in a backward-Euler rollout; Newmark's,
        whose velocity is the trajectory's own, the stored one. With ``nodes`` (global ids
        ``(n,)``) the frames at those nodes only, indexed without taking a whole frame."""
        samples = samples.to(data.pos.device)
        T = data.n_frames
        traj, k = samples // (T - 1), samples % (T - 1)
        if nodes is not None:
            at = torch.as_tensor(nodes, device=data.pos.device)
            data = _NodeFrames(data, at)
        # the samples' frames, then float64 (not the whole split converted per training step)
        pos = lambda j: data.pos[traj, j].to(torch.float64)  # noqa: E731
        t = data.t.to(torch.float64)
        h = t[k + 1] - t[k]
        if not torch.allclose(h, h[0].expand_as(h), rtol=1e-4):
            raise ValueError("implicit_energy trains on evenly sampled trajectories only")
        hk = (t[k] - t[(k - 1).clamp(min=0)]).clamp_min(1e-300)[:, None, None]
        xk = pos(k)
        vk = torch.where((k == 0)[:, None, None], data.vel[traj, 0].to(torch.float64),
                         (xk - pos((k - 1).clamp(min=0))) / hk)
        if self.config.integrator == "newmark":
            vk = data.vel[traj, k].to(torch.float64)
        return traj, xk, vk * self.free[:, None], pos(k + 1), float(h[0])

    @torch.no_grad()
    def _fit_log_stiffness(self, train: Trajectories, every: int = 5) -> None:
        """``a_t`` from the least-squares momentum balance of the training frames with
        ``g = 1``: the stiffness scales that best explain ``m a + c v - f`` (free nodes).
        With ``stiffness_prior = features`` each element's stiffness is
        ``k_e = theta_t . (1, s_e)`` (``s_e`` its static features, the constant ones left
        out), floored at 1e-3 of its type's largest; ``a_t = log mean_e k_e`` and the factor
        ``kappa_e = k_e / mean_e k_e``."""
        T = train.n_frames
        samples = torch.arange(0, len(train) * (T - 1), every)
        n_cols = len(self.kinds) if self.config.stiffness_prior == "uniform" else \
            sum(len(self._basis(k)) for k in self.kinds)
        per = 3 * int(self.free.sum()) * (n_cols + 1) * 8  # bytes of a sample's rows
        if per * len(samples) > START_WHOLE_BYTES:
            s, owner = self._reduced_lstsq(train, samples, max(1, START_CHUNK_BYTES // per))
        else:
            G, rhs, owner, _ = self._balance_system(train, samples)
            s = torch.linalg.lstsq(G, rhs.reshape(-1, 1)).solution[:, 0]
        self._set_stiffness(s, owner)

    def _balance_system(self, train: Trajectories, samples: torch.Tensor,
                        h: float | None = None) -> tuple:
        """The least-squares start's system over ``samples``: ``G (rows, columns)``, ``rhs``
        (the free coordinates' momentum balance without the elastic forces), the columns'
        owners (``_balance_columns``) and the step ``h``: the first sample's unless given
        (the frames' spacing differs in its last bits, and ``x1 - xk - h vk`` is a small
        difference of large ones: another sample's ``h`` moved ``rhs`` by 6e-6)."""
        traj, xk, vk, x1, h_first = self._frames(train, samples)
        h = h_first if h is None else h
        lhs, owner = self._balance_columns(train.youngs[traj], x1)
        m, c = self.mass[:, None], self.damping[:, None]
        rhs = -(m / h**2 * (x1 - xk - h * vk) + c / h * (x1 - xk) - self.force)[:, self.free]
        return torch.stack(lhs, 1), rhs, owner, h

    def _reduced_lstsq(self, train: Trajectories, samples: torch.Tensor, step: int) -> tuple:
        """The least-squares solution over ``samples`` taken ``step`` at a time: each chunk's
        rows ``[G | rhs]`` are stacked under the triangular factor of those before and
        factorised again (QR), so the last factor ``[R | z]`` has the normal equations of all
        rows (``R^T R = G^T G``, ``R^T z = G^T rhs``) without squaring their condition; the
        solution is ``lstsq`` of the small ``R s = z``, with the rank cut-off ``lstsq`` takes
        for the whole ``G`` (``eps max(rows, columns)``: the columns are nearly dependent, and
        the small system's own cut-off kept directions the whole one drops)."""
        R, owner, rows, h = None, [], 0, None
        for i in range(0, len(samples), step):  # every chunk with the first sample's h
            G, rhs, owner, h = self._balance_system(train, samples[i:i + step], h)
            rows += len(G)
            A = torch.cat([G, rhs.reshape(-1, 1)], 1)
            R = torch.linalg.qr(A if R is None else torch.cat([R, A], 0), mode="r").R
        rcond = torch.finfo(R.dtype).eps * max(rows, R.shape[1] - 1)
        return torch.linalg.lstsq(R[:, :-1], R[:, -1:], rcond=rcond).solution[:, 0], owner

    def _set_stiffness(self, s: torch.Tensor, owner: list) -> None:
        """``a_t`` (and ``kappa_e``) from the least-squares solution ``s`` over the columns
        of ``_balance_columns`` (``owner`` as it returns)."""
        if self.config.stiffness_prior == "uniform":
            for k, sk in zip(self.kinds, s):
                sk = float(sk) if float(sk) > 0 else 1e-3 * float(s.abs().max())
                self.terms[k].log_stiffness.fill_(math.log(max(sk, 1e-30)))
            return
        for k in self.kinds:
            ke = sum(float(sj) * phi for (kind, phi), sj in zip(owner, s) if kind == k)
            ke = ke.clamp(min=max(1e-3 * float(ke.abs().max()), 1e-300))
            self.terms[k].log_stiffness.fill_(math.log(float(ke.mean())))
            getattr(self, f"{k}_prior").copy_(ke / ke.mean())

    def _balance_columns(self, youngs, x1) -> tuple[list, list]:
        """The least-squares fit's columns: the forces on the free nodes at ``x1 (B, N, 3)``
        of each element type with ``g = 1`` (``uniform``), or of each of its basis functions
        (``features``, ``_basis``) as the elements' stiffness; and per column ``(kind,
        basis function)`` (``features`` only). The frames go through the element MLPs in
        chunks (``fit_chunk``): every frame's columns are computed alone, so the chunks
        give the same bits as one pass, whose activations (``(B, n, hidden)`` float64, about
        ten of them) took 2.9 GB on the plate's training split."""
        B = len(x1)
        step = self.fit_chunk()
        cols, owner = None, []
        for s in range(0, B, step):
            part, owner = self._balance_block(youngs[s:s + step], x1[s:s + step])
            if cols is None:
                cols = [c.new_empty(B, c.shape[1]) for c in part]
            for c, p in zip(cols, part):
                c[s:s + step] = p
        return [c.reshape(-1) for c in cols], owner

    def fit_chunk(self) -> int:
        """Frames per chunk of ``_balance_columns``: ``FIT_CHUNK_BYTES`` per activation of
        the widest element type's MLP, a multiple of ``FIT_CHUNK_ALIGN`` frames."""
        per = max(len(getattr(self, f"{k}_nodes")) for k in self.kinds) * self.config.hidden * 8
        frames = FIT_CHUNK_BYTES // max(per, 1)
        return max(FIT_CHUNK_ALIGN, frames - frames % FIT_CHUNK_ALIGN)

    def _balance_block(self, youngs, x1) -> tuple[list, list]:
        """``_balance_columns`` of the frames ``x1 (b, N, 3)``: columns ``(b, 3 n_free)``."""
        lhs, owner = [], []
        B, N = x1.shape[:2]
        for k in self.kinds:
            one = EnergySystem(nn.ModuleDict({k: self.terms[k]}), {k: self._elems()[k]},
                               {k: getattr(self, f"{k}_sigma")}, youngs, float(self.ystats[0]),
                               (float(self.ystats[1]), float(self.ystats[2])))
            if self.config.stiffness_prior == "uniform":
                lhs.append(one.gradient(x1)[:, self.free].reshape(B, -1))
                continue
            q, dq, _ = one.geometry(x1, second=False)[k]
            d1, _ = one.derivatives(k, q, 1, False)  # g = 1: the force is linear in kappa
            dofs = one._dofs(k, N).reshape(-1)
            for phi in self._basis(k):
                f = x1.new_zeros(B, 3 * N).index_add(1, dofs, ((d1 * phi)[..., None] * dq)
                                                     .reshape(B, -1))
                lhs.append(f.reshape(B, N, 3)[:, self.free].reshape(B, -1))
                owner.append((k, phi))
        return lhs, owner

    def _basis(self, kind: str) -> list:
        """The functions ``(n,)`` of the elements of ``kind`` a ``features`` least-squares
        stiffness is made of: ones and each static feature that varies over the elements
        (``_basis_columns``)."""
        static = getattr(self, f"{kind}_static")
        return [torch.ones_like(static[:, 0])] + [static[:, j] for j in self._basis_columns(kind)]

    def _basis_columns(self, kind: str) -> list:
        """The static features (columns) of ``_basis``: those that vary over the elements."""
        static = getattr(self, f"{kind}_static")
        return [j for j in range(static.shape[1]) if bool(static[:, j].abs().max() > 0)]
