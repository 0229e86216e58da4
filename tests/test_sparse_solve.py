"""Newton's linear solvers (groundtruth.assembly): band LU, sparse factorizations, the choice.

The band LU is the solver of the committed data, so the default (``"auto"``) must keep the
paper-resolution cases on it bit for bit; the sparse solvers must agree with it to roundoff
on one matrix and to Newton's tolerance on trajectories.
"""

import dataclasses
import sys

import numpy as np
import pytest
import scipy.sparse

from benchmarks.suite.registry import get_case
from groundtruth import assembly, implicit
from groundtruth.assembly import (
    LINEAR_SOLVERS,
    SPARSE_BACKENDS,
    Assembler,
    SparseSolver,
    available_backend,
    uses_band,
)

PAPER_CASES = ("rod_falling", "rod_cantilever", "plate_cantilever", "plate_hanging")


def _backends():
    out = ["superlu"]
    if assembly._AVAILABLE["pardiso"]():
        out.append("pardiso")
    return out


def _spd(n, seed, shift=1.0):
    """A sparse SPD matrix: a 1-D chain and random long-range couplings, plus ``shift`` I."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, n, 3 * n)
    j = rng.integers(0, n, 3 * n)
    b = scipy.sparse.coo_matrix((rng.normal(size=i.size), (i, j)), shape=(n, n)).tocsr()
    a = (b @ b.T + scipy.sparse.diags(np.full(n, shift))).tocsr()
    a.sort_indices()
    return a


def _simulate(case_id, solver, n_steps):
    case = get_case(case_id)
    system = dataclasses.replace(case.system(case.reference_youngs), linear_solver=solver)
    q0, v0 = case.initial_state()
    t = np.arange(n_steps + 1) * case.solver_settings.dt
    return implicit.simulate(system, q0.ravel(), v0.ravel(), t, case.solver_settings)[0], system


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("seed", [0, 1])
def test_sparse_solver_matches_dense(backend, seed):
    a = _spd(60, seed)
    rhs = np.random.default_rng(seed + 10).normal(size=60)
    solver = SparseSolver(a.indptr, a.indices, np.ones(60, bool), backend=backend)
    for scale in (1.0, 3.0):  # a second matrix of the same pattern reuses the analysis
        m = a * scale
        x = solver.solve(solver.factor(m.data), rhs, m)
        ref = np.linalg.solve(m.toarray(), rhs)
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-10 * np.max(np.abs(ref)))


@pytest.mark.parametrize("backend", _backends())
def test_sparse_solver_resting_dofs(backend):
    """Resting dofs (zero right-hand side, uncoupled) get a zero update; a nonzero right-hand
    side there makes the solver fall back to the whole system."""
    a = _spd(40, 3).tolil()
    rest = np.zeros(40, bool)
    rest[::4] = True
    a[np.ix_(rest, ~rest)] = 0.0
    a[np.ix_(~rest, rest)] = 0.0
    a = a.tocsr()
    a.sort_indices()
    solver = SparseSolver(a.indptr, a.indices, ~rest, backend=backend)
    rhs = np.random.default_rng(4).normal(size=40)
    rhs[rest] = 0.0
    x = solver.solve(solver.factor(a.data), rhs, a)
    assert np.all(x[rest] == 0.0)
    np.testing.assert_allclose(x, np.linalg.solve(a.toarray(), rhs), rtol=0, atol=1e-10)
    rhs[rest] = 1.0
    x = solver.solve(solver.factor(a.data), rhs, a)
    np.testing.assert_allclose(x, np.linalg.solve(a.toarray(), rhs), rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", _backends())
def test_sparse_solver_indefinite_falls_back(backend):
    """An indefinite matrix (a static tangent past buckling) is still solved to roundoff."""
    a = _spd(50, 5, shift=0.0) - scipy.sparse.identity(50) * 2.0
    a = a.tocsr()
    a.sort_indices()
    assert np.linalg.eigvalsh(a.toarray()).min() < 0
    rhs = np.arange(50.0)
    solver = SparseSolver(a.indptr, a.indices, np.ones(50, bool), backend=backend)
    x = solver.solve(solver.factor(a.data), rhs, a)
    np.testing.assert_allclose(a @ x, rhs, rtol=0, atol=1e-8 * np.max(np.abs(rhs)))


@pytest.mark.parametrize("solver", ["banded", "sparse"])
def test_assembled_matrix_solves_like_dense(solver):
    """Assembled with clamped dofs, each storage solves as the dense matrix does."""
    rng = np.random.default_rng(7)
    dofs = np.stack([np.arange(0, 90, 3), np.arange(1, 91, 3) % 90, np.arange(5, 95, 3) % 90], 1)
    h = rng.normal(size=(30, 3, 3))
    h = np.einsum("eij,ekj->eik", h, h)
    fixed = np.zeros(90, bool)
    fixed[:3] = True
    asm = Assembler([dofs], 90, fixed, solver=solver)
    k = asm.matrix([h], np.full(90, 2.0))
    rhs = rng.normal(size=90)
    ref = np.linalg.solve(k.toarray(), rhs)
    np.testing.assert_allclose(k.solve(rhs), ref, rtol=0, atol=1e-10 * np.max(np.abs(ref)))


@pytest.mark.parametrize("case_id", PAPER_CASES)
def test_default_keeps_paper_cases_bit_identical(case_id):
    """At r = 1 the default solver is the band LU: trajectories equal to the bit."""
    pos_default, system = _simulate(case_id, "auto", 6)
    assert system.assembler.banded
    pos_banded, _ = _simulate(case_id, "banded", 6)
    assert np.array_equal(pos_default, pos_banded)


def test_sparse_agrees_with_banded_at_r2():
    """plate_cantilever@r2 over 30 steps: positions within Newton's tolerance, z exactly 0."""
    pos_b, _ = _simulate("plate_cantilever@r2", "banded", 30)
    pos_s, system = _simulate("plate_cantilever@r2", "sparse", 30)
    assert system.assembler.sparse is not None
    assert system.assembler.sparse.active.size == 2 * system.n_nodes  # z left out
    scale = np.max(np.abs(pos_b - pos_b[0]))
    assert scale > 0
    assert np.max(np.abs(pos_s - pos_b)) <= 1e-8 * np.max(np.abs(pos_b))
    assert np.all(pos_s[:, 2::3] == 0.0)


def test_auto_switches_by_measured_crossover():
    assert uses_band("auto", 546, 32) and uses_band("auto", 1929, 56)  # plate r = 1, 2
    assert not uses_band("auto", 7215, 104)  # plate r = 4
    assert uses_band("auto", 483, 8)  # rod r = 8
    assert uses_band("banded", 7215, 104) and not uses_band("sparse", 546, 32)
    assert get_case("plate_cantilever@r4").system(5e6).assembler.sparse is not None


def test_bad_linear_solver_lists_valid_names():
    case = get_case("rod_falling")
    with pytest.raises(ValueError, match="linear_solver must be one of") as err:
        dataclasses.replace(case.system(1e9), linear_solver="cholesky")
    assert all(name in str(err.value) for name in LINEAR_SOLVERS)


def test_missing_pardiso_falls_back_to_superlu(monkeypatch):
    monkeypatch.setitem(sys.modules, "pypardiso", None)  # import raises ImportError
    assert available_backend() == "superlu"
    system = get_case("plate_cantilever@r4").system(5e6)
    assert system.assembler.sparse.backend == "superlu"
    assert list(SPARSE_BACKENDS)[-1] == "superlu"


def _flat_hinges(n, seed):
    """``n`` random flat, unfolded hinges ``(n, 12)`` at a common random z: x2 on one side of
    the edge, x3 on the other."""
    rng = np.random.default_rng(seed)
    x0 = rng.normal(size=(n, 2))
    e = rng.normal(size=(n, 2))
    normal = np.stack([-e[:, 1], e[:, 0]], axis=1)
    x1 = x0 + e
    x2 = x0 + rng.uniform(0.1, 0.9, (n, 1)) * e + rng.uniform(0.2, 1.0, (n, 1)) * normal
    x3 = x0 + rng.uniform(0.1, 0.9, (n, 1)) * e - rng.uniform(0.2, 1.0, (n, 1)) * normal
    z = np.full((n, 1), rng.normal())
    return np.concatenate([np.concatenate([x, z], axis=1) for x in (x0, x1, x2, x3)], axis=1)


def test_flat_hinges_act_on_z_only():
    """What lets an in-plane plate skip its hinges: flat at rest, their energy and gradient are
    exactly 0 and their Hessian is exactly 0 wherever an x or y coordinate is involved."""
    from groundtruth.hinge import HingeTerm

    xe = _flat_hinges(200, 0)
    term = HingeTerm(np.arange(800).reshape(200, 4), 0.0, np.linspace(1.0, 3.0, 200))
    assert term.flat_at_rest(xe)
    energy, grad, hess = term.evaluate(xe, 2)
    assert np.all(energy == 0) and np.all(grad == 0)
    inplane = np.ones(12, bool)
    inplane[2::3] = False
    assert np.all(hess[:, inplane, :] == 0) and np.all(hess[:, :, inplane] == 0)
    assert np.any(hess[:, ~inplane][:, :, ~inplane] != 0)  # bending out of the plane is there


@pytest.mark.parametrize("change", ["lifted", "folded", "bent at rest"])
def test_hinges_that_are_not_flat_at_rest_are_kept(change):
    from groundtruth.hinge import HingeTerm

    xe = _flat_hinges(50, 1)
    theta_bar = np.zeros(50)
    if change == "lifted":
        xe[7, 11] += 1e-9                      # x3 of one hinge out of the plane
    elif change == "folded":
        xe[7, 9:11] = 2 * xe[7, 6:8] - xe[7, 0:2]  # x3 onto x2's side: a hinge folded over
    else:
        theta_bar[7] = 0.1
    assert not HingeTerm(np.arange(200).reshape(50, 4), theta_bar, 1.0).flat_at_rest(xe)


def test_in_plane_plate_skips_its_hinges_bit_for_bit():
    """plate_cantilever at r = 4 (sparse path, z at rest) skips its hinges; its trajectory is
    the one with the hinges evaluated and assembled, bit for bit."""
    case = get_case("plate_cantilever@r4")
    system = case.system(case.reference_youngs)
    assert system.assembler.sparse is not None and system._restable == [False, True]
    q0, v0 = case.initial_state()
    assert system._evaluate(q0.ravel(), 2)[1] is None
    t = np.arange(4) * case.solver_settings.dt
    skipped = implicit.simulate(system, q0.ravel(), v0.ravel(), t, case.solver_settings)[0]
    system._restable = [False, False]
    kept = implicit.simulate(system, q0.ravel(), v0.ravel(), t, case.solver_settings)[0]
    assert np.array_equal(skipped, kept)


def test_band_path_evaluates_every_term():
    system = get_case("plate_cantilever").system(5e6)
    assert system.assembler.sparse is None and not any(system._restable)
