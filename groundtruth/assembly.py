"""Assembly of element gradients and Hessians into global vectors and banded/sparse matrices.

Every energy term works on elements: element ``e`` touches the global degrees of freedom
``dofs[e]`` (shape ``(n_el, d)``) and returns a local gradient ``(n_el, d)`` and a local Hessian
``(n_el, d, d)``. The sparsity pattern is fixed for a mesh, so the map from element entries
to storage positions is computed once and each assembly is a single ``np.bincount``.

Storage is LAPACK band form when the pattern's bandwidth is small (rods, and plate meshes
numbered across the width), otherwise CSR.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg


class Assembler:
    """Scatter element contributions into a global vector and a global matrix.

    Args:
        element_dofs: one ``(n_el, d)`` int array per energy term.
        ndof: number of global degrees of freedom.
        fixed: boolean mask ``(ndof,)`` of clamped dofs; their rows and columns of the
            assembled matrix are replaced by the identity (for Newton updates).
    """

    def __init__(self, element_dofs: list[np.ndarray], ndof: int, fixed: np.ndarray | None = None):
        self.ndof = int(ndof)
        self.element_dofs = [np.asarray(d, dtype=np.int64) for d in element_dofs]
        self.fixed = np.zeros(ndof, bool) if fixed is None else np.asarray(fixed, bool)
        rows = np.concatenate([np.repeat(d, d.shape[1], axis=1).ravel() for d in self.element_dofs]
                              + [np.arange(ndof)])
        cols = np.concatenate([np.tile(d, (1, d.shape[1])).ravel() for d in self.element_dofs]
                              + [np.arange(ndof)])
        self.bandwidth = int(np.max(np.abs(rows - cols))) if rows.size else 0
        self.banded = (2 * self.bandwidth + 1) * 4 < ndof or ndof <= 64
        keep = ~(self.fixed[rows] | self.fixed[cols])
        keep[rows.size - ndof:] = True  # the explicit diagonal; fixed entries become 1
        self._keep = keep
        if self.banded:
            u = self.bandwidth
            self._pos = (u + rows - cols) * ndof + cols
            self._size = (2 * u + 1) * ndof
        else:
            pattern = scipy.sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(ndof, ndof))
            csr = pattern.tocsr()
            csr.sum_duplicates()
            csr.sort_indices()
            self._indptr, self._indices = csr.indptr, csr.indices
            self._pos = _csr_positions(self._indptr, self._indices, rows, cols)
            self._size = self._indices.size
        self._n_el_entries = rows.size - ndof

    def vector(self, grads: list[np.ndarray]) -> np.ndarray:
        """Sum element vectors ``(n_el, d)`` into a global ``(ndof,)`` vector."""
        out = np.zeros(self.ndof)
        for dofs, g in zip(self.element_dofs, grads):
            out += np.bincount(dofs.ravel(), weights=g.ravel(), minlength=self.ndof)
        return out

    def matrix(self, hessians: list[np.ndarray], diagonal: np.ndarray) -> SystemMatrix:
        """Assemble ``sum(element Hessians) + diag(diagonal)`` with fixed dofs set to identity."""
        vals = np.concatenate([h.ravel() for h in hessians] + [diagonal])
        vals = np.where(self._keep, vals, 0.0)
        vals[self._n_el_entries:][self.fixed] = 1.0
        data = np.bincount(self._pos, weights=vals, minlength=self._size)
        if self.banded:
            return SystemMatrix(band=data.reshape(2 * self.bandwidth + 1, self.ndof),
                                bandwidth=self.bandwidth)
        csr = scipy.sparse.csr_matrix((data, self._indices, self._indptr),
                                      shape=(self.ndof, self.ndof))
        return SystemMatrix(csr=csr)


class SystemMatrix:
    """A symmetric tangent matrix in band or CSR storage with ``solve`` and ``toarray``."""

    def __init__(self, band: np.ndarray | None = None, bandwidth: int = 0,
                 csr: scipy.sparse.csr_matrix | None = None):
        self.band, self.bandwidth, self.csr = band, bandwidth, csr

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.band is not None:
            u = self.bandwidth
            return scipy.linalg.solve_banded((u, u), self.band, rhs, check_finite=False)
        return scipy.sparse.linalg.spsolve(self.csr.tocsc(), rhs)

    def toarray(self) -> np.ndarray:
        if self.csr is not None:
            return self.csr.toarray()
        u, n = self.bandwidth, self.band.shape[1]
        dense = np.zeros((n, n))
        for k in range(-u, u + 1):
            row = self.band[u - k]
            if k >= 0:
                dense[np.arange(n - k), np.arange(k, n)] = row[k:]
            else:
                dense[np.arange(-k, n), np.arange(n + k)] = row[:n + k]
        return dense


def _csr_positions(indptr, indices, rows, cols):
    """Index into CSR ``data`` of each (row, col) pair (all pairs must be in the pattern)."""
    starts = indptr[rows]
    pos = np.empty(rows.size, dtype=np.int64)
    for r in np.unique(rows):
        sel = np.flatnonzero(rows == r)
        seg = indices[indptr[r]:indptr[r + 1]]
        pos[sel] = starts[sel] + np.searchsorted(seg, cols[sel])
    return pos
