"""Implicit-Energy told less (``meshodenet.energy.dissipation``, ``meshodenet.energy.model_dissipation``):
the learned dissipation's derivatives, sign and invariances, its place in the backward-Euler
step, the least-squares drag, training and reloading, configuration errors."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
import torch

from meshodenet.energy.dissipation import node_features
from meshodenet.energy.model import ImplicitEnergy
from meshodenet.energy.model_dissipation import (
    DissipationConfig,
    ImplicitEnergyDissipation,
    dissipation_presets,
)
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec, load_model
from tests.conftest import rod_arrays, strip_arrays

H = 0.01


def _model(arrays, train=True, seed=0, **cfg):
    """A small model with random coefficients: every MLP perturbed, each element its own
    factor, both terms on (``stiffness_prior = features``)."""
    torch.manual_seed(seed)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays, dtype=torch.float64)
    cfg = {"hidden": 8, "layers": 1, "damping_hidden": 8, "stiffness_prior": "features", **cfg}
    model = ImplicitEnergyDissipation(mesh, DissipationConfig(**cfg), tr if train else None)
    with torch.no_grad():
        for k in model.kinds:
            getattr(model, f"{k}_sigma").fill_(0.02)
            model.terms[k].log_stiffness.fill_(-11.5)
        for t, term in model.dterms.items():
            term.log_rate0.fill_(math.log(1e-3 if t == "node" else 1e-7))
            prior = getattr(model, f"{t}_dprior")
            prior.copy_(0.3 + 2.7 * torch.rand_like(prior))
            for p in term.mlp.parameters():
                p.add_(0.3 * torch.randn_like(p))
    return model, tr


def _state(arrays, seed=3, scale=0.004):
    """``(x_k, v)`` ``(2, N, 3)``: a perturbed rest shape and random velocities (zero on
    clamped nodes)."""
    g = np.random.default_rng(seed)
    x = arrays["rest_pos"] + scale * g.standard_normal(arrays["rest_pos"].shape)
    v = g.standard_normal(x.shape) * (arrays["node_type"] == 0)[:, None]
    return (torch.as_tensor(x)[None].repeat(2, 1, 1),
            torch.as_tensor(v)[None] * torch.tensor([1.0, 0.5], dtype=torch.float64)[:, None, None])


def _damping(model, tr, xk):
    return model._damping(model.system(tr.youngs[:2]), xk)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_dissipation_gradient_and_hessian_match_finite_differences(make):
    """``dD/dv = C v`` and ``d2D/dv2 = C`` against central differences of ``D`` and of
    ``C v``; the step's term ``h D((x - x_k)/h)`` has the gradient ``C v`` and the Hessian
    ``C / h`` in ``x``, through the model's residual and Newton matrix."""
    arrays = make()
    model, tr = _model(arrays)
    xk, v = _state(arrays)
    C = _damping(model, tr, xk)
    act = model._active(xk, v)
    M = C.matrix(act, model.mesh.n_nodes)
    F = C.force(v).reshape(2, -1)[:, act]
    eps = 1e-6
    for i in range(len(act)):
        dv = torch.zeros(2, 3 * model.mesh.n_nodes, dtype=torch.float64)
        dv[:, act[i]] = eps
        vp, vm = v + dv.reshape(v.shape), v - dv.reshape(v.shape)
        fd = (C.dissipation(vp) - C.dissipation(vm)) / (2 * eps)
        assert torch.allclose(F[:, i], fd, rtol=1e-7, atol=1e-9 * F.abs().max())
        fdh = (C.force(vp) - C.force(vm)).reshape(2, -1)[:, act] / (2 * eps)
        assert torch.allclose(M[:, :, i], fdh, rtol=1e-7, atol=1e-9 * M.abs().max())
    assert torch.allclose(M, M.transpose(1, 2), rtol=0, atol=1e-14 * M.abs().max())
    assert C.alpha is not None and float(C.alpha.min()) > 0  # the edge term is on
    # through the model: residual and matrix of the step (the energy's part cancels)
    sys = model.system(tr.youngs[:2])
    x = xk + H * v
    vk = torch.zeros_like(v)
    r = model._residual(sys, x, xk, vk, H)[:, act] \
        - ImplicitEnergy._residual(model, sys, x, xk, vk, H)[:, act]
    assert torch.allclose(r, F, rtol=1e-10, atol=1e-14 * F.abs().max())
    A = model._matrix(sys, x, H, act, xk=xk) \
        - ImplicitEnergy._matrix(model, sys, x, H, act)
    assert torch.allclose(A, M / H, rtol=1e-10, atol=1e-14 * M.abs().max() / H)
    phi = model._objective(sys, x, xk, vk, H) \
        - ImplicitEnergy._objective(model, sys, x, xk, vk, H)
    assert torch.allclose(phi, H * C.dissipation(v), rtol=1e-8)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_dissipation_is_nonnegative_zero_at_rest_and_never_adds_energy(make):
    arrays = make()
    model, tr = _model(arrays)
    xk, v = _state(arrays)
    C = _damping(model, tr, xk)
    zero = torch.zeros_like(v)
    assert torch.equal(C.dissipation(zero), torch.zeros(2, dtype=torch.float64))
    assert torch.equal(C.force(zero), zero)
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        w = torch.randn(v.shape, dtype=v.dtype, generator=g) * model.free[:, None]
        D = C.dissipation(w)
        assert bool((D > 0).all())
        # the dissipative force -C v has the power -2 D <= 0
        assert torch.allclose((C.force(w) * w).sum((1, 2)), 2 * D, rtol=1e-12)
    # convex: C positive semidefinite
    act = model._active(xk, v)
    assert float(torch.linalg.eigvalsh(C.matrix(act, model.mesh.n_nodes)).min()) > 0


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_dissipation_is_invariant_under_rigid_motions(make):
    """``D`` of the rotated and translated state is ``D``; the force rotates with it; a rigid
    rotation rate dissipates nothing in the edge term."""
    arrays = make()
    model, tr = _model(arrays)
    xk, v = _state(arrays)
    a, b = 0.7, -0.4
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]],
                      dtype=torch.float64)
    Rx = torch.tensor([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]],
                      dtype=torch.float64)
    R = Rx @ Rz
    moved = xk @ R.T + torch.tensor([0.3, -1.0, 0.2], dtype=torch.float64)
    C, Cm = _damping(model, tr, xk), _damping(model, tr, moved)
    assert torch.allclose(Cm.dissipation(v @ R.T), C.dissipation(v), rtol=1e-12)
    assert torch.allclose(Cm.force(v @ R.T), C.force(v) @ R.T, rtol=1e-10,
                          atol=1e-14 * float(C.force(v).abs().max()))
    omega = torch.tensor([0.2, -0.5, 1.0], dtype=torch.float64)
    spin = torch.cross(omega.expand_as(xk), xk, dim=-1)  # v = omega x x: a rigid rotation rate
    assert float(C.rates(spin).abs().max()) < 1e-12 * float(spin.abs().max())


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_step_solves_backward_euler_and_the_solvers_agree(make):
    """The Newton step zeroes the residual with the learned damping; the batched solver
    (banded, per trajectory) rolls out what the reference solver does, within Newton's
    tolerance."""
    arrays = make()
    model, tr = _model(arrays)
    sys = model.system(tr.youngs[:2])
    xk, vk = tr.pos[:2, 2], (tr.pos[:2, 2] - tr.pos[:2, 1]) / (tr.t[2] - tr.t[1])
    vk = vk * model.free[:, None]
    act = model._active(xk, vk)
    h = float(tr.t[1] - tr.t[0])
    with torch.no_grad():
        x = model.step(sys, xk, vk, h, act)
    r = model._residual(sys, x, xk, vk, h)[:, act]
    assert float(r.abs().max()) < 1e-8 * float(model.mass.max() / h**2 * 0.01 + model.force.abs().max())
    with torch.no_grad():
        model.solver = "batched"
        a, _ = model.rollout(tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
        model.solver = "reference"
        b, _ = model.rollout(tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
    assert float((a - b).abs().max()) < 10 * model.config.newton_rtol * model.length
    assert float((a - tr.pos).abs().max()) > 0  # not a copy of the data


def test_the_mesh_drag_is_never_read():
    """Only masses and loads are given: another ``damping`` in the mesh changes nothing, and
    the mesh passed in is left as it was."""
    arrays = rod_arrays()
    model, tr = _model(arrays)
    other = dict(arrays, damping=arrays["damping"] * 7.0)
    again, _ = _model(other)
    assert np.array_equal(model.mesh.damping, arrays["damping"])
    with torch.no_grad():
        a, _ = model.rollout(tr.pos[:2, 0], tr.vel[:2, 0], tr.youngs[:2], tr.t)
        b, _ = again.rollout(tr.pos[:2, 0], tr.vel[:2, 0], tr.youngs[:2], tr.t)
    # equal to round-off (LAPACK's banded kernels may round the last bit differently with
    # the arrays' alignment; the other drag would move the rod by millimetres)
    assert torch.allclose(a, b, rtol=0, atol=1e-13) and float(model.damping.abs().max()) == 0


def test_least_squares_recovers_a_known_drag_of_a_free_body():
    """A free rod rolled out by the model itself with a known drag (each node its own, linear
    in its features: a heavy, dragging middle node): the total-momentum fit finds every node's
    coefficient (relative error 1e-6) whatever the energy."""
    arrays = rod_arrays(n_nodes=6, B=3, T=8)
    arrays["mass"] = arrays["mass"] * np.array([1, 1, 30, 1, 1, 1])
    model, tr = _model(arrays, train=False, damping_terms=("node",))
    with torch.no_grad():
        model.ystats.copy_(torch.tensor([1e9, 20.0, 1.0, 1e-6]))
        for k in model.kinds:
            model.terms[k].log_stiffness.fill_(-16.0)
        term = model.dterms["node"]
        for p in term.mlp.parameters():
            p.zero_()
        static = model.node_dstatic
        want = 0.5 + 0.2 * static[:, 0] + 0.1 * static[:, 1]  # N s/m, linear in the features
        assert float(want.min()) > 0
        term.log_rate0.fill_(math.log(float(want.mean())))
        model.node_dprior.copy_(want / want.mean())
        pos, vel = model.rollout(tr.pos[:, 0], tr.vel[:, 0] * 0, tr.youngs, tr.t)
        term.log_rate0.fill_(0.0)
        model.node_dprior.fill_(1.0)
    model._fit_log_stiffness(Trajectories(tr.t, pos, vel, tr.youngs), every=1)
    with torch.no_grad():
        got = model.coefficients(torch.zeros(1, dtype=torch.float64))["node"][0]
    assert float(((got - want) / want).abs().max()) < 1e-6


def test_clamped_mesh_fits_drag_and_stiffness_together():
    """A clamped strip (no total-momentum balance): the joint fit gives positive
    coefficients to both terms and the model steps."""
    arrays = strip_arrays()
    model, tr = _model(arrays, train=False)
    model._statistics(tr)
    model._fit_log_stiffness(tr, every=1)
    c = model.coefficients(torch.zeros(1, dtype=torch.float64))
    assert all(bool((v > 0).all()) and bool(torch.isfinite(v).all()) for v in c.values())


def test_node_features_are_standardised_and_see_mass_and_measure():
    mesh = Mesh.from_arrays(rod_arrays())
    f = node_features(mesh)
    assert f.shape == (mesh.n_nodes, 4)
    assert np.allclose(f[:, 0], 0) and np.allclose(f[:, 3], 0)  # equal masses, no triangles
    assert f[0, 1] < f[2, 1] and f[0, 2] < f[2, 2]  # an end node: half the length, one edge
    strip = Mesh.from_arrays(strip_arrays())
    assert np.allclose(node_features(strip).mean(0), 0, atol=1e-12)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_registered_trains_and_reloads(make, tmp_path):
    from meshodenet.training.train import fit

    spec = get_model_spec("implicit_energy_dissipation")
    arrays = make(B=4, T=6)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    torch.manual_seed(0)
    model = spec.build(mesh, mc, tr)
    before = {k: v.detach().clone() for k, v in model.dterms.state_dict().items()}
    fit(model, tr.subset(slice(0, 3)), tr.subset(slice(3, 4)), tc, tmp_path, progress=False)
    assert any(not torch.equal(v, model.dterms.state_dict()[k]) for k, v in before.items())
    again, _ = load_model(tmp_path / "last.pt")  # weights_only
    assert again.config == mc and isinstance(again, ImplicitEnergyDissipation)
    with torch.no_grad():
        a = model.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
        b = again.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
    assert torch.isfinite(a).all() and torch.equal(a, b)


def test_trains_on_the_solvers_data(tiny_case, tmp_path):
    """The smoke preset on the tiny rod made by the real ground-truth solver: the drag starts
    at the data's (a free body: the total-momentum fit), trains end to end, reloads and rolls
    the test split out closer than standing still."""
    from groundtruth import store
    from meshodenet.training.train import fit

    case, root = tiny_case
    train = store.load_split(case, "train", root)
    test = Trajectories.from_arrays(store.load_split(case, "test", root))
    spec = get_model_spec("implicit_energy_dissipation")
    mesh = Mesh.from_arrays(train)
    tr = Trajectories.from_arrays(train)
    tc, mc = spec.presets("smoke", mesh.kind)
    mc = dataclasses.replace(mc, stiffness_prior="features", damping_terms=("node",))
    torch.manual_seed(0)
    model = spec.build(mesh, mc, tr)
    with torch.no_grad():
        beta = model.coefficients(torch.zeros(1, dtype=torch.float64))["node"][0]
    true = torch.as_tensor(train["damping"])
    assert float(((beta - true) / true).abs().max()) < 3e-4  # the data in float32
    fit(model, tr.subset(slice(0, 3)), tr.subset(slice(3, 4)), tc, tmp_path, progress=False)
    again, _ = load_model(tmp_path / "best.pt")
    pos, _ = again.rollout_all(test)
    err = float((pos - test.pos).square().sum(-1).mean().sqrt())
    still = float((test.pos[:, :1] - test.pos).square().sum(-1).mean().sqrt())
    assert err < 0.2 * still


@pytest.mark.parametrize("field, value", [("damping_terms", ("node", "wind")),
                                          ("damping_terms", ()),
                                          ("damping_terms", ("node", "node")),
                                          ("damping_terms", ["node"]),
                                          ("damping_step", 0.0), ("damping_step", True),
                                          ("damping_train", "some"),
                                          ("damping_step", math.inf),
                                          ("damping_hidden", 0), ("damping_layers", -1),
                                          ("stiffness_prior", "nope")])
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=rf"DissipationConfig\.{field}.*{re.escape(repr(value))}"):
        DissipationConfig(**{field: value})


def test_presets_and_suite():
    from benchmarks.suite.suites import get_suite

    for kind, train in (("line", "none"), ("triangle", "rate")):
        _, mc = dissipation_presets("quick", kind)
        assert mc.stiffness_prior == "features" and mc.damping_terms == ("node",)
        assert mc.damping_train == train and mc.damping_step == 0.01
    ids = [r.run_id for r in get_suite("quick").runs(only="*implicit_energy*")]
    for case in ("rod_falling", "plate_cantilever"):
        assert ids.index(f"{case}-implicit_energy-quick-s0") + 1 \
            == ids.index(f"{case}-implicit_energy_dissipation-quick-s0")


@pytest.mark.parametrize("train", ["all", "rate", "none"])
def test_damping_train_chooses_what_moves(train):
    """``damping_train``: ``none`` leaves the coefficients at their start, ``rate`` trains
    each term's rate alone, ``all`` the MLP too; the energy trains in every case."""
    arrays = rod_arrays()
    model, tr = _model(arrays, damping_train=train)
    loss = model.training_loss(tr, torch.arange(model.n_training_samples(tr)))
    loss.backward()
    for term in model.dterms.values():
        assert (term.log_rate.grad is not None) == (train != "none")
        assert all((p.grad is not None) == (train == "all") for p in term.mlp.parameters())
    assert all(p.grad is not None for p in model.terms.parameters())


def test_damping_matrix_on_a_subset_of_coordinates():
    """``Damping.matrix`` on the unknowns equals the full matrix's rows and columns."""
    arrays = strip_arrays()
    model, tr = _model(arrays)
    xk, v = _state(arrays)
    C = _damping(model, tr, xk)
    n = 3 * model.mesh.n_nodes
    full = C.matrix(torch.arange(n), model.mesh.n_nodes)
    act = model._active(xk, v)
    assert torch.allclose(C.matrix(act, model.mesh.n_nodes), full[:, act][:, :, act],
                          rtol=1e-14, atol=0)



def test_least_squares_basis_has_no_dependent_columns():
    """A triangle mesh's lumped masses are its nodes' areas, a rod's end nodes differ in
    both length and degree: the drag's basis keeps independent columns only, as many as the
    features' rank on the free nodes."""
    for make in (strip_arrays, rod_arrays):
        arrays = make()
        arrays["mass"] = arrays["mass"] * (1 + node_features(Mesh.from_arrays(arrays))[:, 1])
        model, _ = _model(arrays, train=False)
        basis = model._damping_basis("node")
        free = model.free
        full = torch.cat([torch.ones(len(free), 1, dtype=torch.float64), model.node_dstatic], 1)
        rank = int(torch.linalg.matrix_rank(full[free]))
        assert len(basis) == rank < full.shape[1]
        assert int(torch.linalg.matrix_rank(torch.stack(basis, 1)[free])) == rank
