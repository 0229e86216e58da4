"""Implicit-Energy's ``clamp_q`` (why: trained ``plate_hanging`` energies failed Newton
where an edge was compressed beyond anything the training frames held and its learned energy
softened there): each element MLP's input ``qhat`` saturates smoothly beyond the training
frames' range, so far beyond it the element energy is ``c/2 qhat^p g(edge + SATURATION)``,
positive curvature for edges. Gradient and Hessian against central differences with
elements on both sides of the range, the batched energy against the assembled one, the range
itself, configuration and reloading."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from meshodenet.energy.core import SATURATION, BatchedEnergy, measure
from meshodenet.energy.model import EnergyConfig
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec, load_model
from tests.conftest import rod_arrays, strip_arrays
from tests.test_energy import _model, _perturbed, check_energy_derivatives


def _clamped_model(make):
    """A model whose clamp binds for 60 % of the perturbed fixture's elements of each kind
    (its range: between their 20th and 60th percentiles of ``qhat``)."""
    arrays = make()
    model, tr = _model(arrays, clamp_q=True)
    sys = model.system(tr.youngs[:2])
    with torch.no_grad():
        for k, (q, _, _) in sys.geometry(_perturbed(arrays)).items():
            u = torch.unique(q / sys.sigma[k])  # sorted; the bounds fall between values
            i, j = len(u) // 5, 3 * len(u) // 5
            getattr(model, f"{k}_qrange").copy_(torch.stack([(u[i] + u[i + 1]) / 2,
                                                             (u[j] + u[j + 1]) / 2]))
    return arrays, model, tr


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_clamped_gradient_and_hessian_match_finite_differences(make):
    arrays, model, tr = _clamped_model(make)
    sys = model.system(tr.youngs[:2])
    x = _perturbed(arrays)
    for k, (q, _, _) in sys.geometry(x).items():  # the check covers both sides of the clamp
        qh, (lo, hi) = q / sys.sigma[k], sys.qrange[k]
        assert bool(((qh > lo) & (qh < hi)).any()) and bool(((qh < lo) | (qh > hi)).any())
    check_energy_derivatives(sys, x)


def test_beyond_the_range_an_edge_energy_is_quadratic():
    """Far above ``hi`` (below ``lo``) ``U = c/2 qhat^2 g(hi + w)`` (``g(lo - w)``, ``w =
    SATURATION``): its second derivative is ``c g > 0`` whatever the MLP does beyond the data,
    and without the clamp it is not."""
    model, tr = _model(strip_arrays(), clamp_q=True)
    sys = model.system(tr.youngs[:1])
    term, n = model.terms["edge"], len(model.edge_nodes)
    static, yhat, yrel = model.edge_static[None], sys.yhat[:, None].expand(1, n), sys.scale("edge")
    for edge in (0.1, -0.1):
        q = torch.full((1, n), 25 * edge)  # 2.5 (or -2.5): 9.6 widths beyond the range
        sat = edge + math.copysign(SATURATION, edge)  # where the MLP's input saturates
        cg = term.taylor(torch.full((1, n), sat), static, yhat, yrel, None)[0] / (0.5 * sat**2)
        u, d1, d2 = term.taylor(q, static, yhat, yrel, (-0.1, 0.1))
        assert torch.allclose(u, 0.5 * q**2 * cg, rtol=1e-6)
        assert torch.allclose(d1, q * cg, rtol=1e-6)
        assert torch.allclose(d2, cg, rtol=1e-6) and bool((d2 > 0).all())
        assert torch.allclose(term(q, static, yhat, yrel, (-0.1, 0.1)), u, rtol=1e-12)
        free = term.taylor(q, static, yhat, yrel, None)[2]
        assert not torch.allclose(free, d2, rtol=1e-3)


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_clamped_batched_energy_equals_the_assembled_energy(make):
    arrays, model, tr = _clamped_model(make)
    sys = model.system(tr.youngs[:2])
    x = _perturbed(arrays)
    act = model._active(x, torch.zeros_like(x))
    be = BatchedEnergy(sys, act, model.mesh.n_nodes)
    idx = torch.arange(2)
    U, dU, ab = be.evaluate(x, idx, 2)
    H = sys.hessian(x)[:, be.unknowns][:, :, be.unknowns]
    n, w = be.n, be.width
    band = torch.zeros_like(H)
    for k in range(w + 1):
        i = torch.arange(n - k)
        band[:, i + k, i] = band[:, i, i + k] = ab[:, k, :n - k]
    assert torch.allclose(U, sys.energy(x), rtol=1e-12)
    g = sys.gradient(x).reshape(2, -1)[:, be.unknowns]
    assert torch.allclose(dU, g, rtol=1e-12, atol=1e-12 * float(g.abs().max()))
    assert torch.allclose(band, H, rtol=1e-12, atol=1e-12 * float(H.abs().max()))


def test_range_is_the_training_frames_and_old_configs_have_no_clamp():
    arrays = strip_arrays()
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays, dtype=torch.float64)
    from meshodenet.energy.model import ImplicitEnergy

    model = ImplicitEnergy(mesh, EnergyConfig(hidden=8, layers=1, clamp_q=True), tr)
    for k, (nodes, _, rest, l0) in model._elems().items():
        qh = measure(k, tr.pos[:, :, nodes], rest, l0) / getattr(model, f"{k}_sigma")
        assert torch.equal(getattr(model, f"{k}_qrange"), torch.stack([qh.min(), qh.max()]))
    plain = ImplicitEnergy(mesh, EnergyConfig(hidden=8, layers=1), tr)
    assert not any(name.endswith("_qrange") for name, _ in plain.named_buffers())
    assert plain.system(tr.youngs[:1]).qrange == {}
    with pytest.raises(ValueError, match="clamp_q must be a bool"):
        EnergyConfig(clamp_q="yes")
    spec = get_model_spec("implicit_energy")
    old = {k: v for k, v in dataclasses.asdict(EnergyConfig()).items() if k != "clamp_q"}
    assert spec.config_from_dict(old).clamp_q is False


def test_clamped_model_trains_and_reloads(tmp_path):
    from meshodenet.training.train import fit

    spec = get_model_spec("implicit_energy")
    arrays = strip_arrays(B=4, T=6)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    mc = dataclasses.replace(mc, clamp_q=True)
    model = spec.build(mesh, mc, tr)
    fit(model, tr.subset(slice(0, 3)), tr.subset(slice(3, 4)), tc, tmp_path, progress=False)
    again, _ = load_model(tmp_path / "last.pt")
    assert again.config == mc
    assert torch.equal(again.edge_qrange, model.edge_qrange)
    with torch.no_grad():
        a = model.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
        b = again.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
    assert torch.isfinite(a).all() and torch.equal(a, b)
