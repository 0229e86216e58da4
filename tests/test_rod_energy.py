"""Finite-difference and invariance checks of the DER energies and their assembly."""

import numpy as np
import pytest

from groundtruth.cases import RodCase
from groundtruth.rod import bending, curvature_binormal, rod_terms
from groundtruth.stretch import spring
from groundtruth.system import MechanicalSystem


def fd_check(f, x, h=1e-6):
    """Central differences of energy -> gradient and gradient -> Hessian; relative errors."""
    _, g, H = f(x, 2)
    d = x.shape[1]
    g_fd, H_fd = np.zeros_like(g), np.zeros_like(H)
    for i in range(d):
        dx = np.zeros(d)
        dx[i] = h
        g_fd[:, i] = (f(x + dx, 0)[0] - f(x - dx, 0)[0]) / (2 * h)
        H_fd[:, :, i] = (f(x + dx, 1)[1] - f(x - dx, 1)[1]) / (2 * h)
    return (np.abs(g - g_fd).max() / np.abs(g).max(), np.abs(H - H_fd).max() / np.abs(H).max())


def random_triples(rng, n, max_turn):
    """Node triples with edge lengths in [0.5, 1.5] and turning angles up to ``max_turn``."""
    out = []
    for _ in range(n):
        e = rng.normal(size=3)
        e /= np.linalg.norm(e)
        axis = np.cross(e, rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        phi = rng.uniform(-max_turn, max_turn)
        f = e * np.cos(phi) + np.cross(axis, e) * np.sin(phi)
        x0 = rng.normal(size=3)
        x1 = x0 + rng.uniform(0.5, 1.5) * e
        x2 = x1 + rng.uniform(0.5, 1.5) * f
        out.append(np.concatenate([x0, x1, x2]))
    return np.array(out)


@pytest.mark.parametrize("max_turn", [0.3, 2.0, 2.9])  # gentle, strongly bent, almost folded
def test_bending_fd(max_turn):
    rng = np.random.default_rng(1)
    x = random_triples(rng, 20, max_turn)
    kappa0 = rng.normal(size=(20, 3)) * 0.5
    EI, lv = rng.uniform(0.5, 2, 20), rng.uniform(0.5, 1.5, 20)

    def f(X, order):
        return bending(X[:, :3], X[:, 3:6], X[:, 6:], kappa0, EI, lv, order)

    eg, eh = fd_check(f, x, h=1e-6 if max_turn < 2.5 else 1e-7)
    assert eg < 1e-6 and eh < 1e-5, (eg, eh)


def test_stretching_fd():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(30, 6))
    l0, k = rng.uniform(0.3, 2, 30), rng.uniform(1, 5, 30)

    def f(X, order):
        return spring(X[:, :3], X[:, 3:], l0, k, order)

    eg, eh = fd_check(f, x)
    assert eg < 1e-7 and eh < 1e-6, (eg, eh)


def test_curvature_is_two_tan_half_angle():
    phi = np.linspace(-3.0, 3.0, 13)
    e = np.tile([1.0, 0, 0], (13, 1))
    f = np.stack([np.cos(phi), np.sin(phi), 0 * phi], axis=1) * 2.0
    kb = curvature_binormal(e, f)
    np.testing.assert_allclose(kb[:, 2], 2 * np.tan(phi / 2), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(kb[:, :2], 0, atol=1e-15)


def _bent_rod(rng, n=9, planar=False):
    t = np.linspace(0, 2.5, n)
    x = np.stack([np.cos(t), np.sin(t), 0 * t if planar else 0.2 * t], axis=1)
    return x + 0.01 * rng.normal(size=x.shape) * np.array([1, 1, 0 if planar else 1])


def _system(rest):
    n = rest.shape[0]
    return MechanicalSystem(rod_terms(rest, EA=50.0, EI=2.0), np.ones(n), np.zeros(n),
                            np.zeros((n, 3)), np.zeros(n, bool), force_scale=1.0)


def test_assembled_gradient_and_hessian_fd():
    rng = np.random.default_rng(3)
    rest = _bent_rod(rng)
    s = _system(rest)
    q = (rest + 0.1 * rng.normal(size=rest.shape)).ravel()
    g, H = s.gradient(q), s.hessian(q)
    h = 1e-6
    for i in range(q.size):
        dq = np.zeros(q.size)
        dq[i] = h
        assert abs((s.energy(q + dq) - s.energy(q - dq)) / (2 * h) - g[i]) < 1e-6 * np.abs(g).max()
        col = (s.gradient(q + dq) - s.gradient(q - dq)) / (2 * h)
        np.testing.assert_allclose(col, H[:, i], atol=1e-5 * np.abs(H).max())
    # the banded tangent used by Newton equals the dense Hessian plus the diagonal
    diag = rng.uniform(1, 2, q.size)
    _, K = s.gradient_hessian(q, diag)
    np.testing.assert_allclose(K.toarray(), H + np.diag(diag), atol=1e-10 * np.abs(H).max())
    assert s.assembler.banded


def _rotation(rng, about_z=False):
    if about_z:
        a = rng.uniform(0, 2 * np.pi)
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return Q * np.sign(np.linalg.det(Q))


# (rest shape, rotations the energy must be invariant under): a straight rod is invariant
# under every rotation, a naturally curved planar rod under rotations about its plane normal.
SHAPES = [("straight", False), ("planar_curved", True)]


def _rest(kind, rng):
    if kind == "straight":
        return np.stack([np.linspace(0, 1, 9), np.zeros(9), np.zeros(9)], axis=1)
    return _bent_rod(rng, planar=True)


@pytest.mark.parametrize("kind,about_z", SHAPES)
def test_rest_shape_is_stress_free_under_rigid_motion(kind, about_z):
    rng = np.random.default_rng(4)
    rest = _rest(kind, rng)
    s = _system(rest)
    for _ in range(5):
        moved = rest @ _rotation(rng, about_z).T + rng.normal(size=3)
        assert s.energy(moved.ravel()) < 1e-20
        assert np.abs(s.gradient(moved.ravel())).max() < 1e-10


@pytest.mark.parametrize("kind,about_z", SHAPES)
def test_elastic_forces_have_no_net_force_or_torque(kind, about_z):
    rng = np.random.default_rng(5)
    rest = _rest(kind, rng)
    s = _system(rest)
    x = rest + 0.2 * rng.normal(size=rest.shape)
    f = -s.gradient(x.ravel()).reshape(-1, 3)
    scale = np.abs(f).max()
    assert np.abs(f.sum(0)).max() < 1e-10 * scale
    torque = np.cross(x, f).sum(0)
    assert np.abs(torque[2] if about_z else torque).max() < 1e-10 * scale
    Q, b = _rotation(rng, about_z), rng.normal(size=3)
    assert np.isclose(s.energy((x @ Q.T + b).ravel()), s.energy(x.ravel()), rtol=1e-10)


def test_case_system_builds_with_paper_constants():
    c = RodCase()
    s = c.system(1e9)
    assert s.n_nodes == 21 and np.isclose(c.dL, 0.005)
    R = c.node_radius()
    assert np.isclose(R[10], 0.025) and np.allclose(np.delete(R, 10), 5e-4)
    np.testing.assert_allclose(s.mass, 4 / 3 * np.pi * R**3 * 7000)
    np.testing.assert_allclose(s.force[:, 1], -4 / 3 * np.pi * R**3 * 6000 * 9.81)
    np.testing.assert_allclose(s.damping, 6 * np.pi * 1000 * R)
    assert np.isclose(s.terms[0].k[0], 1e9 * np.pi * 1e-6)
    assert np.isclose(s.terms[1].EI_el[0], 1e9 * np.pi * 1e-12 / 4)
