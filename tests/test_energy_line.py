"""``meshodenet.energy.planar``: the batched solver's numpy evaluation of a planar mesh's edge and
rod-hinge energy (docs/ENERGY.md, "A numpy evaluation for planar meshes") against the torch one
it stands in for."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshodenet.energy import planar as el
from meshodenet.energy.core import BatchedEnergy, _edge_geometry, _hinge_geometry
from meshodenet.energy.model import STIFFNESS_PRIORS, ImplicitEnergy
from tests.conftest import rod_arrays, strip_arrays
from tests.test_energy import _model, _perturbed


def planar_strip_arrays():
    """``strip_arrays`` turned into its own plane: the sag along ``y``, gravity along ``y``
    (a triangle mesh that Implicit-Energy solves in its plane, edges only)."""
    a = dict(strip_arrays())
    for k in ("pos", "vel"):
        v = a[k].copy()
        v[..., 1] = a["rest_pos"][:, 1] + v[..., 2] if k == "pos" else v[..., 2]
        v[..., 2] = 0.0
        a[k] = v
    f = np.zeros_like(a["force"])
    f[:, 1] = a["force"][:, 2]
    a["force"] = f
    return a


def _random_planar(n, seed):
    rng = np.random.default_rng(seed)
    x = np.zeros((3, n, 3))
    x[..., 0] = 0.1 * np.arange(n)
    x[..., :2] += 0.02 * rng.standard_normal((3, n, 2))
    return x, rng


def _against(torch_geo, numpy_geo, sel, rng):
    """``q``, ``dq`` and ``alpha dq dq^T + beta d2q`` of the two, on the in-plane ``sel``."""
    q, dq, d2q = (t.numpy() for t in torch_geo)
    qn, dqn, parts = numpy_geo
    k = len(sel)
    alpha, beta = rng.standard_normal(qn.shape), rng.standard_normal(qn.shape)
    mixed = el.element_hessian(parts, alpha, beta).reshape(*qn.shape, k, k)
    dqs, d2qs = dq[..., sel], d2q[..., sel][..., sel, :]
    ref = alpha[..., None, None] * dqs[..., :, None] * dqs[..., None, :] \
        + beta[..., None, None] * d2qs
    alone = el.element_hessian(parts, np.zeros(qn.shape), np.ones(qn.shape))
    assert np.allclose(qn, q, rtol=1e-12, atol=1e-15)
    assert np.allclose(dqn, dqs, rtol=0, atol=1e-12 * np.abs(dqs).max())
    assert np.allclose(alone.reshape(d2qs.shape), d2qs, rtol=0, atol=1e-12 * np.abs(d2qs).max())
    assert np.allclose(mixed, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.allclose(mixed, mixed.swapaxes(-1, -2), rtol=0, atol=1e-14 * np.abs(ref).max())


def test_edge_geometry_is_the_torch_geometry_in_the_plane():
    x, rng = _random_planar(7, 0)
    nodes = np.stack([np.arange(6), np.arange(1, 7)], 1)
    l0 = 0.1 * (1 + 0.2 * rng.random(6))
    _against(_edge_geometry(torch.as_tensor(x), torch.as_tensor(nodes), torch.as_tensor(l0),
                            True),
             el.edge_geometry(x[..., :2], nodes, l0, True), np.array([0, 1, 3, 4]), rng)


@pytest.mark.parametrize("bent", [False, True])
def test_hinge_geometry_is_the_torch_geometry_in_the_plane(bent):
    """The turning-angle form of ``kappa``'s derivatives against ``_hinge_geometry``'s
    (straight and curved rest shapes; hinges bent both ways)."""
    x, rng = _random_planar(8, 1)
    nodes = np.stack([np.arange(6), np.arange(1, 7), np.arange(2, 8)], 1)
    kap0 = np.zeros((6, 3))
    if bent:
        kap0[:, 2] = 0.5 * rng.standard_normal(6)
    _against(_hinge_geometry(torch.as_tensor(x), torch.as_tensor(nodes), torch.as_tensor(kap0),
                             True),
             el.hinge_geometry(x[..., :2], nodes, kap0[:, 2], True),
             np.array([0, 1, 3, 4, 6, 7]), rng)


@pytest.mark.parametrize("prior", STIFFNESS_PRIORS)
@pytest.mark.parametrize("make", [rod_arrays, planar_strip_arrays])
def test_planar_energy_equals_the_batched_energy(make, prior):
    """``PlanarLineEnergy.evaluate`` equals ``BatchedEnergy.evaluate`` (energy, gradient,
    band) for orders 0-2, on the whole batch and on a subset of it."""
    arrays = make()
    model, tr = _model(arrays, stiffness_prior=prior)
    sys = model.system(torch.cat([tr.youngs, 1.5 * tr.youngs])[:3])
    x = _perturbed(arrays).repeat(2, 1, 1)[:3]
    x[..., 2] = float(arrays["rest_pos"][0, 2])
    x[2, :, :2] += 0.003 * torch.randn_like(x[2, :, :2])
    act = model._active(x, torch.zeros_like(x))
    be = BatchedEnergy(sys, act, model.mesh.n_nodes)
    assert el.PlanarLineEnergy.applies(be)
    pl = el.PlanarLineEnergy(be)
    for idx in (torch.arange(3), torch.tensor([0, 2])):
        for order in (0, 1, 2):
            ref = be.evaluate(x[idx], idx, order)
            out = pl.evaluate(x[idx].numpy(), idx.numpy(), order)
            for r, o in zip(ref, out):
                assert (r is None) == (o is None)
                if r is not None:
                    r = r.numpy()
                    assert np.allclose(o, r, rtol=1e-12, atol=1e-12 * np.abs(r).max())


def test_the_rollout_uses_numpy_where_it_applies_and_agrees_with_torch():
    """A planar rod's and an in-plane strip's batched rollouts evaluate in numpy and roll out
    the positions of the torch evaluation to Newton's tolerance; an out-of-plane strip, the
    learned-dissipation model and ``clamp_q`` keep torch."""
    from meshodenet.energy.model_dissipation import ImplicitEnergyDissipation

    for make in (rod_arrays, planar_strip_arrays):
        arrays = make()
        model, tr = _model(arrays)
        args = (tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
        sys = model.system(tr.youngs)
        assert isinstance(model._batched_energy(sys, model._active(*args[:2])),
                          el.PlanarLineEnergy)
        with torch.no_grad():
            fast, _ = model.rollout(*args)
            model.line_numpy = False
            slow, _ = model.rollout(*args)
        tol = model.config.newton_rtol * model.length
        assert float((fast - slow).abs().max()) <= tol
    model, tr = _model(strip_arrays())
    sys = model.system(tr.youngs)
    assert isinstance(model._batched_energy(sys, model._active(tr.pos[:, 0], tr.vel[:, 0])),
                      BatchedEnergy)
    assert ImplicitEnergyDissipation.line_numpy is False and ImplicitEnergy.line_numpy is True
    model, tr = _model(rod_arrays(), clamp_q=True)
    sys = model.system(tr.youngs)
    assert isinstance(model._batched_energy(sys, model._active(tr.pos[:, 0], tr.vel[:, 0])),
                      BatchedEnergy)


def test_the_predictor_saves_newton_iterations_and_keeps_the_positions(tmp_path):
    """The previous interval's Newton correction, carried to the next interval's first guess,
    cuts the evaluations of rollouts of a real rod (1 s of the ground-truth solver's data, 10
    intervals; the ``quick`` model before training) and leaves their positions within
    Newton's tolerance of the rollouts without it."""
    import dataclasses

    from benchmarks.suite.generate import generate
    from benchmarks.suite.registry import CASES, register_case
    from groundtruth import store
    from groundtruth.cases import RodCase
    from meshodenet.energy.model import energy_presets
    from meshodenet.mesh.data import Mesh, Trajectories

    case = dataclasses.replace(RodCase(), id="rod_predictor_test", n_train=2, n_test=2,
                               t_end=1.0)
    register_case(case, overwrite=True)
    try:
        generate(case, tmp_path, workers=1, progress=False)
        train, test = (store.load_split(case, s, tmp_path) for s in ("train", "test"))
    finally:
        CASES.pop(case.id, None)
    mesh = Mesh.from_arrays(train)
    torch.manual_seed(0)
    model = ImplicitEnergy(mesh, energy_presets("quick", mesh.kind)[1],
                           Trajectories.from_arrays(train))
    te = Trajectories.from_arrays(test, dtype=torch.float64)
    args = (te.pos[:, 0], te.vel[:, 0], te.youngs, te.t)
    counts, pos = {}, {}
    real = el.PlanarLineEnergy.evaluate
    for predict in (True, False):
        calls = []

        def counting(self, *a, calls=calls):
            calls.append(1)
            return real(self, *a)

        model.newton_predictor = predict
        el.PlanarLineEnergy.evaluate = counting
        try:
            with torch.no_grad():
                pos[predict], _ = model.rollout(*args)
        finally:
            el.PlanarLineEnergy.evaluate = real
        counts[predict] = len(calls)
    tol = model.config.newton_rtol * model.length
    assert counts[True] < counts[False]
    assert float((pos[True] - pos[False]).abs().max()) <= tol


def test_applies_needs_a_planar_line_or_edge_energy():
    be = type("Fake", (), {})()
    be.kinds, be.clamp = ["edge", "dihedral"], False
    be.unknowns = torch.tensor([0, 1, 3, 4])
    assert not el.PlanarLineEnergy.applies(be)
    be.kinds = ["edge", "hinge"]
    assert el.PlanarLineEnergy.applies(be)
    be.unknowns = torch.tensor([0, 1, 2])  # a z coordinate
    assert not el.PlanarLineEnergy.applies(be)
    with pytest.raises(ValueError, match="plane"):
        el.PlanarLineEnergy(be)


def test_newton_starts_again_without_the_predictor_where_it_fails(monkeypatch):
    """A Newton solve that does not converge from the predicted first guess is solved again
    from ``x_k + h v_k`` (the learned-dissipation model's rod rollout once failed so): the
    rollout goes through and equals the one without the predictor."""
    from meshodenet.integrators.implicit import NewtonError

    arrays = rod_arrays(T=12, dt=0.02)
    model, tr = _model(arrays)
    args = (tr.pos[:, 0], tr.vel[:, 0], tr.youngs, tr.t)
    model.newton_predictor = False
    with torch.no_grad():
        plain, _ = model.rollout(*args)
    model.newton_predictor = True
    real, starts = ImplicitEnergy._iterate, []

    def failing_when_predicted(self, evaluate, y, h, where):
        predicted = getattr(failing_when_predicted, "guess", None) is not None
        starts.append(predicted)
        if predicted:
            failing_when_predicted.guess = None
            raise NewtonError("not from the predicted guess")
        return real(self, evaluate, y, h, where)

    def newton(self, be, xk, vk, h, where):
        if getattr(be, "last_correction", None) is not None:
            failing_when_predicted.guess = True
        return real_newton(self, be, xk, vk, h, where)

    real_newton = ImplicitEnergy._newton_batched
    monkeypatch.setattr(ImplicitEnergy, "_iterate", failing_when_predicted)
    monkeypatch.setattr(ImplicitEnergy, "_newton_batched", newton)
    with torch.no_grad():
        again, _ = model.rollout(*args)
    assert sum(starts) == len(tr.t) - 2  # every interval after the first tried the prediction
    assert torch.allclose(again, plain, rtol=0, atol=1e-12)
