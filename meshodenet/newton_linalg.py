"""Factorisations of Implicit-Energy's Newton matrices (``meshodenet.models.energy``):
dense Cholesky with an LU fallback or convexifying shifts, and LAPACK's banded Cholesky for the
batched solver's matrices in band storage."""

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

def band_solve(facs: list, r: torch.Tensor) -> torch.Tensor:
    """The Newton steps ``-A^{-1} r`` ``(b, n)`` of the factorised matrices ``facs`` (one
    per row of ``r``); a dense LU step that is not a descent direction is replaced by the
    convexified one (``ImplicitEnergy._newton``)."""
    rhs = (-r).cpu().numpy()
    out = np.empty_like(rhs)
    for j, fac in enumerate(facs):
        if fac[0] == "band":
            out[j] = lapack.dpbtrs(fac[1], rhs[j], lower=1)[0]
            continue
        b = torch.as_tensor(rhs[j])[None]
        dx = substitute(fac[1], b)
        if fac[1][0] == "lu" and float((b * dx).sum()) <= 0:
            facs[j] = fac = ("dense", factor(fac[2], convexify=True), fac[2])
            dx = substitute(fac[1], b)
        out[j] = dx[0].numpy()
    return torch.as_tensor(out).to(r)
