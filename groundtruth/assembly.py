"""Assembly of element gradients and Hessians into global vectors and banded/sparse matrices.

Every energy term works on elements: element ``e`` touches the global degrees of freedom
``dofs[e]`` (shape ``(n_el, d)``) and returns a local gradient ``(n_el, d)`` and a local Hessian
``(n_el, d, d)``. The sparsity pattern is fixed for a mesh, so the map from element entries
to storage positions is computed once and each assembly is a single ``np.bincount``.

The linear solver (``LINEAR_SOLVERS``) decides the storage:

- ``"banded"``: LAPACK band form and ``scipy.linalg.solve_banded`` (LU with partial pivoting)
  when the pattern's bandwidth is small (rods, and plate meshes numbered across the width),
  otherwise CSR and ``scipy.sparse.linalg.spsolve``. This is the solver of the committed data.
- ``"sparse"``: CSR and a sparse factorization with a fill-reducing ordering whose analysis is
  done once per pattern (``SparseSolver``): MKL PARDISO (through ``pypardiso``, if importable)
  or SciPy's SuperLU. Dofs that the physics keeps at rest exactly (``resting``: the z of an
  in-plane plate) are left out of the factorization.
- ``"auto"`` (the default): ``"banded"`` while its cost is measured to be no higher, i.e. while
  ``bandwidth**2 <= BANDED_CROSSOVER * sqrt(ndof)`` (rods at every resolution, the plates at
  r = 1 and 2), ``"sparse"`` beyond (docs/SCALE.md, "Ground truth at scale").
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

LINEAR_SOLVERS = ("auto", "banded", "sparse")
#: ``"auto"`` keeps the band solver while ``bandwidth**2 <= BANDED_CROSSOVER * sqrt(ndof)``:
#: band LU costs ~ ndof bandwidth^2, a nested-dissection-like sparse factorization of a 2-D
#: mesh ~ ndof^1.5; the constant is the measured crossover of SciPy's SuperLU against the band
#: LU on ``plate_cantilever`` (between r = 2, 71, and r = 4, 127).
BANDED_CROSSOVER = 100.0


def check_linear_solver(name: str) -> str:
    if name not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {name!r}")
    return name


def uses_band(solver: str, ndof: int, bandwidth: int) -> bool:
    """Whether ``solver`` (one of ``LINEAR_SOLVERS``) factors a pattern of this size and
    bandwidth with the band LU (else a sparse factorization)."""
    fits_band = (2 * bandwidth + 1) * 4 < ndof or ndof <= 64
    if check_linear_solver(solver) == "auto":
        return fits_band and bandwidth**2 <= BANDED_CROSSOVER * np.sqrt(ndof)
    return solver == "banded" and fits_band


class Assembler:
    """Scatter element contributions into a global vector and a global matrix.

    Args:
        element_dofs: one ``(n_el, d)`` int array per energy term.
        ndof: number of global degrees of freedom.
        fixed: boolean mask ``(ndof,)`` of clamped dofs; their rows and columns of the
            assembled matrix are replaced by the identity (for Newton updates).
        solver: one of ``LINEAR_SOLVERS`` (module docstring).
        resting: boolean mask ``(ndof,)`` of dofs that the physics keeps at rest exactly: no
            load, no velocity and no coupling to the other dofs (the z of an in-plane plate).
            The sparse solver leaves them out (their update is zero); the band solver ignores it.
    """

    def __init__(self, element_dofs: list[np.ndarray], ndof: int, fixed: np.ndarray | None = None,
                 solver: str = "auto", resting: np.ndarray | None = None):
        self.ndof = int(ndof)
        self.element_dofs = [np.asarray(d, dtype=np.int64) for d in element_dofs]
        self.fixed = np.zeros(ndof, bool) if fixed is None else np.asarray(fixed, bool)
        rows = np.concatenate([np.repeat(d, d.shape[1], axis=1).ravel() for d in self.element_dofs]
                              + [np.arange(ndof)])
        cols = np.concatenate([np.tile(d, (1, d.shape[1])).ravel() for d in self.element_dofs]
                              + [np.arange(ndof)])
        self.bandwidth = int(np.max(np.abs(rows - cols))) if rows.size else 0
        self.solver = check_linear_solver(solver)
        self.banded = uses_band(solver, ndof, self.bandwidth)
        keep = ~(self.fixed[rows] | self.fixed[cols])
        keep[rows.size - ndof:] = True  # the explicit diagonal; fixed entries become 1
        self.sparse = None
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
            if solver != "banded":
                active = np.ones(ndof, bool) if resting is None else ~np.asarray(resting, bool)
                self.sparse = SparseSolver(self._indptr, self._indices, active)
        self._keep = keep
        sizes = [d.shape[0] * d.shape[1] ** 2 for d in self.element_dofs]
        self._starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self._layouts = {}
        self._layout(None)

    def _layout(self, used) -> tuple:
        """``(positions, dropped entries, number of element entries)`` of the concatenated
        values when only the terms flagged in ``used`` are assembled (all for ``None``)."""
        key = None if used is None or all(used) else tuple(bool(u) for u in used)
        if key not in self._layouts:
            if key is None:
                pos, keep = self._pos, self._keep
                n_el = int(self._starts[-1])
            else:
                idx = np.concatenate([np.arange(self._starts[i], self._starts[i + 1])
                                      for i, u in enumerate(key) if u]
                                     + [np.arange(self._starts[-1], self._pos.size)])
                pos, keep = self._pos[idx], self._keep[idx]
                n_el = idx.size - self.ndof
            self._layouts[key] = (pos, np.flatnonzero(~keep), n_el)
        return self._layouts[key]

    def _used_dofs(self, used) -> list:
        return self.element_dofs if used is None else [
            d for d, u in zip(self.element_dofs, used) if u]

    def vector(self, grads: list[np.ndarray], used: list[bool] | None = None) -> np.ndarray:
        """Sum element vectors ``(n_el, d)`` into a global ``(ndof,)`` vector; with ``used``
        (one flag per term), ``grads`` holds the flagged terms' only (the others add 0)."""
        out = np.zeros(self.ndof)
        for dofs, g in zip(self._used_dofs(used), grads):
            out += np.bincount(dofs.ravel(), weights=g.ravel(), minlength=self.ndof)
        return out

    def matrix(self, hessians: list[np.ndarray], diagonal: np.ndarray,
               used: list[bool] | None = None) -> SystemMatrix:
        """Assemble ``sum(element Hessians) + diag(diagonal)`` with fixed dofs set to identity;
        with ``used`` (one flag per term), ``hessians`` holds the flagged terms' only."""
        pos, dropped, n_el = self._layout(used)
        vals = np.concatenate([h.ravel() for h in hessians] + [diagonal])
        vals[dropped] = 0.0  # entries of clamped rows and columns (a few)
        vals[n_el:][self.fixed] = 1.0
        data = np.bincount(pos, weights=vals, minlength=self._size)
        if self.banded:
            return SystemMatrix(band=data.reshape(2 * self.bandwidth + 1, self.ndof),
                                bandwidth=self.bandwidth)
        csr = scipy.sparse.csr_matrix((data, self._indices, self._indptr),
                                      shape=(self.ndof, self.ndof))
        return SystemMatrix(csr=csr, sparse=self.sparse)


class SystemMatrix:
    """A symmetric tangent matrix in band or CSR storage with ``solve`` and ``toarray``.

    With ``sparse`` (a ``SparseSolver`` of the CSR pattern) ``solve`` factors the matrix once,
    on its first call, with that solver; without it, CSR is solved by ``spsolve``."""

    def __init__(self, band: np.ndarray | None = None, bandwidth: int = 0,
                 csr: scipy.sparse.csr_matrix | None = None, sparse: SparseSolver | None = None):
        self.band, self.bandwidth, self.csr, self.sparse = band, bandwidth, csr, sparse
        self._factor = None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.band is not None:
            u = self.bandwidth
            return scipy.linalg.solve_banded((u, u), self.band, rhs, check_finite=False)
        if self.sparse is None:
            return scipy.sparse.linalg.spsolve(self.csr.tocsc(), rhs)
        if self._factor is None:
            self._factor = self.sparse.factor(self.csr.data)
        return self.sparse.solve(self._factor, rhs, self.csr)

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


class SparseSolver:
    """Factor and solve symmetric matrices of one CSR pattern, reusing its analysis.

    The pattern's active block (rows and columns ``active``) is factored; ``solve`` sets the
    update of the other (resting) dofs to zero when their right-hand side is exactly zero, as
    Newton's is for dofs at rest, and falls back to SuperLU on the whole matrix otherwise. The
    backend is the first importable of ``SPARSE_BACKENDS``: MKL PARDISO (``pypardiso``; SPD
    Cholesky, its ordering and symbolic factorization done once) or SciPy's SuperLU (its
    minimum-degree ordering of A^T + A computed once, then each matrix is factored symmetrically
    permuted with the natural ordering). A factorization whose residual is not at roundoff
    (an indefinite tangent: static solves past a buckling load) is redone with SuperLU's default
    partial pivoting.

    Args:
        indptr, indices: the CSR pattern ``(ndof, ndof)``, sorted, symmetric.
        active: boolean ``(ndof,)``, the dofs to factor.
        backend: a key of ``SPARSE_BACKENDS``; default: the first available.
    """

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, active: np.ndarray,
                 backend: str | None = None):
        self.active = np.flatnonzero(active)
        self._resting = np.flatnonzero(~np.asarray(active, bool))
        n = indptr.size - 1
        rows = np.repeat(np.arange(n), np.diff(indptr))
        sub = np.zeros(n, np.int64) - 1
        sub[self.active] = np.arange(self.active.size)
        keep = (sub[rows] >= 0) & (sub[indices] >= 0)
        self._take = np.flatnonzero(keep)  # CSR order is kept: the block is CSR as well
        r, c = sub[rows[keep]], sub[indices[keep]]
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=self.active.size))])
        self.indices = c
        self.backend = backend or available_backend()
        self._impl = SPARSE_BACKENDS[self.backend](self.indptr, self.indices)

    def factor(self, data: np.ndarray):
        """Factor the matrix with CSR values ``data`` (on the full pattern); ``None`` if the
        backend fails (PARDISO's Cholesky on an indefinite matrix), then ``solve`` uses SuperLU."""
        try:
            return self._impl.factor(data[self._take])
        except Exception:  # pypardiso's PyPardisoError derives from Exception
            return None

    def solve(self, lu, rhs: np.ndarray, csr: scipy.sparse.csr_matrix) -> np.ndarray:
        """``x (ndof,)`` with ``csr x = rhs``; ``lu`` is ``factor(csr.data)``."""
        if np.any(rhs[self._resting] != 0):  # not at rest: solve the whole system
            return scipy.sparse.linalg.splu(csr.tocsc()).solve(rhs)
        x = np.zeros_like(rhs)
        b = rhs[self.active]
        block = self._block(csr.data)
        if lu is not None:
            x[self.active] = self._impl.solve(lu, b)
        if lu is None or not _accurate(block, x[self.active], b):
            x[self.active] = scipy.sparse.linalg.splu(block.tocsc()).solve(b)
        return x

    def _block(self, data):
        n = self.active.size
        return scipy.sparse.csr_matrix((data[self._take], self.indices, self.indptr), shape=(n, n))


def _accurate(a, x, b) -> bool:
    """``|A x - b| <= 1e-9 (|A| |x| + |b|)`` in the max norm (a stable solve reaches ~1e-15)."""
    scale = abs(a).max() * np.max(np.abs(x)) + np.max(np.abs(b))
    return bool(np.max(np.abs(a @ x - b)) <= 1e-9 * scale)


class _SuperLU:
    """SciPy SuperLU: the minimum-degree ordering of A^T + A from the first matrix, then
    each matrix permuted symmetrically (one gather of its values) and factored in that order
    with diagonal pivots."""

    def __init__(self, indptr, indices):
        self.n = indptr.size - 1
        self.indptr, self.indices, self.perm = indptr, indices, None

    def _order(self, data):
        a = scipy.sparse.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        # splu factors Pr A Pc with column j of A Pc = column argsort(perm_c)[j] of A
        perm_c = scipy.sparse.linalg.splu(a, permc_spec="MMD_AT_PLUS_A").perm_c
        self.perm = np.argsort(perm_c)
        ids = scipy.sparse.csr_matrix((np.arange(1.0, data.size + 1), self.indices, self.indptr),
                                      shape=(self.n, self.n))
        p = ids[self.perm][:, self.perm].tocsc()
        p.sort_indices()
        self._gather = p.data.astype(np.int64) - 1
        self._pindptr, self._pindices = p.indptr, p.indices

    def factor(self, data):
        if self.perm is None:
            self._order(data)
        a = scipy.sparse.csc_matrix((data[self._gather], self._pindices, self._pindptr),
                                    shape=(self.n, self.n))
        return scipy.sparse.linalg.splu(a, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                        options={"SymmetricMode": True})

    def solve(self, lu, b):
        x = np.empty_like(b)
        x[self.perm] = lu.solve(b[self.perm])
        return x


class _Pardiso:
    """MKL PARDISO through ``pypardiso`` as SPD Cholesky (mtype 2, upper triangle): phase 11
    (ordering, symbolic factorization) once, phase 22 (numeric) per matrix, phase 33 per solve.
    The handle holds one factorization, so ``factor`` returns a token and a solve with an older
    token factors again."""

    def __init__(self, indptr, indices):
        import pypardiso

        n = indptr.size - 1
        rows = np.repeat(np.arange(n), np.diff(indptr))
        self._upper = np.flatnonzero(indices >= rows)
        up = np.zeros(indices.size)
        up[self._upper] = 1.0
        self._a = scipy.sparse.csr_matrix((up, indices, indptr), shape=(n, n))
        self._a.eliminate_zeros()  # the upper triangle's pattern (every entry is 1 here)
        self._a.sort_indices()
        self._solver = pypardiso.PyPardisoSolver(mtype=2)
        self._solver._check_A(self._a)
        self._analysed, self._current = False, 0

    def _call(self, phase, data, b):
        self._a.data[:] = data[self._upper]
        self._solver.set_phase(phase)
        return self._solver._call_pardiso(self._a, b)

    def factor(self, data):
        b = np.zeros(self._a.shape[0])
        if not self._analysed:
            self._call(11, data, b)
            self._analysed = True
        self._call(22, data, b)
        self._current += 1
        return (self._current, data)

    def __del__(self):
        try:  # MKL keeps the factorization in its own memory until phase -1
            if self._analysed:
                self._solver.free_memory(everything=True)
        except Exception:  # at interpreter shutdown there is nothing left to free
            pass

    def solve(self, lu, b):
        token, data = lu
        if token != self._current:
            token, _ = lu = self.factor(data)
        return self._call(33, data, np.ascontiguousarray(b))


def _pardiso_available() -> bool:
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return False
    return True


#: Sparse backends by preference; ``available`` says whether the package imports.
SPARSE_BACKENDS = {"pardiso": _Pardiso, "superlu": _SuperLU}
_AVAILABLE = {"pardiso": _pardiso_available, "superlu": lambda: True}


def available_backend() -> str:
    """The first key of ``SPARSE_BACKENDS`` whose package imports (``"superlu"`` always does)."""
    return next(k for k in SPARSE_BACKENDS if _AVAILABLE[k]())


def _csr_positions(indptr, indices, rows, cols):
    """Index into CSR ``data`` of each (row, col) pair (all pairs must be in the pattern):
    a sorted CSR pattern lists its keys ``row * n + col`` in increasing order."""
    n = indptr.size - 1
    keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) * n + indices
    return np.searchsorted(keys, rows * n + cols)
