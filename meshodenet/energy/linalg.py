"""Factorisations of Implicit-Energy's Newton matrices (``meshodenet.energy.model``):
dense Cholesky with an LU fallback or convexifying shifts, and the same three in LAPACK's band
storage for the batched solver's matrices and the training loss (``BandSolve``, differentiable);
the batched solver's line search, on numpy arrays."""

from __future__ import annotations

import numpy as np
import torch
from scipy.linalg import lapack


def factor(A, convexify: bool = False):
    """A factorisation of symmetric ``A (B, n, n)``: Cholesky where ``A`` is positive
    definite, else LU (the exact Newton step), or with ``convexify`` Cholesky of ``A`` with
    growing diagonal shifts (a descent direction of the objective)."""
    L, info = torch.linalg.cholesky_ex(A)
    if not torch.any(info):
        return "cholesky", L
    if not convexify:
        return "lu", torch.linalg.lu_factor(A)
    shift = 1e-6
    while torch.any(info) and shift < 1e4:
        d = torch.diagonal(A, dim1=1, dim2=2).abs()
        bad = (info > 0).to(A.dtype)[:, None, None]
        L, info = torch.linalg.cholesky_ex(A + bad * shift * torch.diag_embed(d))
        shift *= 10
    return "cholesky", L


def substitute(fac, b):
    """``A^{-1} b`` of a factorisation ``fac`` of ``factor``."""
    kind, f = fac
    if kind == "cholesky":
        return torch.cholesky_solve(b[..., None], f)[..., 0]
    return torch.linalg.lu_solve(*f, b[..., None])[..., 0]


def band_factor(ab: np.ndarray):
    """A factorisation of the symmetric matrix in lower band storage ``ab (w + 1, n)``
    (``ab[i - j, j] = A[i, j]``): LAPACK's banded Cholesky (``dpbtrf``), or where it is not
    positive definite its banded LU with partial pivoting (``dgbtrf``, kept with ``ab`` for
    ``band_convexified``); ``O(n w)`` memory either way."""
    c, info = lapack.dpbtrf(ab, lower=1)
    if info == 0:
        return "band", c
    w = len(ab) - 1
    lu, piv, _ = lapack.dgbtrf(general_band(ab), w, w)
    return "lu", lu, piv, ab


def general_band(ab: np.ndarray) -> np.ndarray:
    """The symmetric matrix of lower band storage ``ab (w + 1, n)`` in LAPACK's general band
    storage for ``dgbtrf`` ``(3 w + 1, n)``: ``A[i, j]`` at row ``2 w + i - j``."""
    w, n = len(ab) - 1, ab.shape[1]
    out = np.zeros((3 * w + 1, n))
    out[2 * w] = ab[0]
    for k in range(1, w + 1):
        out[2 * w + k, :n - k] = ab[k, :n - k]    # A[j + k, j]
        out[2 * w - k, k:] = ab[k, :n - k]        # A[j, j + k]
    return out


def band_convexified(ab: np.ndarray):
    """``factor``'s convexified Cholesky in band storage: ``dpbtrf`` of ``ab`` with the
    diagonal grown by ``shift |diag|``, ``shift`` from 1e-6 times 10 until it factorises."""
    shift, info = 1e-6, 1
    while info and shift < 1e4:
        shifted = ab.copy()
        shifted[0] += shift * np.abs(ab[0])
        c, info = lapack.dpbtrf(shifted, lower=1)
        shift *= 10
    return "band", c


def band_substitute(fac, b: np.ndarray) -> np.ndarray:
    """``A^{-1} b`` ``(n,)`` of a factorisation ``fac`` of ``band_factor`` or
    ``band_convexified``."""
    if fac[0] == "band":
        return lapack.dpbtrs(fac[1], b, lower=1)[0]
    w = len(fac[3]) - 1
    return lapack.dgbtrs(fac[1], w, w, b, fac[2])[0]


def band_solve(facs: list, r: np.ndarray) -> np.ndarray:
    """The Newton steps ``-A^{-1} r`` ``(b, n)`` of the factorised matrices ``facs`` (one
    per row of ``r``); an LU step that is not a descent direction is replaced by the
    convexified one (``ImplicitEnergy._newton``)."""
    out = np.empty_like(r)
    for j, fac in enumerate(facs):
        dx = band_substitute(fac, -r[j])
        if fac[0] == "lu" and float(-r[j] @ dx) <= 0:
            facs[j] = fac = band_convexified(fac[3])
            dx = band_substitute(fac, -r[j])
        out[j] = dx
    return out


class BandSolve(torch.autograd.Function):
    """``x = A^{-1} b`` per graph of symmetric ``A`` in lower band storage ``ab (B, w + 1,
    n)`` and ``b (B, n)`` (``band_factor``: Cholesky, or LU where ``A`` is not positive
    definite; no convexifying), differentiable in both: ``db = A^{-1} g``, and ``dA = -db
    x^T`` on the stored entries (an entry below the diagonal stands for both of its
    matrix's entries, so it gets both of theirs). The matrices never exist densely."""

    @staticmethod
    def forward(ctx, ab, b):
        facs = [band_factor(a) for a in ab.detach().cpu().numpy()]
        x = np.stack([band_substitute(f, v) for f, v in zip(facs, b.detach().cpu().numpy())])
        x = torch.from_numpy(x).to(device=b.device, dtype=b.dtype)
        ctx.facs, ctx.width = facs, ab.shape[1] - 1
        ctx.save_for_backward(x)
        return x

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        gb = np.stack([band_substitute(f, v) for f, v in zip(ctx.facs,
                                                                  g.detach().cpu().numpy())])
        gb = torch.from_numpy(gb).to(g)
        gab = _band_outer(gb, x, ctx.width) if ctx.needs_input_grad[0] else None
        return gab, gb


def _band_outer(u: torch.Tensor, v: torch.Tensor, w: int) -> torch.Tensor:
    """``-(u v^T + v u^T)`` below the diagonal and ``-u v`` on it, in band storage ``(B, w
    + 1, n)``: the gradient of ``BandSolve``'s stored entries."""
    B, n = u.shape
    out = u.new_zeros(B, w + 1, n)
    out[:, 0] = -u * v
    for k in range(1, w + 1):
        out[:, k, :n - k] = -(u[:, k:] * v[:, :n - k] + u[:, :n - k] * v[:, k:])
    return out


def armijo_search(evaluate, idx, y, dx, r, phi, order: int, halvings: int = 12):
    """``(y, phi, r, ab)`` at ``y + alpha dx`` per trajectory (numpy arrays), ``alpha``
    halved from 1 until the objective decreases (Armijo), the full step where none does: the
    batched solver's ``ImplicitEnergy._line_search``, the trial steps after the first on the
    energy alone and only for the trajectories still searching."""
    trial = y + dx
    phi_t, r_t, ab_t = evaluate(trial, idx, order)
    slope = (r * dx).sum(1)
    ok = phi_t <= phi + 1e-4 * slope
    if ok.all():
        return trial, phi_t, r_t, ab_t
    left = np.flatnonzero(~ok)
    alpha = np.ones(len(left))
    found = np.zeros(len(left), bool)
    for _ in range(halvings - 1):
        alpha = np.where(found, alpha, alpha / 2)
        s = np.flatnonzero(~found)
        j = left[s]
        p, _, _ = evaluate(y[j] + alpha[s, None] * dx[j], idx[j], 0)
        found[s] = p <= phi[j] + 1e-4 * alpha[s] * slope[j]
        if found.all():
            break
    j = left[found]
    if len(j):
        trial[j] = y[j] + alpha[found, None] * dx[j]
        p, rr, aa = evaluate(trial[j], idx[j], order)
        phi_t[j], r_t[j] = p, rr
        if ab_t is not None:
            ab_t[j] = aa
    return trial, phi_t, r_t, ab_t


def on_numpy(evaluate, device):
    """``evaluate(y, idx, order)`` of ``ImplicitEnergy._batched_objective`` on tensors (on
    ``device``) as a function of numpy arrays (the batched solver's iteration)."""
    def wrapped(y, idx, order):
        out = evaluate(torch.from_numpy(y).to(device), torch.from_numpy(idx).to(device), order)
        return tuple(None if o is None else o.cpu().numpy() for o in out)

    return wrapped
