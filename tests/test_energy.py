"""Implicit-Energy (``meshodenet.energy.core``, ``meshodenet.energy.model``): the learned energy's
derivatives and invariances, the backward-Euler step and its implicit gradients, the
least-squares stiffness, the solver's order, training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from meshodenet.energy.core import measure
from meshodenet.energy.model import STIFFNESS_PRIORS, EnergyConfig, ImplicitEnergy
from meshodenet.integrators.implicit import NewtonError
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec, load_model
from tests.conftest import check_geometry_derivatives, rod_arrays, strip_arrays


def _model(arrays, seed=0, train=True, **cfg):
    torch.manual_seed(seed)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays, dtype=torch.float64)
    model = ImplicitEnergy(mesh, EnergyConfig(hidden=8, layers=1, **cfg), tr if train else None)
    with torch.no_grad():
        # the fixtures' synthetic strains are tiny: strains of a few percent as O(1) inputs
        # and stiffnesses 10-100 times m / h^2 (the fixtures' motions obey no energy)
        for k in model.kinds:
            getattr(model, f"{k}_sigma").fill_(0.02)
            model.terms[k].log_stiffness.fill_(-11.5)  # a non-trivial g (the last layer starts at zero)
            if model.config.stiffness_prior == "features":  # each element its own factor
                prior = getattr(model, f"{k}_prior")
                prior.copy_(0.3 + 2.7 * torch.rand_like(prior))
        for term in model.terms.values():
            for p in term.mlp.parameters():
                p.add_(0.3 * torch.randn_like(p))
    return model, tr


def _perturbed(arrays, scale=0.004, seed=3):
    rng = np.random.default_rng(seed)
    x = torch.as_tensor(arrays["rest_pos"] + scale * rng.standard_normal(arrays["rest_pos"].shape))
    return x[None].repeat(2, 1, 1)


@pytest.mark.parametrize("prior", STIFFNESS_PRIORS)
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_gradient_and_hessian_match_finite_differences(make, prior):
    arrays = make()
    model, tr = _model(arrays, stiffness_prior=prior)
    sys = model.system(tr.youngs[:2])
    check_energy_derivatives(sys, _perturbed(arrays))


def check_energy_derivatives(sys, x, eps=1e-7):
    """``sys``'s gradient and Hessian at ``x (2, N, 3)`` against central differences of its
    energy and gradient (every other coordinate); the Hessian symmetric."""
    g = sys.gradient(x)
    H = sys.hessian(x)
    flat = x.reshape(2, -1)
    for i in range(0, flat.shape[1], 2):
        d = torch.zeros_like(flat)
        d[:, i] = eps
        xp, xm = (flat + d).reshape(x.shape), (flat - d).reshape(x.shape)
        fd = (sys.energy(xp) - sys.energy(xm)) / (2 * eps)
        assert torch.allclose(g.reshape(2, -1)[:, i], fd, rtol=1e-5, atol=1e-7 * g.abs().max())
        fdh = (sys.gradient(xp) - sys.gradient(xm)).reshape(2, -1) / (2 * eps)
        assert torch.allclose(H[:, :, i], fdh, rtol=1e-4, atol=1e-6 * H.abs().max())
    assert torch.allclose(H, H.transpose(1, 2), atol=1e-10 * H.abs().max())


@pytest.mark.parametrize("prior", STIFFNESS_PRIORS)
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_energy_is_invariant_under_rigid_motions_and_zero_at_rest(make, prior):
    arrays = make()
    model, tr = _model(arrays, stiffness_prior=prior)
    sys = model.system(tr.youngs[:2])
    x = _perturbed(arrays)
    c, s = math.cos(0.7), math.sin(0.7)
    R = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    moved = x @ R.T + torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
    assert torch.allclose(sys.energy(moved), sys.energy(x), rtol=1e-10)
    rest = torch.as_tensor(arrays["rest_pos"])[None].repeat(2, 1, 1)
    assert torch.allclose(sys.energy(rest), torch.zeros(2, dtype=torch.float64), atol=1e-20)
    assert torch.allclose(sys.gradient(rest), torch.zeros_like(rest), atol=1e-12)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_step_solves_backward_euler_and_holds_the_clamp(make):
    arrays = make()
    model, tr = _model(arrays)
    sys = model.system(tr.youngs[:2])
    xk, vk = tr.pos[:2, 2], (tr.pos[:2, 2] - tr.pos[:2, 1]) / 0.1
    vk = vk * model.free[:, None]
    act = model._active(xk, vk)
    with torch.no_grad():
        x = model.step(sys, xk, vk, 0.1, act)
    r = model._residual(sys, x, xk, vk, 0.1)[:, act]
    scale = (model.mass.max() / 0.01 * 0.01 + model.force.abs().max()).item()
    assert r.abs().max() < 1e-8 * scale
    clamped = ~model.free
    assert torch.equal(x[:, clamped], xk[:, clamped])


def test_in_plane_solve_equals_the_full_solve():
    arrays = strip_arrays()
    arrays["force"] = np.roll(arrays["force"], -1, axis=1)  # load in -y: in the plane
    model, tr = _model(arrays)
    x0 = torch.as_tensor(arrays["rest_pos"])[None].repeat(2, 1, 1)
    v0 = torch.zeros_like(x0)
    t = torch.arange(4, dtype=torch.float64) * 0.01
    assert model.planar and len(model._active(x0, v0)) == 2 * int(model.free.sum())
    got, _ = model.rollout(x0, v0, tr.youngs[:2], t)
    model.planar = False
    full, _ = model.rollout(x0, v0, tr.youngs[:2], t)
    assert torch.allclose(got, full, rtol=0, atol=1e-12)
    assert got[..., 2].abs().max() == 0 and got[..., 1].min() < 0


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_implicit_gradient_matches_finite_differences_of_the_solve(make):
    arrays = make()
    model, tr = _model(arrays, newton_rtol=1e-11)  # converged far below the differences
    idx = torch.tensor([0, 1])
    t = tr.t[:3]

    def loss():
        pos, _ = model.rollout(tr.pos[idx, 0], tr.vel[idx, 0], tr.youngs[idx], t)
        return ((pos - tr.pos[idx, :3]) ** 2).sum() * 1e4

    model.zero_grad()
    loss().backward()
    params = [p for p in model.parameters()]
    gmax = max(float(p.grad.abs().max()) for p in params)
    eps = 1e-4  # the loss is smooth; a larger step keeps Newton's tolerance out of the quotient
    for p in params:
        flat, gflat = p.data.reshape(-1), p.grad.reshape(-1)
        for i in range(0, len(flat), max(len(flat) // 3, 1)):
            old = float(flat[i])
            with torch.no_grad():
                flat[i] = old + eps
                lp = float(loss())
                flat[i] = old - eps
                lm = float(loss())
                flat[i] = old
            fd = (lp - lm) / (2 * eps)
            assert abs(float(gflat[i]) - fd) <= 1e-3 * abs(fd) + 1e-5 * gmax, (p.shape, i)


def test_gradient_matches_backpropagation_through_converged_newton():
    """The one-extra-step implicit gradient equals autograd through 12 full Newton steps."""
    arrays = rod_arrays()
    model, tr = _model(arrays)
    sys = model.system(tr.youngs[:2])
    xk = tr.pos[:2, 1]
    vk = (tr.pos[:2, 1] - tr.pos[:2, 0]) / 0.1
    act = model._active(xk, vk)
    x = model.step(sys, xk, vk, 0.1, act)
    w = torch.randn(x.shape, dtype=x.dtype, generator=torch.Generator().manual_seed(1))
    model.zero_grad()
    (x * w).sum().backward()  # not x.sum(): internal forces sum to zero
    want = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    y = (xk + 0.1 * vk).requires_grad_(True)
    for _ in range(12):  # Newton unrolled on the graph, the energy differentiated by autograd
        u = sum(sys._energy_q(k, measure(k, y[:, n], rest, l0)).sum()
                for k, (n, _, rest, l0) in sys.elems.items())
        (gu,) = torch.autograd.grad(u, y, create_graph=True)
        m, c = model.mass[:, None], model.damping[:, None]
        r = (m / 0.01 * (y - xk - 0.1 * vk) + c / 0.1 * (y - xk) - model.force + gu)
        r = r.reshape(2, -1)[:, act]
        H = sys.hessian(y)
        d = (model.mass / 0.01 + model.damping / 0.1).repeat_interleave(3)
        A = (H + torch.diag(d))[:, act][:, :, act]
        # the matrix's dependence on y and the parameters matters only before convergence
        step = torch.linalg.solve(A, -r[..., None])[..., 0]
        flat = y.reshape(2, -1).clone()
        flat[:, act] = flat[:, act] + step
        y = flat.reshape(y.shape)
    (y * w).sum().backward()
    scale = max(float(w.abs().max()) for w in want)
    for p, w in zip(model.parameters(), want):
        assert torch.allclose(p.grad, w, rtol=1e-6, atol=1e-9 * scale)


def test_backward_euler_converges_at_first_order():
    """A quadratic chain (g = 1) released from a bent shape: the error at t = 0.4 s against a
    1/512-step solve halves with h."""
    arrays = rod_arrays(n_nodes=4)
    model, tr = _model(arrays, train=False)
    with torch.no_grad():
        for k, term in model.terms.items():
            for p in term.mlp.parameters():
                p.zero_()
            term.log_stiffness.fill_(math.log(1e-4))
            getattr(model, f"{k}_sigma").fill_(1.0)
        model.ystats.copy_(torch.tensor([1e9, math.log(1e9), 1.0, 1.0]))
    x0 = torch.as_tensor(arrays["rest_pos"])[None].clone()
    x0[..., 1] = 0.002 * torch.sin(torch.pi * x0[..., 0] / 0.1)
    v0 = torch.zeros_like(x0)
    y = torch.tensor([1e9], dtype=torch.float64)

    def final(n):
        t = torch.linspace(0, 0.4, n + 1, dtype=torch.float64)
        return model.rollout(x0, v0, y, t)[0][:, -1]

    ref = final(512)
    errs = [float((final(n) - ref).norm()) for n in (16, 32, 64)]
    orders = [math.log2(a / b) for a, b in zip(errs[:-1], errs[1:])]
    assert errs[0] > 1e-7 and all(0.85 < o < 1.25 for o in orders), (errs, orders)


def test_newton_failure_names_the_interval():
    arrays = rod_arrays()
    model, tr = _model(arrays, newton_max_iter=1)
    with pytest.raises(NewtonError, match=r"interval 0 \(t = 0 s\).*last step"):
        model.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)


def test_evaluation_rollout_is_nan_after_a_failed_newton(monkeypatch, tmp_path):
    """``on_newton_failure = "nan"`` (the suite's evaluation): the trajectory whose Newton
    fails keeps its frames up to the failing interval and is NaN after it; the others of its
    batch are rolled alone and equal their rollouts without the failure; the default raises,
    a rollout with gradients raises, a bad value is an error naming the attribute."""
    arrays = rod_arrays()
    model, tr = _model(arrays)
    x0, v0, y, t = tr.pos[:2, 0], tr.vel[:2, 0], tr.youngs[:2], tr.t[:6]
    with torch.no_grad():
        clean = model.rollout(x0, v0, y, t)[0]
    real = ImplicitEnergy._newton_batched

    def failing(self, be, xk, vk, h, where):  # the second trajectory fails at interval 3
        near = [torch.allclose(xk[i], clean[1, 3].double(), rtol=0, atol=1e-6)
                for i in range(len(xk))]
        if "interval 3 " in where and any(near):
            raise NewtonError(f"did not converge at {where}")
        return real(self, be, xk, vk, h, where)

    monkeypatch.setattr(ImplicitEnergy, "_newton_batched", failing)
    with torch.no_grad(), pytest.raises(NewtonError, match="interval 3"):
        model.rollout(x0, v0, y, t)
    model.on_newton_failure = "nan"
    with torch.no_grad(), pytest.warns(RuntimeWarning, match="interval 3.*NaN"):
        pos, vel = model.rollout(x0, v0, y, t)
    assert torch.allclose(pos[0], clean[0], rtol=0, atol=1e-9)
    assert torch.allclose(pos[1, :4], clean[1, :4], rtol=0, atol=1e-9)
    assert torch.isnan(pos[1, 4:]).all() and torch.isnan(vel[1, 4:]).all()
    assert not torch.isnan(vel[1, :4]).any()
    model.on_newton_failure = "skip"
    with torch.no_grad(), pytest.raises(ValueError, match="on_newton_failure .*'skip'"):
        model.rollout(x0, v0, y, t)


def set_known_energy(model, sigma: dict, ystats, log_stiffness: dict) -> None:
    """Give ``model`` a known energy: every MLP zeroed (``g = 1``), the invariants' scales
    ``sigma`` and the moduli statistics ``ystats`` fixed, and the log-stiffnesses set (what
    the least-squares fit must then recover from the model's own rollouts)."""
    with torch.no_grad():
        for term in model.terms.values():
            for p in term.mlp.parameters():
                p.zero_()
        for kind, value in sigma.items():
            getattr(model, f"{kind}_sigma").fill_(value)
        model.ystats.copy_(torch.tensor(ystats))
        for kind, value in log_stiffness.items():
            model.terms[kind].log_stiffness.fill_(value)


def test_least_squares_stiffness_recovers_a_quadratic_energy():
    """Data made by the model itself with g = 1 and known stiffnesses: the initial fit finds
    them (relative error 1e-6)."""
    arrays = rod_arrays(n_nodes=6, B=3, T=8)
    arrays["damping"] = arrays["damping"] * np.array([1, 1, 20, 1, 1, 1])  # a dragging node bends it
    model, tr = _model(arrays, train=False)
    # stiffnesses about 100 times m / h^2
    set_known_energy(model, {"edge": 1e-3, "hinge": 1e-3}, [1e9, 20.0, 1.0, 1e-6],
                     {"edge": -19.0, "hinge": -12.5})
    with torch.no_grad():
        pos, vel = model.rollout(tr.pos[:, 0], tr.vel[:, 0] * 0, tr.youngs, tr.t)
        for term in model.terms.values():
            term.log_stiffness.fill_(0.0)
    data = Trajectories(tr.t, pos, vel * 0 + vel[:, :1] * 0, tr.youngs)
    model._fit_log_stiffness(data, every=1)
    assert abs(float(model.terms["edge"].log_stiffness) + 19.0) < 1e-5
    assert abs(float(model.terms["hinge"].log_stiffness) + 12.5) < 1e-5


def test_registered_trains_and_reloads(tmp_path):
    from meshodenet.training.train import fit

    spec = get_model_spec("implicit_energy")
    arrays = rod_arrays(B=4, T=6)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    model = spec.build(mesh, mc, tr)
    fit(model, tr.subset(slice(0, 3)), tr.subset(slice(3, 4)), tc, tmp_path, progress=False)
    again, _ = load_model(tmp_path / "last.pt")
    assert again.config == mc
    with torch.no_grad():
        a = model.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
        b = again.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
    assert torch.isfinite(a).all() and a.dtype == torch.float32
    assert torch.equal(a, b)


def test_window_training_runs_exact_steps():
    """``shooting = S``: the loss of windows of S Newton steps, finite, with gradients."""
    arrays = rod_arrays(B=3, T=8)
    model, tr = _model(arrays, shooting=3)
    n = model.n_training_samples(tr)
    assert n == 3 * 2
    loss = model.training_loss(tr, torch.arange(n), torch.Generator().manual_seed(0))
    loss.backward()
    assert torch.isfinite(loss) and loss > 0
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_bench_section_times_the_model_against_the_solver(tiny_case, tmp_path):
    from benchmarks.cost.energybench import energy_bench, energy_line

    case, root = tiny_case
    lines = []
    r = energy_bench(case.id, 1, "cpu", lines.append, root)
    for key in ("train_step_s", "single_per_trajectory_s", "batched_per_trajectory_s",
                "solver_h_per_trajectory_s", "solver_per_trajectory_s"):
        assert r[key] > 0 and r["reference"].get(key, 1) > 0, key
    assert r["max_abs_diff_m"] < 2 * r["newton_tol_m"] and r["split_trajectories"] >= 1
    assert r["intervals"] == round(case.t_end / case.save_dt) and lines == [energy_line(case.id, r)]
    assert "skipped" in energy_bench(case.id, 1, "cpu", lines.append, tmp_path)


# --- the rod hinges' derivatives by hand, the batched solver -----------------------------------
def _random_rod_hinges(n: int, seed: int = 0):
    """``n`` random, strongly bent node triples (turning angles up to about 2.5 rad) with
    random rest curvatures: ``(x (1, 3n, 3), nodes (n, 3), kappa_0 (n, 3))``."""
    g = torch.Generator().manual_seed(seed)
    F64 = dict(dtype=torch.float64)
    a = torch.randn(n, 3, generator=g, **F64)
    e = torch.randn(n, 3, generator=g, **F64)
    f = -e + 1.5 * torch.randn(n, 3, generator=g, **F64)  # far from straight, not folded back
    x = torch.stack([a, a + e, a + e + f], 1).reshape(1, -1, 3)
    return x, torch.arange(3 * n).reshape(n, 3), 0.5 * torch.randn(n, 3, generator=g, **F64)


def test_rod_hinge_derivatives_match_finite_differences_and_autograd():
    """``dq/dx`` and ``d2q/dx2`` of ``q = |kappa - kappa_0|^2``: analytic (``_hinge_geometry``)
    against central differences of ``q`` and of the analytic gradient (h = 1e-6) and against
    ``torch.func`` (the first version's derivatives), on 64 random bent hinges."""
    from meshodenet.energy.core import _hinge_geometry

    x, nodes, kap0 = _random_rod_hinges(64)
    check_geometry_derivatives(_hinge_geometry, "hinge", x, nodes, kap0, "rod hinge", 1e-13)


@pytest.mark.parametrize("prior", STIFFNESS_PRIORS)
@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_batched_energy_equals_the_assembled_energy(make, prior):
    """``BatchedEnergy.evaluate`` (one stacked MLP pass, band storage, a subset of the batch)
    equals ``EnergySystem``'s energy, gradient and dense Hessian on the unknowns."""
    from meshodenet.energy.core import BatchedEnergy

    arrays = make()
    model, tr = _model(arrays, stiffness_prior=prior)
    sys = model.system(torch.cat([tr.youngs, 1.5 * tr.youngs])[:3])
    x = _perturbed(arrays).repeat(2, 1, 1)[:3]
    x[2] = x[2] + 0.003 * torch.randn_like(x[2])
    act = model._active(x, torch.zeros_like(x))
    be = BatchedEnergy(sys, act, model.mesh.n_nodes)
    assert sorted(be.unknowns.tolist()) == sorted(act.tolist())
    idx = torch.tensor([0, 2])
    U, dU, ab = be.evaluate(x[idx], idx, 2)
    H = sys.hessian(x)[idx][:, be.unknowns][:, :, be.unknowns]
    n, w = be.n, be.width
    band = torch.zeros_like(H)
    for k in range(w + 1):
        i = torch.arange(n - k)
        band[:, i + k, i] = band[:, i, i + k] = ab[:, k, :n - k]
    assert torch.allclose(U, sys.energy(x)[idx], rtol=1e-12)
    g = sys.gradient(x).reshape(3, -1)[idx][:, be.unknowns]
    assert torch.allclose(dU, g, rtol=1e-12, atol=1e-12 * float(g.abs().max()))
    assert torch.allclose(band, H, rtol=1e-12, atol=1e-12 * float(H.abs().max()))
    assert be.evaluate(x[idx], idx, 0)[1] is None and be.evaluate(x[idx], idx, 1)[2] is None
    assert torch.allclose(be.evaluate(x[idx], idx, 0)[0], U, rtol=1e-12)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_batched_solver_agrees_with_the_reference_within_newton_tolerance(make):
    """``solver = batched`` (per-trajectory Newton, banded Cholesky, converged trajectories
    dropping out) and ``reference`` roll out the same positions to Newton's tolerance; a
    trajectory's rollout does not depend on the batch it is rolled out in."""
    arrays = make()
    model, tr = _model(arrays)
    tol = model.config.newton_rtol * model.length
    args = (tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
    with torch.no_grad():
        model.solver = "reference"
        ref, _ = model.rollout(*args)
        model.solver = "batched"
        got, _ = model.rollout(*args)
        alone, _ = model.rollout(*(a[1:2] for a in args[:3]), tr.t)
    print(f"batched - reference: max {float((got - ref).abs().max()):.2e} m (tol {tol:.1e} m)")
    assert float((got - ref).abs().max()) < 2 * tol
    assert torch.allclose(alone[0], got[1], rtol=0, atol=1e-3 * tol)
    model.solver = "dense"
    with pytest.raises(ValueError, match="solver must be one of batched, reference"):
        model.rollout(*args)
