"""Training on patches (``meshodenet.subdomain.PatchTraining``) on ``plate_cantilever`` (182
nodes, the paper's mesh), float64, synthetic trajectories near rest.

MeshGraphNet is exact: a batch holding every patch of some frames has the whole mesh's loss
and gradient to round-off for k = 1, 2, 4, and a halo one hop short breaks it.
Implicit-Energy's one-step loss with a driven halo equals the whole mesh's for k = 1 and for
halos that reach the whole mesh, and differs otherwise (the bias docs/SUBDOMAIN.md measures);
its residual loss sums exactly over patches. Through ``fit``: the learner's checkpoints,
exact resume. Bad input: ``patch_nodes`` out of range, learners that cannot train on patches.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from meshodenet.energy.model import ImplicitEnergy, energy_presets
from meshodenet.gnn.imex import MeshODENetIMEX, imex_presets
from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig
from meshodenet.subdomain import PatchTraining, energy_view, halo_depth, patch_count
from meshodenet.training.train import TrainConfig, fit, load_checkpoint
from tests.test_partition import case_mesh, lively, synthetic

torch.set_num_threads(1)

RTOL = 1e-12
#: node budgets on the 182-node mesh: k = 1, 2, 4 patches
BUDGETS = {1: 182, 2: 91, 4: 46}


@pytest.fixture(scope="module")
def plate():
    mesh = case_mesh("plate_cantilever")
    return mesh, synthetic(mesh, frames=6)


@pytest.fixture(scope="module")
def mgn(plate):
    mesh, data = plate
    torch.manual_seed(0)
    cfg = MeshGraphNetConfig(hidden=16, layers=3, mlp_hidden_layers=1, rest_position=True)
    return lively(MeshGraphNet(mesh, cfg, data).double())


@pytest.fixture(scope="module")
def energy(plate):
    mesh, data = plate
    torch.manual_seed(0)
    return lively(ImplicitEnergy(mesh, energy_presets("quick", mesh.kind)[1], data), scale=0.1)


def loss_and_grad(model, loss):
    model.zero_grad()
    loss.backward()
    return float(loss.detach()), torch.cat([p.grad.reshape(-1) for p in model.parameters()])


def rel(a, b) -> float:
    return float((torch.as_tensor(a) - b).abs().max() / torch.as_tensor(b).abs().max())


FRAMES = torch.tensor([0, 3, 7, 9])  # (trajectory, frame) samples, frame 0 of each included


@pytest.mark.parametrize("k", sorted(BUDGETS))
def test_mgn_on_patches_is_the_whole_mesh_loss_and_gradient(plate, mgn, k):
    data = plate[1]
    whole, g_whole = loss_and_grad(mgn, mgn.training_loss(data, FRAMES))
    pt = PatchTraining(mgn, BUDGETS[k])
    assert pt.k == k and pt.halo == halo_depth(mgn) == 3
    patched, g = loss_and_grad(mgn, pt.training_loss(data, pt.every_patch(FRAMES)))
    assert rel(patched, whole) < RTOL and rel(g, g_whole) < RTOL


def test_mgn_halo_one_hop_short_is_not_exact(plate, mgn):
    data = plate[1]
    whole = float(mgn.training_loss(data, FRAMES).detach())
    pt = PatchTraining(mgn, BUDGETS[4], halo=halo_depth(mgn) - 1)
    assert rel(float(pt.training_loss(data, pt.every_patch(FRAMES)).detach()), whole) > 1e-8


def test_patch_frames_are_the_whole_frames_at_the_patch_nodes(plate, mgn, energy):
    data = plate[1]
    patch = PatchTraining(mgn, BUDGETS[4]).patches[1]
    nodes = patch.nodes
    for a, b in zip(mgn._frames(data, FRAMES, nodes)[1:], mgn._frames(data, FRAMES)[1:]):
        assert torch.equal(a, b[:, nodes])
    view = energy_view(energy, patch, 1)
    _, xk, vk, x1, _ = view._frames(data, FRAMES, nodes)
    _, xk_w, vk_w, x1_w, _ = energy._frames(data, FRAMES)
    assert torch.equal(xk, xk_w[:, nodes]) and torch.equal(x1, x1_w[:, nodes])
    assert torch.equal(vk, vk_w[:, nodes] * view.free[:, None])


@pytest.mark.parametrize("k", (1, 2))
def test_energy_driven_halo_is_exact_when_it_reaches_the_whole_mesh(plate, energy, k):
    data = plate[1]
    whole, g_whole = loss_and_grad(energy, energy.training_loss(data, FRAMES))
    pt = PatchTraining(energy, BUDGETS[k], halo=1 if k == 1 else 200)
    patched, g = loss_and_grad(energy, pt.training_loss(data, pt.every_patch(FRAMES)))
    assert rel(patched, whole) < RTOL and rel(g, g_whole) < RTOL


def test_energy_driven_halo_is_biased_and_less_so_when_deeper(plate, energy):
    data = plate[1]
    whole = float(energy.training_loss(data, FRAMES).detach())
    bias = []
    for rings in (1, 2, 4):
        pt = PatchTraining(energy, BUDGETS[4], halo=rings)
        bias.append(abs(float(pt.training_loss(data, pt.every_patch(FRAMES)).detach()) / whole - 1))
    assert bias[0] > 1e-8 and bias[2] < bias[1] < bias[0]  # far above round-off (1e-15)


def test_energy_residual_loss_sums_exactly_over_patches(plate, energy):
    data = plate[1]
    one = PatchTraining(energy, BUDGETS[1], loss="residual")
    whole, g_whole = loss_and_grad(energy, one.training_loss(data, one.every_patch(FRAMES)))
    pt = PatchTraining(energy, BUDGETS[4], loss="residual")
    patched, g = loss_and_grad(energy, pt.training_loss(data, pt.every_patch(FRAMES)))
    assert rel(patched, whole) < RTOL and rel(g, g_whole) < RTOL


def test_bad_input_names_the_field(plate, mgn, energy):
    mesh = plate[0]
    for bad in (0, -3, mesh.n_nodes + 1, 50.0, True):
        with pytest.raises(ValueError, match="patch_nodes"):
            PatchTraining(mgn, bad)
    with pytest.raises(ValueError, match="patch_nodes"):
        TrainConfig(patch_nodes=-1)
    assert patch_count(mesh.n_nodes, 2000 if mesh.n_nodes >= 2000 else mesh.n_nodes) == 1
    imex = MeshODENetIMEX(mesh, imex_presets("smoke", mesh.kind)[1], plate[1])
    with pytest.raises(TypeError, match="meshodenet_imex.*implicit-explicit"):
        PatchTraining(imex, 50)
    shooting = ImplicitEnergy(mesh, dataclasses.replace(energy.config, shooting=2), plate[1])
    with pytest.raises(ValueError, match="shooting"):
        PatchTraining(shooting, 50)
    with pytest.raises(ValueError, match="loss"):
        PatchTraining(mgn, 50, loss="residual")


def test_fit_on_patches_writes_the_learners_checkpoints_and_resumes_exactly(plate, tmp_path):
    mesh, data = plate[0], plate[1].to(dtype=torch.float32)
    cfg = TrainConfig(epochs=2, lr=1e-3, lr_milestones=(), batch_size=4, max_batches=3,
                      val_fraction=0.0, patch_nodes=BUDGETS[4])
    fit_resumes_exactly(lambda: MeshGraphNet(mesh, MeshGraphNetConfig(
        hidden=8, layers=2, noise=0.1, mlp_hidden_layers=1), data), data, cfg, tmp_path, "mgn")


def fit_resumes_exactly(make, data, cfg: TrainConfig, tmp_path, name: str) -> None:
    """``fit`` of ``PatchTraining`` around a learner from ``make()`` (seeded): two epochs
    straight equal one epoch and a resumed second, bit for bit; ``last.pt`` is the learner's
    own checkpoint (``name``, its state), and the model ``load_model`` rebuilds from it rolls
    out as the trained learner."""
    def run(out, epochs, resume=False):
        torch.manual_seed(0)
        learner = make()
        fit(PatchTraining(learner, cfg.patch_nodes), data, data.subset(torch.arange(1)),
            dataclasses.replace(cfg, epochs=epochs), out, resume=resume, progress=False)
        return learner

    straight = run(tmp_path / "a", 2)
    run(tmp_path / "b", 1)
    resumed = run(tmp_path / "b", 2, resume=True)
    for key, value in straight.state_dict().items():
        assert torch.equal(value, resumed.state_dict()[key]), key
    ck = load_checkpoint(tmp_path / "a" / "last.pt")
    assert ck["model_info"]["name"] == name and set(ck["model"]) == set(straight.state_dict())
    from meshodenet.registry import load_model

    loaded, _ = load_model(tmp_path / "a" / "last.pt")
    start = (data.pos[:1, 0], data.vel[:1, 0], data.youngs[:1], data.t[:3])
    assert torch.equal(loaded.rollout(*start)[0], straight.rollout(*start)[0])


def test_runner_wraps_the_model_when_patch_nodes_is_set(mgn):
    from benchmarks.suite.runs import on_patches

    assert on_patches(mgn, TrainConfig()) is mgn
    pt = on_patches(mgn, TrainConfig(patch_nodes=60))
    assert isinstance(pt, PatchTraining) and pt.k == 4 and pt.learner is mgn
    assert np.array_equal(np.sort(np.concatenate([p.inner_nodes for p in pt.patches])),
                          np.arange(mgn.mesh.n_nodes))


def test_a_total_budget_bounds_every_patch_halo_included(plate, mgn, energy):
    """With ``budget = "total"`` every patch, halo included, holds at most ``patch_nodes``
    nodes (more parts are cut than ``ceil(N / patch_nodes)``); with ``inner`` the halo comes
    on top; a halo that alone is about the budget is refused, naming ``patch_nodes``."""
    for model, budget in ((mgn, 100), (energy, 40)):
        inner = PatchTraining(model, budget)
        total = PatchTraining(model, budget, budget="total")
        assert max(p.n_nodes for p in inner.patches) > budget
        assert max(p.n_nodes for p in total.patches) <= budget
        assert total.k > inner.k == patch_count(plate[0].n_nodes, budget)
    with pytest.raises(ValueError, match="patch_nodes = 40 .*halo"):
        PatchTraining(mgn, 40, budget="total")  # 3 hops around any part: more than 40 nodes
    with pytest.raises(ValueError, match="patch_budget"):
        PatchTraining(mgn, 40, budget="halo")
    with pytest.raises(ValueError, match="patch_budget"):
        TrainConfig(patch_budget="all")
