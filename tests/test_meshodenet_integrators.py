"""Integrators: convergence orders, agreement with torchdiffeq, registry errors, and the
three gradient modes giving the same loss gradient."""

import dataclasses

import numpy as np
import pytest
import torch

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.integrators.explicit import GRADIENT_MODES, INTEGRATORS, get_integrator, odesolve
from meshodenet.mesh.data import Mesh, Trajectories

torch.set_num_threads(1)  # tiny problems: threads only add overhead


class Linear(torch.nn.Module):
    """dz/dt = A z, a damped rotation, with the exact solution expm(A t) z0."""

    def __init__(self):
        super().__init__()
        self.A = torch.nn.Parameter(torch.tensor([[-0.1, 1.0], [-1.0, -0.1]],
                                                 dtype=torch.float64))

    def forward(self, t, z):
        return z @ self.A.T

    def exact(self, z0, t):
        return torch.stack([z0 @ torch.linalg.matrix_exp(self.A * tk).T for tk in t])


class TestConvergence:
    """Global error at t = 2 over step sizes 2/8 ... 2/64: fitted log-log slope = order."""

    expected = {"euler": 1, "midpoint": 2, "rk4": 4, "backward_euler": 1, "sdirk2": 2}

    @pytest.mark.parametrize("name", ["euler", "midpoint", "rk4", "backward_euler", "sdirk2"])
    def test_order(self, name):
        f = Linear()
        z0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
        t = torch.tensor([0.0, 2.0], dtype=torch.float64)
        exact = f.exact(z0, t)[-1].detach()
        ns = np.array([8, 16, 32, 64])
        with torch.no_grad():
            errs = [float((odesolve(f, z0, t, name, substeps=int(n))[-1] - exact).norm())
                    for n in ns]
        slope = -np.polyfit(np.log(ns), np.log(errs), 1)[0]
        assert abs(slope - self.expected[name]) < 0.15, (name, slope, errs)


def test_rk4_is_torchdiffeqs_rk4():
    from torchdiffeq import odeint

    f = Linear()
    z0 = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    t = torch.linspace(0, 3, 7, dtype=torch.float64)
    with torch.no_grad():
        ours = odesolve(f, z0, t, "rk4")
        theirs = odeint(f, z0, t, method="rk4")
    torch.testing.assert_close(ours, theirs, rtol=1e-13, atol=1e-14)


def test_dopri5_meets_its_tolerance():
    f = Linear()
    z0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    t = torch.linspace(0, 5, 6, dtype=torch.float64)
    with torch.no_grad():
        z = odesolve(f, z0, t, "dopri5", rtol=1e-9, atol=1e-11)
    torch.testing.assert_close(z, f.exact(z0, t).detach(), rtol=1e-7, atol=1e-8)


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(ValueError, match="euler, midpoint, rk4"):
        get_integrator("rk45")
    with pytest.raises(ValueError, match="direct, checkpoint, adjoint"):
        odesolve(Linear(), torch.ones(1, 2, dtype=torch.float64),
                 torch.tensor([0.0, 1.0], dtype=torch.float64), grad_mode="reverse")


def _loss_grad(model, data):
    model.zero_grad()
    loss = model.training_loss(data, torch.arange(len(data)))
    loss.backward()
    return loss.detach(), torch.cat([p.grad.reshape(-1) for p in model.parameters()])


@pytest.mark.parametrize("integrator", ["euler", "midpoint", "rk4"])
def test_gradient_modes_agree(integrator):
    from tests.conftest import rod_arrays

    arrays = rod_arrays(B=2, T=5)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    base = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, integrator=integrator, substeps=4,
                            activation="tanh")
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), base, data).double()
    results = {}
    for mode in GRADIENT_MODES:
        model.config = dataclasses.replace(base, grad_mode=mode, checkpoint_every=2)
        results[mode] = _loss_grad(model, data)
    loss, grad = results["direct"]
    # checkpointing recomputes the very same operations: equal to rounding
    torch.testing.assert_close(results["checkpoint"][0], loss, rtol=1e-12, atol=0)
    torch.testing.assert_close(results["checkpoint"][1], grad, rtol=1e-10, atol=1e-14)
    # the adjoint solves the continuous adjoint ODE backwards with the same scheme: its
    # gradient differs by that solve's discretisation error only
    torch.testing.assert_close(results["adjoint"][0], loss, rtol=1e-12, atol=0)
    rel = float((results["adjoint"][1] - grad).norm() / grad.norm())
    assert rel < {"euler": 0.2, "midpoint": 1e-2, "rk4": 1e-6}[integrator], rel


def test_adjoint_gradient_converges_to_direct():
    """Halving the step shrinks the adjoint/direct gap at about the scheme's order (rk4)."""
    from tests.conftest import rod_arrays

    arrays = rod_arrays(B=1, T=3)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    base = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, activation="tanh")
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), base, data).double()
    gaps = []
    for substeps in (1, 2):
        g = {}
        for mode in ("direct", "adjoint"):
            model.config = dataclasses.replace(base, grad_mode=mode, substeps=substeps)
            g[mode] = _loss_grad(model, data)[1]
        gaps.append(float((g["adjoint"] - g["direct"]).norm()))
    assert gaps[1] < gaps[0] / 8, gaps


def test_dopri5_modes_agree_to_tolerance():
    from tests.conftest import rod_arrays

    arrays = rod_arrays(B=1, T=4)
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    base = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, integrator="dopri5", rtol=1e-9,
                            atol=1e-11, activation="tanh")
    torch.manual_seed(0)
    model = MeshODENet(Mesh.from_arrays(arrays), base, data).double()
    grads = {}
    for mode in GRADIENT_MODES:
        model.config = dataclasses.replace(base, grad_mode=mode)
        grads[mode] = _loss_grad(model, data)[1]
    for mode in ("checkpoint", "adjoint"):
        rel = float((grads[mode] - grads["direct"]).norm() / grads["direct"].norm())
        assert rel < 1e-5, (mode, rel)


def test_every_integrator_rolls_out(arrays):
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    for name in INTEGRATORS:
        cfg = MeshODENetConfig(hidden=8, mlp_hidden_layers=1, integrator=name)
        model = MeshODENet(Mesh.from_arrays(arrays), cfg, data).double()
        pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
        assert pos.shape == data.pos.shape and torch.isfinite(pos).all()


def test_adaptive_solver_gives_up_on_a_stiff_field_with_a_warning():
    """A stiff field must not make dopri5 crawl for hours: past the step cap the solve returns
    NaN (training skips the step) with a warning naming the tolerances."""
    import torch

    from meshodenet.integrators.explicit import MAX_STEPS_PER_INTERVAL, odesolve

    calls = []

    def f(t, z):
        calls.append(1)
        return -1e9 * z * (1 + torch.sin(1e4 * t))

    z0 = torch.ones(3, dtype=torch.float64)
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="too stiff"):
        z = odesolve(f, z0, t, "dopri5", rtol=1e-8, atol=1e-12)
    assert z.shape == (2, 3) and torch.isnan(z).all()
    assert len(calls) <= 7 * MAX_STEPS_PER_INTERVAL * 2
    # a benign field is unaffected
    z = odesolve(lambda t, z: -z, z0, t, "dopri5", rtol=1e-8, atol=1e-10)
    assert torch.allclose(z[-1], z0 * torch.exp(torch.tensor(-1.0, dtype=torch.float64)))
