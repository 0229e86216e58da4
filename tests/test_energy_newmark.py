"""Implicit-Energy stepped by Newmark's average acceleration (``EnergyConfig.integrator =
'newmark'``): its order, its first step from rest, its losses against its own rollouts, the
batched solver, and the configurations that refuse it."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from meshodenet.energy.model import EnergyConfig
from meshodenet.energy.model_dissipation import DissipationConfig
from meshodenet.mesh.data import Trajectories
from tests.conftest import rod_arrays, strip_arrays
from tests.test_energy import _model


def _quadratic_chain(integrator: str, **cfg):
    """A 4-node quadratic chain (g = 1) and a bent initial shape at rest (as
    ``test_backward_euler_converges_at_first_order``)."""
    arrays = rod_arrays(n_nodes=4)
    model, _ = _model(arrays, train=False, integrator=integrator, **cfg)
    with torch.no_grad():
        for k, term in model.terms.items():
            for p in term.mlp.parameters():
                p.zero_()
            term.log_stiffness.fill_(math.log(1e-4))
            getattr(model, f"{k}_sigma").fill_(1.0)
        model.ystats.copy_(torch.tensor([1e9, math.log(1e9), 1.0, 1.0]))
    x0 = torch.as_tensor(arrays["rest_pos"])[None].clone()
    x0[..., 1] = 0.002 * torch.sin(torch.pi * x0[..., 0] / 0.1)
    return model, x0, torch.zeros_like(x0), torch.tensor([1e9], dtype=torch.float64)


def test_newmark_converges_at_second_order():
    """The chain's position at t = 0.4 s against a 1/1024-step solve: the error falls 4x per
    halving of h (backward Euler's 2x: tests/test_energy.py); at 16 steps (h = 25 ms) the
    chain's fastest mode is not resolved yet (error 4.5e-7 m against 3.7e-10 m at 32)."""
    model, x0, v0, y = _quadratic_chain("newmark")

    def final(n):
        t = torch.linspace(0, 0.4, n + 1, dtype=torch.float64)
        with torch.no_grad():
            return model.rollout(x0, v0, y, t)[0][:, -1]

    ref = final(1024)
    errs = [float((final(n) - ref).norm()) for n in (32, 64, 128)]
    orders = [math.log2(a / b) for a, b in zip(errs[:-1], errs[1:])]
    assert errs[0] > 1e-10 and all(1.8 < o < 2.3 for o in orders), (errs, orders)


@pytest.mark.parametrize("gamma", [0.5, 0.75, 1.0])
def test_first_step_from_rest_moves_half_as_far_as_backward_euler(gamma):
    """From rest a short step moves a node h^2 a / 2 (the truth to second order) whatever
    ``gamma``; backward Euler's moves it h^2 a: the step-1 error of docs/ENERGY.md, "Newmark"."""
    t = torch.tensor([0.0, 1e-6], dtype=torch.float64)  # drag and stiffness: O(h) relative
    moves = {}
    for integrator in ("backward_euler", "newmark"):  # Newton to round-off: moves of 1e-12 m
        model, x0, v0, y = _quadratic_chain(integrator, newton_rtol=1e-14, newmark_gamma=gamma)
        with torch.no_grad():
            moves[integrator] = model.rollout(x0, v0, y, t)[0][:, 1] - x0
            a0 = model._acceleration(model.system(y), x0, v0)
    free = model.free
    nm, be = moves["newmark"][:, free], moves["backward_euler"][:, free]
    assert float(a0[:, free].abs().max()) > 0
    tol = dict(rtol=1e-3, atol=1e-3 * 1e-12 * float(a0.abs().max()))  # round-off: 1e-17 m
    torch.testing.assert_close(nm, 0.5e-12 * a0[:, free], **tol)
    torch.testing.assert_close(be, 1e-12 * a0[:, free], **tol)


@pytest.mark.parametrize("gamma", [0.5, 0.75])
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_losses_vanish_on_the_models_own_rollouts(make, gamma):
    """Trajectories the model rolled out itself (its velocities stored) are fitted exactly:
    the one-step loss and a window loss are round-off there, not on the fixture's data, and
    both have finite gradients on the data."""
    arrays = make(B=2, T=6)
    model, tr = _model(arrays, integrator="newmark", newmark_gamma=gamma)
    with torch.no_grad():
        pos, vel = model.rollout(tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
    own = Trajectories(pos=pos, vel=vel, youngs=tr.youngs, t=tr.t)
    for shooting in (0, 2):
        model.config = dataclasses.replace(model.config, shooting=shooting)
        samples = torch.arange(model.n_training_samples(tr))
        gen = lambda: torch.Generator().manual_seed(0)  # noqa: E731
        with torch.no_grad():
            fit = float(model.training_loss(own, samples, gen()))
        model.zero_grad()
        data = model.training_loss(tr, samples, gen())
        data.backward()
        assert fit < 1e-12 * float(data), (shooting, fit, float(data))
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_batched_newmark_agrees_with_the_reference(make):
    arrays = make()
    model, tr = _model(arrays, integrator="newmark")
    tol = model.config.newton_rtol * model.length
    args = (tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
    with torch.no_grad():
        model.solver = "reference"
        ref, vref = model.rollout(*args)
        model.solver = "batched"
        got, vgot = model.rollout(*args)
        model.config = dataclasses.replace(model.config, integrator="backward_euler")
        be, _ = model.rollout(*args)
    assert float((got - ref).abs().max()) < 2 * tol
    assert float((be - got).abs().max()) > 1e3 * tol  # another integrator, not a relabel


def test_configurations_that_refuse_it():
    with pytest.raises(ValueError, match="EnergyConfig.integrator must be one of "
                                         "backward_euler, newmark, got 'rk4'"):
        EnergyConfig(integrator="rk4")
    for bad in (0.4, 1.5, True, "0.75"):
        with pytest.raises(ValueError, match=r"EnergyConfig.newmark_gamma must be a number in "
                                             r"\[0.5, 1\], got " + repr(bad)):
            EnergyConfig(integrator="newmark", newmark_gamma=bad)
    with pytest.raises(ValueError, match="DissipationConfig.integrator must be 'backward_euler'"):
        DissipationConfig(integrator="newmark")


@pytest.mark.parametrize("integrator", ["backward_euler", "newmark"])
def test_a_failed_interval_is_retried_in_halves(monkeypatch, integrator):
    """``max_halvings``: an interval whose Newton fails is taken as two half steps (the same
    frames as a rollout sampled twice as finely there); without halvings, or with too few, the
    failure stands."""
    from meshodenet.energy.model import ImplicitEnergy
    from meshodenet.integrators.implicit import NewtonError

    arrays = rod_arrays()
    model, tr = _model(arrays, integrator=integrator, newmark_gamma=0.75)
    x0, v0, y, t = tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t[:5]
    fine = torch.cat([t[:3], (t[2:3] + t[3:4]) / 2, t[3:]])  # interval 2 in halves
    with torch.no_grad():
        ref, vref = model.rollout(x0, v0, y, fine)
    real = ImplicitEnergy._newton_batched

    def failing(self, be, xk, vk, h, where):  # interval 2 fails at its full length
        if where.startswith("interval 2 ") and "half" not in where:
            raise NewtonError(f"did not converge at {where}")
        return real(self, be, xk, vk, h, where)

    monkeypatch.setattr(ImplicitEnergy, "_newton_batched", failing)
    with torch.no_grad(), pytest.raises(NewtonError, match="interval 2"):
        model.rollout(x0, v0, y, t)
    model.config = dataclasses.replace(model.config, max_halvings=1)
    with torch.no_grad():
        pos, vel = model.rollout(x0, v0, y, t)
    keep = [0, 1, 2, 4, 5]  # the fine rollout's frames at t
    torch.testing.assert_close(pos, ref[:, keep], rtol=0, atol=1e-12)
    torch.testing.assert_close(vel, vref[:, keep], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="max_halvings must be an int >= 0, got -1"):
        EnergyConfig(max_halvings=-1)
