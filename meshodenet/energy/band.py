"""Where an ``EnergySystem``'s element Hessians go in LAPACK's lower band storage
(``BandPattern``): the training loss's and the batched solver's Newton matrices without a dense
``(n, n)`` matrix (``meshodenet.energy.linalg`` factorises them)."""

from __future__ import annotations

import numpy as np
import torch

from meshodenet.mesh.graph import band_order


class BandPattern:
    """Where the element Hessians of ``sys`` (an ``EnergySystem``) go in LAPACK's lower band storage, on the
    coordinates ``act`` of its Newton solves (``n`` of them), reordered so that the matrix is
    banded (``band_order``): ``unknowns (n,)`` the flat coordinates ``3 node + axis`` in that
    order (``cols`` the same as numpy), ``width`` the number of sub-diagonals, and per element
    kind ``maps[kind] = (g_at, g_to, h_at, h_to)``: the entries of its elements' flattened
    gradients ``(n_e 3k)`` that are unknowns and their positions in ``(n,)``, and the entries
    of their flattened Hessians ``(n_e 3k 3k)`` on or below the band's diagonal and their
    positions in the flattened band ``((width + 1) n)``, ``ab[i - j, j] = H[i, j]``. It depends
    on the mesh and ``act`` only, so one serves every batch and every step."""

    def __init__(self, sys, act: torch.Tensor, n_nodes: int):
        dev, n = act.device, len(act)
        where = torch.full((3 * n_nodes,), -1, dtype=torch.long, device=dev)
        where[act] = torch.arange(n, device=dev)
        dofs = {k: where[sys._dofs(k, n_nodes)] for k in sys.elems}   # -1: not an unknown
        pairs = torch.cat([torch.stack(torch.broadcast_tensors(d[:, :, None], d[:, None, :]),
                                       -1).reshape(-1, 2) for d in dofs.values()])
        perm = band_order(pairs[(pairs >= 0).all(1)].cpu().numpy(), n)
        rank = np.full(n + 1, -1, np.int64)  # old index -> new position; rank[-1] = -1
        rank[perm] = np.arange(n)
        self.unknowns = act[torch.as_tensor(perm, device=dev)]
        self.cols = self.unknowns.cpu().numpy()
        self.n, self.width, self.maps = n, 0, {}
        for k, d in dofs.items():
            s = torch.as_tensor(rank, device=dev)[d]                     # (n_e, 3k)
            a, b = (z.reshape(-1) for z in torch.broadcast_tensors(s[:, :, None], s[:, None, :]))
            g_at = torch.nonzero(s.reshape(-1) >= 0)[:, 0]
            h_at = torch.nonzero((b >= 0) & (a >= b))[:, 0]
            self.width = max(self.width, int((a - b)[h_at].max()) if len(h_at) else 0)
            self.maps[k] = (g_at, s.reshape(-1)[g_at], h_at, ((a - b) * n + b)[h_at])

    def band(self, he: dict, diag: torch.Tensor | None = None) -> torch.Tensor:
        """``ab (B, width + 1, n)``: the sum of the element Hessians ``he[kind] (B, n_e, 3k,
        3k)`` (any of the kinds) and the diagonal ``diag (B, n)`` or ``(n,)`` (in
        ``unknowns``' order) in band storage, differentiable in both."""
        ref = next(iter(he.values()), None)
        B = len(ref if ref is not None else diag)
        ab = (ref if ref is not None else diag).new_zeros(B, (self.width + 1) * self.n)
        for k, h in he.items():
            _, _, h_at, h_to = self.maps[k]
            ab = ab.index_add(1, h_to, h.reshape(B, -1)[:, h_at])
        ab = ab.reshape(B, self.width + 1, self.n)
        if diag is None:
            return ab
        return torch.cat([ab[:, :1] + diag.expand(B, self.n)[:, None], ab[:, 1:]], 1)
