"""Factorisations of Implicit-Energy's Newton matrices (``meshodenet.energy.model``):
dense Cholesky with an LU fallback or convexifying shifts, and LAPACK's banded Cholesky for the
batched solver's matrices in band storage; the batched solver's line search, on numpy
arrays."""

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
    """A factorisation of the symmetric matrix in lower band storage ``ab (w + 1, n)``:
    LAPACK's banded Cholesky (``dpbtrf``); where it is not positive definite, ``factor``'s
    on the dense matrix (its LU, kept with the matrix for the convexified Cholesky)."""
    c, info = lapack.dpbtrf(ab, lower=1)
    if info == 0:
        return "band", c
    w, n = ab.shape
    A = np.zeros((n, n))
    for k in range(w):
        i = np.arange(n - k)
        A[i + k, i] = A[i, i + k] = ab[k, :n - k]
    A = torch.as_tensor(A)[None]
    return "dense", factor(A), A

def band_solve(facs: list, r: np.ndarray) -> np.ndarray:
    """The Newton steps ``-A^{-1} r`` ``(b, n)`` of the factorised matrices ``facs`` (one
    per row of ``r``); a dense LU step that is not a descent direction is replaced by the
    convexified one (``ImplicitEnergy._newton``)."""
    out = np.empty_like(r)
    for j, fac in enumerate(facs):
        if fac[0] == "band":
            out[j] = lapack.dpbtrs(fac[1], -r[j], lower=1)[0]
            continue
        b = torch.as_tensor(-r[j])[None]
        dx = substitute(fac[1], b)
        if fac[1][0] == "lu" and float((b * dx).sum()) <= 0:
            facs[j] = fac = ("dense", factor(fac[2], convexify=True), fac[2])
            dx = substitute(fac[1], b)
        out[j] = dx[0].numpy()
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
