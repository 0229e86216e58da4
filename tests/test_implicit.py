"""Implicit integrators (``meshodenet.integrators.implicit``): the coloured Jacobian, gradients by implicit
differentiation against finite differences and against an unrolled Newton, stiff stability,
the Newton error, and training MeshODENet with ``backward_euler`` (the convergence orders are
tested with the explicit schemes' in tests/test_meshodenet_integrators.py)."""

import dataclasses

import numpy as np
import pytest
import torch

from meshodenet.gnn import reference
from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig, meshodenet_presets
from meshodenet.integrators import implicit
from meshodenet.integrators.explicit import INTEGRATORS, get_integrator, odesolve
from meshodenet.integrators.implicit import IMPLICIT, JACOBIANS, MeshCoupling, NewtonError
from meshodenet.mesh.data import Mesh, Trajectories
from tests.conftest import rod_arrays, strip_arrays

torch.set_num_threads(1)  # tiny problems: threads only add overhead


def _model(arrays, integrator="backward_euler", layers=1, B=None):
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    cfg = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, layers=layers, activation="tanh",
                           integrator=integrator)
    torch.manual_seed(0)
    return MeshODENet(Mesh.from_arrays(arrays), cfg, data).double(), data


def _state(data, k=1):
    return torch.stack([data.pos[:, k].reshape(-1, 3), data.vel[:, k].reshape(-1, 3)])


def test_registered_beside_the_explicit_schemes():
    assert {"euler", "midpoint", "rk4", "dopri5", "backward_euler", "sdirk2"} <= set(INTEGRATORS)
    with pytest.raises(ValueError, match="backward_euler, dopri5, euler"):
        get_integrator("bdf2")


@pytest.mark.parametrize("make", [lambda: rod_arrays(n_nodes=12, B=2),
                                  lambda: strip_arrays(nx=10, ny=2)], ids=["rod", "strip"])
@pytest.mark.parametrize("layers", [0, 1, 2])
def test_coloured_jacobian_equals_the_dense_one(make, layers):
    """The coupling pattern (``layers + 1`` hops) holds every nonzero of ``df/dz``, and the
    colouring needs fewer JVPs than columns."""
    model, data = _model(make(), layers=layers)
    ctx = model.field_context(data.youngs, torch.float64)
    f = reference.BoundField(model, ctx)
    z = _state(data)
    with torch.no_grad():
        dense = torch.func.jacfwd(lambda y: f(0.0, y.reshape(z.shape)).reshape(-1))(z.reshape(-1))
        coupling = f.coupling()
        sparse = implicit.coloured_jacobian(lambda y: f(0.0, y), z, coupling).toarray()
    assert coupling.n_colours < coupling.n_nodes
    np.testing.assert_allclose(sparse, dense.numpy(), rtol=0, atol=1e-12)


def _rollout_loss(model, data, T=3):
    pos, vel = model.rollout(data.pos[:, 1], data.vel[:, 1], data.youngs, data.t[:T])
    return (pos[:, 1:] ** 2).sum() + 0.1 * (vel[:, 1:] ** 2).sum()


@pytest.mark.parametrize("jacobian", JACOBIANS)
@pytest.mark.parametrize("scheme", sorted(IMPLICIT))
def test_gradient_matches_central_differences(scheme, jacobian, monkeypatch):
    monkeypatch.setattr(implicit, "DEFAULT_JACOBIAN", jacobian)
    model, data = _model(rod_arrays(B=2, T=4), scheme)
    params = list(model.parameters())
    loss = _rollout_loss(model, data)
    grads = torch.autograd.grad(loss, params)
    eps = 1e-6
    for p, g in ((params[0], grads[0]), (params[-1], grads[-1])):
        for idx in [(0,) * p.dim(), tuple(s - 1 for s in p.shape)]:
            with torch.no_grad():
                p[idx] += eps
                up = float(_rollout_loss(model, data))
                p[idx] -= 2 * eps
                down = float(_rollout_loss(model, data))
                p[idx] += eps
            fd = (up - down) / (2 * eps)
            assert float(g[idx]) == pytest.approx(fd, rel=1e-5, abs=1e-9), (idx, float(g[idx]), fd)


def _unrolled_backward_euler(fz, z, h, iters=12):
    """Backward Euler by Newton with autograd through every iteration (dense Jacobian built
    with ``create_graph``)."""
    Y = z
    for _ in range(iters):
        J = torch.autograd.functional.jacobian(lambda y: fz(y.reshape(z.shape)).reshape(-1),
                                               Y.reshape(-1), create_graph=True)
        A = torch.eye(z.numel(), dtype=z.dtype) - h * J
        R = (Y - z - h * fz(Y)).reshape(-1)
        Y = Y - torch.linalg.solve(A, R).reshape(z.shape)
    return Y


@pytest.mark.parametrize("jacobian", JACOBIANS)
def test_gradient_equals_backprop_through_converged_unrolled_newton(jacobian, monkeypatch):
    monkeypatch.setattr(implicit, "DEFAULT_JACOBIAN", jacobian)
    model, data = _model(rod_arrays(B=1, T=3))
    ctx = model.field_context(data.youngs, torch.float64)
    f = reference.BoundField(model, ctx)
    h = float(data.t[1] - data.t[0])
    params = list(model.parameters())
    z0 = _state(data).requires_grad_(True)
    w = torch.randn(z0.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ours = IMPLICIT["backward_euler"].solve(f, z0, data.t[:2])[1]
    g_ours = torch.autograd.grad((ours * w).sum(), [z0, *params])
    theirs = _unrolled_backward_euler(lambda y: f(0.0, y), z0, h)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-12)
    g_theirs = torch.autograd.grad((theirs * w).sum(), [z0, *params])
    for a, b in zip(g_ours, g_theirs, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-11)


class Linear(torch.nn.Module):
    """dz/dt = A z, a damped rotation, with the exact solution expm(A t) z0."""

    def __init__(self, A):
        super().__init__()
        self.A = torch.nn.Parameter(torch.as_tensor(A, dtype=torch.float64))

    def forward(self, t, z):
        return z @ self.A.T

    def exact(self, z0, t):
        return z0 @ torch.linalg.matrix_exp(self.A * t).T


@pytest.mark.parametrize("A,energy", [([[-100.0]], [1.0]),  # lambda h = -100
                                      ([[0.0, 1.0], [-900.0, 0.0]], [900.0, 1.0])],  # omega h = 30
                         ids=["decay", "oscillator"])
def test_stiff_linear_systems_decay_where_rk4_blows_up(A, energy):
    """At ``h = 1``: the energy ``sum(energy * z^2)`` never grows and has decayed by 1e-6 after
    20 implicit steps; rk4's grows beyond 1e20."""
    f = Linear(A)
    z0 = torch.ones(1, len(A), dtype=torch.float64)
    t = torch.arange(21, dtype=torch.float64)
    w = torch.tensor(energy, dtype=torch.float64)
    with torch.no_grad():
        e_rk4 = (w * odesolve(f, z0, t, "rk4")[:, 0] ** 2).sum(-1)
        assert float(e_rk4[-1]) > 1e20 * float(e_rk4[0])
        for name in IMPLICIT:
            e = (w * odesolve(f, z0, t, name)[:, 0] ** 2).sum(-1)
            assert bool((e[1:] <= e[:-1] * (1 + 1e-12)).all()), (name, e)
            assert float(e[-1]) < 1e-6 * float(e[0]), (name, e)


class Failing(torch.nn.Module):
    """Two trajectories of two nodes (states ``(1, 4, 1)``): the first decays (``-z``); from
    ``t > 0.6`` the second follows ``z^2 + 1``, whose backward Euler step has no real root."""

    def forward(self, t, z):
        out = -z.clone()
        if float(t) > 0.6:
            out[:, 2:] = z[:, 2:] ** 2 + 1
        return out

    def coupling(self):
        return MeshCoupling(np.array([0]), np.array([1]), 2, 1, n_graphs=2)


@pytest.mark.parametrize("jacobian", JACOBIANS)
def test_newton_failure_names_step_time_residual_and_trajectory(jacobian, monkeypatch):
    monkeypatch.setattr(implicit, "DEFAULT_JACOBIAN", jacobian)
    z0 = torch.ones(1, 4, 1, dtype=torch.float64)
    t = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    with pytest.raises(NewtonError, match=r"backward_euler: Newton did not converge on step 1 "
                                          r"\(substep 0, stage time t=1\).*residual\| [0-9.e+-]+ .*"
                                          r"worst in trajectory 1 "):
        odesolve(Failing(), z0, t, "backward_euler")


def _train_two_epochs(arrays, integrator):
    from meshodenet.training.train import make_optimizer, train_epoch

    data = Trajectories.from_arrays(arrays)
    tc, mc = meshodenet_presets("smoke", Mesh.from_arrays(arrays).kind)
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), dataclasses.replace(mc, integrator=integrator),
                       data)
    opt, _ = make_optimizer(model, tc)
    gen = torch.Generator().manual_seed(0)
    losses = []
    for epoch in range(2):
        model.start_epoch(epoch)
        losses.append(train_epoch(model, opt, data, tc, gen)[0])
    return losses


@pytest.mark.parametrize("scheme", sorted(IMPLICIT))
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays], ids=["rod", "strip"])
def test_meshodenet_trains_the_smoke_preset_implicitly(make, scheme):
    losses = _train_two_epochs(make(), scheme)
    assert all(np.isfinite(losses)), losses


def test_a_run_spec_and_the_cli_accept_the_implicit_integrators(tiny_case, tmp_path, capsys):
    from benchmarks.cli import main
    from benchmarks.suite.suites import RunSpec

    case, root = tiny_case
    spec = RunSpec(case.id, "meshodenet", "smoke", integrator="backward_euler")
    assert "model.integrator=backward_euler" in spec.all_overrides()
    common = ["--case", case.id, "--preset", "smoke", "--data-dir", str(root), "--threads", "1",
              "--no-progress", "--epochs", "1"]
    assert main(["train", *common, "--out", str(tmp_path / "ok"),
                 "--set", "model.integrator=backward_euler"]) == 0
    assert main(["train", *common, "--out", str(tmp_path / "bad"),
                 "--set", "model.integrator=bdf9"]) == 2
    err = capsys.readouterr().err
    assert "bdf9" in err and "backward_euler" in err and "Traceback" not in err


@pytest.mark.parametrize("jacobian", JACOBIANS)
def test_float32_steps_converge_relative_to_the_motion_not_the_positions(jacobian, monkeypatch):
    """A plate moves ~1e-4 of its coordinates per step: Newton's tolerance must be relative to
    the step's change, or float32 stops early (it did: 12 % off the float64 rollout)."""
    monkeypatch.setattr(implicit, "DEFAULT_JACOBIAN", jacobian)
    arrays = strip_arrays(B=2, T=6, dt=0.003)
    out = {}
    for dtype in (torch.float64, torch.float32):
        data = Trajectories.from_arrays(arrays, dtype=dtype)
        torch.manual_seed(0)
        model = MeshODENet(Mesh.from_arrays(arrays),
                           MeshODENetConfig(hidden=16, integrator="backward_euler"), data).to(dtype)
        with torch.no_grad():
            pos, _ = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
        out[dtype] = (pos - data.pos[:, :1]).double()
    motion = float(out[torch.float64].abs().max())
    assert float((out[torch.float32] - out[torch.float64]).abs().max()) < 1e-3 * motion
