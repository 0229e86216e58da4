"""Implicit-Energy's stiffness prior (``EnergyConfig.stiffness_prior``, docs/ENERGY.md "No bad
seed"): each element's fixed stiffness factor ``kappa_e`` keeps zero force and positive
stiffness at rest, the ``features`` least-squares fit recovers a per-element stiffness linear
in the static features, old configurations and checkpoints stay ``uniform``. The gradient,
Hessian, invariance and batched-energy checks with a prior are tests/test_energy.py's,
parametrized over ``STIFFNESS_PRIORS``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from meshodenet.energy.core import POWER
from meshodenet.energy.model import STIFFNESS_PRIORS, EnergyConfig, energy_presets
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec, load_model
from tests.conftest import rod_arrays, strip_arrays
from tests.test_energy import _model, set_known_energy


@pytest.mark.parametrize("make", [rod_arrays, strip_arrays])
def test_prior_scales_each_element_and_keeps_it_stiff_at_rest(make):
    """At rest: no force, and each element's stiffness (``U''(0)`` of an edge's stretch,
    ``U'(0)`` of a hinge's squared angle or curvature: ``POWER``) is ``kappa_e`` times the
    one of the same model without the prior (> 0); the Hessian there is positive
    semidefinite."""
    arrays = make()
    model, tr = _model(arrays, stiffness_prior="features")
    plain = model.system(tr.youngs[:2])
    plain.prior = {}
    sys = model.system(tr.youngs[:2])
    rest = torch.as_tensor(arrays["rest_pos"])[None].repeat(2, 1, 1)
    assert torch.allclose(sys.gradient(rest), torch.zeros_like(rest), atol=1e-12)
    for kind, (q, _, _) in sys.geometry(rest).items():
        got, want = (s.derivatives(kind, q, 2, False)[POWER[kind] - 1] for s in (sys, plain))
        assert bool((got > 0).all())
        assert torch.allclose(got, getattr(model, f"{kind}_prior") * want, rtol=1e-13)
    H = sys.hessian(rest)
    assert float(torch.linalg.eigvalsh(H).min()) > -1e-10 * float(H.abs().max())


def test_features_fit_recovers_a_per_element_stiffness_linear_in_the_features():
    """Data made by the model itself with ``g = 1`` and known per-element stiffnesses
    ``k_e = theta . (1, s_e)`` (edges and dihedral hinges of a sagging strip): the
    ``features`` fit finds every element's stiffness (largest relative error 2.2e-8 for
    edges, 2.8e-5 for the hinges, whose forces are 1e-3 of the edges' and are resolved to
    Newton's tolerance); a ``uniform`` model has no prior buffers."""
    arrays = strip_arrays(nx=6, ny=3, B=3, T=8)
    model, tr = _model(arrays, train=False, stiffness_prior="features")
    rng = np.random.default_rng(5)
    set_known_energy(model, {"edge": 0.02, "dihedral": 0.02}, [5e6, 15.4, 0.3, 1e-6],
                     {"edge": -9.0, "dihedral": -16.0})
    truth = {}
    with torch.no_grad():
        for kind in model.kinds:
            basis = torch.stack(model._basis(kind), 1)
            theta = torch.as_tensor(rng.uniform(-0.15, 0.15, basis.shape[1]))
            theta[0] = 1.0
            ke = basis @ theta
            assert float(ke.min()) > 0.3
            getattr(model, f"{kind}_prior").copy_(ke)
            truth[kind] = ke * torch.exp(model.terms[kind].log_stiffness)
        pos, vel = model.rollout(tr.pos[:, 0], tr.vel[:, 0] * 0, tr.youngs, tr.t)
        for kind in model.kinds:
            model.terms[kind].log_stiffness.fill_(0.0)
            getattr(model, f"{kind}_prior").fill_(1.0)
    data = Trajectories(tr.t, pos, vel * 0, tr.youngs)
    model._fit_log_stiffness(data, every=1)
    for kind in model.kinds:
        kappa = getattr(model, f"{kind}_prior")
        got = kappa * torch.exp(model.terms[kind].log_stiffness.detach())
        assert abs(float(kappa.mean()) - 1) < 1e-12
        err = float(((got - truth[kind]) / truth[kind]).abs().max())
        print(f"{kind}: largest relative error of k_e {err:.1e}")
        assert err < (1e-6 if kind == "edge" else 1e-4)  # hinges: 1e-3 of the edges' forces
    uniform = dataclasses.replace(model.config, stiffness_prior="uniform")
    assert not any(n.endswith("_prior") for n, _ in
                   type(model)(model.mesh, uniform).named_buffers())


def test_stiffness_prior_config_defaults_and_presets():
    """An unknown prior names the valid ones; a stored configuration without the field (runs
    before it existed) is ``uniform``, whose model has no prior buffers (old checkpoints
    load); ``quick`` sets ``features`` for triangle meshes only."""
    with pytest.raises(ValueError, match="stiffness_prior must be one of uniform, features"):
        EnergyConfig(stiffness_prior="linear")
    spec = get_model_spec("implicit_energy")
    old = {k: v for k, v in dataclasses.asdict(EnergyConfig()).items() if k != "stiffness_prior"}
    assert spec.config_from_dict(old).stiffness_prior == "uniform"
    assert list(STIFFNESS_PRIORS)[0] == EnergyConfig().stiffness_prior
    assert energy_presets("quick", "triangle")[1].stiffness_prior == "features"
    assert energy_presets("quick", "line")[1].stiffness_prior == "uniform"
    assert energy_presets("paper", "triangle")[1].stiffness_prior == "uniform"


def test_features_prior_trains_and_reloads(tmp_path):
    from meshodenet.training.train import fit

    spec = get_model_spec("implicit_energy")
    arrays = strip_arrays(B=4, T=6)
    mesh = Mesh.from_arrays(arrays)
    tr = Trajectories.from_arrays(arrays)
    tc, mc = spec.presets("smoke", mesh.kind)
    mc = dataclasses.replace(mc, stiffness_prior="features")
    model = spec.build(mesh, mc, tr)
    assert all(bool((getattr(model, f"{k}_prior") > 0).all()) for k in model.kinds)
    fit(model, tr.subset(slice(0, 3)), tr.subset(slice(3, 4)), tc, tmp_path, progress=False)
    again, _ = load_model(tmp_path / "last.pt")
    assert again.config == mc
    assert torch.equal(again.edge_prior, model.edge_prior)
    with torch.no_grad():
        a = model.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
        b = again.rollout(tr.pos[:1, 0], tr.vel[:1, 0], tr.youngs[:1], tr.t)[0]
    assert torch.isfinite(a).all() and torch.equal(a, b)

