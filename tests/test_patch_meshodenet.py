"""MeshODENet trained on patches with a driven halo (``meshodenet.subdomain.driven``) on
``plate_cantilever`` (182 nodes), float64.

One patch is the whole mesh's loss and gradient to round-off, in every gradient mode, with
frame weights and the release term; a buffer as deep as the window's stencil is exact on any
cut, none is not. On data that are the model's own rollout the whole mesh's loss is zero and
the patches' is the driving's error, which falls at the fourth order of the frame spacing
(cubic Hermite, RK4). The interpolant is exact for cubics. Bad input: adaptive and implicit
integrators, the ``rms`` loss, a bad buffer. Through ``fit``: the learner's checkpoints, exact
resume.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig
from meshodenet.mesh.data import Trajectories
from meshodenet.subdomain import PatchTraining
from meshodenet.subdomain.driven import Hermite
from meshodenet.training.train import TrainConfig
from tests.test_partition import case_mesh, lively, synthetic
from tests.test_patch_training import fit_resumes_exactly, loss_and_grad, rel

torch.set_num_threads(1)

RTOL = 1e-12
#: a smooth activation: RK4 and the Hermite interpolant reach their order on a smooth field
#: (with ReLU's kinks the driving's error falls at about the third order)
SMALL = dict(hidden=16, layers=1, mlp_hidden_layers=1, rest_position=True, activation="tanh")


@pytest.fixture(scope="module")
def plate():
    mesh = case_mesh("plate_cantilever")
    return mesh, synthetic(mesh, frames=11)


def model(plate, scale=0.1, **fields) -> MeshODENet:
    mesh, data = plate
    torch.manual_seed(0)
    m = MeshODENet(mesh, MeshODENetConfig(**dict(SMALL, **fields)), data).double()
    return lively(m, scale=scale) if scale else m


def both(m, pt, data, samples, seed=1):
    """(whole mesh's loss and gradient, every patch's) from the same generator draws."""
    whole = loss_and_grad(m, m.training_loss(data, samples, torch.Generator().manual_seed(seed)))
    every = pt.every_patch(samples)
    return whole, loss_and_grad(m, pt.training_loss(data, every,
                                                    torch.Generator().manual_seed(seed)))


@pytest.mark.parametrize("fields", [
    dict(shooting=5),
    dict(shooting=3, grad_mode="direct", frame_weight=0.5, release_weight=0.1,
         release_fraction=0.5),
    dict(shooting=2, grad_mode="adjoint", integrator="midpoint", substeps=2),
], ids=["checkpoint", "direct-weights-release", "adjoint-midpoint"])
def test_one_patch_is_the_whole_mesh_loss_and_gradient(plate, fields):
    m, data = model(plate, **fields), plate[1]
    pt = PatchTraining(m, plate[0].n_nodes)
    assert pt.k == 1 and not (pt.patches[0].hops > 0).any()
    samples = torch.arange(m.n_training_samples(data))
    (whole, g_whole), (patched, g) = both(m, pt, data, samples)
    assert rel(patched, whole) < RTOL and rel(g, g_whole) < RTOL


def test_a_buffer_as_deep_as_the_windows_stencil_is_exact_and_none_is_not(plate):
    """A window of ``S`` RK4 steps of a 1-layer field reads states ``4 S`` hops away, and the
    halo's first-stage states are the true frame's: ``4 S - 1`` solved rings beyond a part
    leave its inner nodes the whole mesh's."""
    S = 2
    m, data = model(plate, shooting=S), plate[1]
    samples = torch.arange(m.n_training_samples(data))
    for buffer, exact in ((4 * S - 1, True), (0, False)):
        pt = PatchTraining(m, 91, buffer=buffer)
        assert pt.k == 2 and all((p.hops > buffer).any() for p in pt.patches)  # driven nodes
        (whole, g_whole), (patched, g) = both(m, pt, data, samples)
        assert (rel(patched, whole) < RTOL and rel(g, g_whole) < RTOL) == exact
        if not exact:
            assert rel(patched, whole) > 1e-8 and rel(g, g_whole) > 1e-6


def own_rollout(m, base, n: int, span: float = 0.01) -> Trajectories:
    """The model's own RK4 rollout (one step per frame) over ``span`` s in ``n`` intervals
    from a state of ``base``: positions and velocities at the frames."""
    t = torch.linspace(0, span, n + 1, dtype=torch.float64)
    with torch.no_grad():
        x, v = m.rollout(base.pos[:, 1], base.vel[:, 1], base.youngs, t)
    return Trajectories(t, x, v, base.youngs)


def test_on_its_own_rollout_the_driven_halo_converges_at_the_fourth_order(plate):
    m = model(plate, scale=0, shooting=0)  # windows of the whole rollout
    pt = PatchTraining(m, 46)
    assert pt.k == 4
    h, err = [], []
    for n in (4, 8, 16):
        data = own_rollout(m, plate[1], n)
        samples = torch.arange(m.n_training_samples(data))
        with torch.no_grad():
            assert float(m.training_loss(data, samples)) < 1e-28  # its own rollout
            loss = float(pt.training_loss(data, pt.every_patch(samples)))
        h.append(0.01 / n)
        err.append(loss ** 0.5)  # a relative position error
    order = np.polyfit(np.log(h), np.log(err), 1)[0]
    assert 1e-11 < err[-1] < err[1] < err[0] < 1e-5 and 3.7 < order < 4.3  # 3.95


def test_hermite_is_exact_for_cubics():
    t = torch.tensor([0.0, 0.3, 0.5, 1.1], dtype=torch.float64)
    c = torch.randn(4, 1, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def cubic(s, d=0):
        s = torch.as_tensor(s, dtype=torch.float64)
        terms = [(1, s, s**2, s**3), (0, 1, 2 * s, 3 * s**2), (0, 0, 2, 6 * s)][d]
        return sum(ci * ti for ci, ti in zip(c, terms))

    x = torch.stack([cubic(s) for s in t], 1)
    v = torch.stack([cubic(s, 1) for s in t], 1)
    H = Hermite(t, x, v)
    for s in (0.0, 0.1, 0.3, 0.42, 0.77, 1.1):
        for d, y in enumerate(H(s)):
            assert torch.allclose(y, cubic(s, d), rtol=0, atol=1e-12), (s, d)


def test_bad_input_names_the_field(plate):
    for fields, match in ((dict(integrator="dopri5"), "integrator='dopri5'.*adaptive"),
                          (dict(integrator="backward_euler"), "integrator.*implicit"),
                          (dict(loss="rms", shooting=5), "loss='rms'")):
        with pytest.raises(ValueError, match=match):
            PatchTraining(model(plate, scale=0, **fields), 91)
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="buffer"):
            PatchTraining(model(plate, scale=0, shooting=5), 91, buffer=bad)
    mgn = MeshGraphNet(plate[0], MeshGraphNetConfig(hidden=8, layers=1), plate[1])
    with pytest.raises(ValueError, match="buffer"):
        PatchTraining(mgn, 91, buffer=2)


def test_fit_on_patches_writes_meshodenets_checkpoints_and_resumes_exactly(plate, tmp_path):
    mesh, data = plate[0], plate[1].to(dtype=torch.float32)
    cfg = TrainConfig(epochs=2, lr=1e-3, lr_milestones=(), batch_size=4, max_batches=2,
                      val_fraction=0.0, patch_nodes=46)
    fit_resumes_exactly(lambda: MeshODENet(mesh, MeshODENetConfig(
        hidden=8, mlp_hidden_layers=1, shooting=3), data), data, cfg, tmp_path, "meshodenet")
