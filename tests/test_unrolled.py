"""MeshGraphNet trained through its own rollouts (``mgn_unrolled``): one step is MeshGraphNet's
loss exactly, a constant acceleration error weighs the same at every step of the window, the
gradient flows through the window and errors name their field (training from the CLI:
``tests/test_mgn.py``)."""

import dataclasses

import pytest
import torch

from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig
from meshodenet.gnn.unrolled import UnrolledMGN, UnrolledMGNConfig, unrolled_mgn_presets
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.registry import get_model_spec
from tests.conftest import rod_arrays, strip_arrays
from tests.test_mgn import Replay, true_accelerations

torch.set_num_threads(1)

SMALL = dict(hidden=8, layers=2, mlp_hidden_layers=1)


def build(arrays, cls=UnrolledMGN, **cfg):
    data = Trajectories.from_arrays(arrays, dtype=torch.float64)
    config_cls = UnrolledMGNConfig if cls is UnrolledMGN else MeshGraphNetConfig
    torch.manual_seed(0)
    model = cls(Mesh.from_arrays(arrays), config_cls(**{**SMALL, **cfg}), data).double()
    return model, data


@pytest.mark.parametrize("arrays", [rod_arrays(B=2, T=8), strip_arrays(B=2, T=8)])
def test_one_step_window_is_mgns_loss(arrays):
    mgn, data = build(arrays, MeshGraphNet, noise=0.3)
    one, _ = build(arrays, unroll=1, noise=0.3)
    assert one.n_training_samples(data) == mgn.n_training_samples(data) == 14
    s = torch.tensor([0, 3, 6, 7, 13])
    a = mgn.training_loss(data, s, torch.Generator().manual_seed(3))
    b = one.training_loss(data, s, torch.Generator().manual_seed(3))
    torch.testing.assert_close(a, b, rtol=1e-14, atol=0)
    a.backward()
    b.backward()
    for p, q in zip(mgn.parameters(), one.parameters()):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-12, atol=1e-15)


def test_constant_acceleration_error_weighs_the_same_at_every_step():
    K, delta = 4, 0.25
    model, data = build(rod_arrays(B=2, T=9), unroll=K)
    a = true_accelerations(model, data)  # (B, T-1, N, 3), normalised
    n_start = data.n_frames - K
    assert model.n_training_samples(data) == 2 * n_start
    samples = torch.tensor([0, 2, n_start, 2 * n_start - 1])
    traj, k = samples // n_start, samples % n_start
    # a batch of n samples trains on its first ceil(n / K) windows: these four
    samples = torch.cat([samples, torch.arange(2 * n_start).flip(0)[:3 * K - 1]])
    assert -(-len(samples) // K) == 4
    active = model.active.to(a.dtype)
    # the true acceleration of each step of each window, plus delta on the moving components
    model.forward = Replay([(a[traj, k + j] + delta * active).reshape(-1, 3) for j in range(K)])
    loss = model.training_loss(data, samples, torch.Generator())
    assert not model.forward.outputs  # the network was called once per step of the window
    torch.testing.assert_close(loss, delta ** 2 * active.sum(), rtol=1e-9, atol=0)
    # the oracle's loss is zero, and step j starts from the model's own frames
    model.forward = Replay([a[traj, k + j].reshape(-1, 3) for j in range(K)])
    assert float(model.training_loss(data, samples, torch.Generator())) < 1e-20
    x1, x0 = model.forward.calls[1]
    torch.testing.assert_close(x1, data.pos[traj, k + 1].reshape(-1, 3), rtol=0, atol=1e-12)
    torch.testing.assert_close(x0, data.pos[traj, k].reshape(-1, 3), rtol=0, atol=1e-12)


def test_window_starts_from_mgns_noisy_frame():
    """The window's first step sees the positions MeshGraphNet's loss would (same noise draws),
    and its target moves with the noise as MeshGraphNet's does."""
    model, data = build(rod_arrays(B=2, T=6), unroll=2, noise=0.5)
    mgn, _ = build(rod_arrays(B=2, T=6), MeshGraphNet, noise=0.5)
    samples = torch.tensor([0, 3, 4, 7])  # windows (0, 0), (0, 3), (1, 0), (1, 3)
    model.forward = Replay([torch.zeros(4 * model.mesh.n_nodes, 3, dtype=torch.float64)] * 2)
    model.training_loss(data, torch.cat([samples, samples]), torch.Generator().manual_seed(5))
    mgn.forward = Replay([torch.zeros(4 * mgn.mesh.n_nodes, 3, dtype=torch.float64)])
    mgn.training_loss(data, torch.tensor([0, 3, 5, 8]), torch.Generator().manual_seed(5))
    for a, b in zip(model.forward.calls[0], mgn.forward.calls[0]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-15)
    n = model.forward.calls[0][0] - data.pos[[0, 0, 1, 1], [0, 3, 0, 3]].reshape(-1, 3)
    assert n.abs().max() > 0  # there was noise
    # the oracle: step 1 lands on x_{k+1} + (1 - gamma) n, step 2 on the true x_{k+2}
    dt, gamma = float(model.dt), model.config.noise_gamma
    std = torch.where(model.active > 0, model.stats.acc.std, 1.0)
    pos = [data.pos[[0, 0, 1, 1], [0, 3, 0, 3]], data.pos[[0, 0, 1, 1], [1, 4, 1, 4]],
           data.pos[[0, 0, 1, 1], [2, 5, 2, 5]]]
    _, prev, _, _ = mgn._frames(data, torch.tensor([0, 3, 5, 8]))
    d = [(p - pos[0]).reshape(-1, 3) for p in pos] + [(prev - pos[0]).reshape(-1, 3)]
    step1 = d[1] + (1 - gamma) * n - 2 * n + d[3]
    step2 = d[2] - 2 * (d[1] + (1 - gamma) * n) + n
    model.forward = Replay([(s / dt ** 2 - model.stats.acc.mean) / std for s in (step1, step2)])
    loss = model.training_loss(data, torch.cat([samples, samples]),
                               torch.Generator().manual_seed(5))
    assert float(loss) < 1e-18


def test_one_step_epochs_then_windows():
    model, data = build(rod_arrays(B=2, T=9), unroll=4, one_step_epochs=2)
    one, _ = build(rod_arrays(B=2, T=9), unroll=1)
    samples = torch.tensor([1, 5, 9, 14])
    for epoch, window in ((0, 1), (1, 1), (2, 4), (5, 4)):
        model.start_epoch(epoch)
        assert model.window == window
        assert model.n_training_samples(data) == 2 * (9 - window)
    model.start_epoch(1)  # one-step epochs: MeshGraphNet's loss on the whole batch
    torch.testing.assert_close(model.training_loss(data, samples, torch.Generator()),
                               one.training_loss(data, samples, torch.Generator()),
                               rtol=1e-14, atol=0)
    model.start_epoch(2)
    model.forward = Replay([torch.zeros(model.mesh.n_nodes, 3, dtype=torch.float64)] * 4)
    model.training_loss(data, samples, torch.Generator())  # one window of 4 steps
    assert not model.forward.outputs


def test_gradient_flows_through_the_window():
    """The loss of a window of 3 differs from the mean of the one-step losses of its frames
    (the later steps start from the model's frames), and every weight gets a gradient; the
    fast path and the modules' own forward agree on both."""
    losses, grads = {}, {}
    for engine in ("fast", "reference"):
        model, data = build(rod_arrays(B=1, T=6), unroll=3, engine=engine)
        loss = model.training_loss(data, torch.arange(3).repeat(3), torch.Generator())
        loss.backward()
        losses[engine] = loss.detach()
        grads[engine] = [p.grad.clone() for p in model.parameters()]
        assert all(g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
                   for g in grads[engine])
    torch.testing.assert_close(losses["fast"], losses["reference"], rtol=1e-10, atol=0)
    for g, h in zip(grads["fast"], grads["reference"]):
        torch.testing.assert_close(g, h, rtol=1e-8, atol=1e-12)
    one, data = build(rod_arrays(B=1, T=6), unroll=1)
    teacher = one.training_loss(data, torch.tensor([0, 1, 2]), torch.Generator())
    assert abs(float(teacher.detach()) - float(losses["fast"])) > 1e-6 * float(teacher.detach())


@pytest.mark.parametrize("field,value", [("unroll", 0), ("unroll", -1), ("unroll", 1.5),
                                         ("unroll", True), ("unroll", "4"),
                                         ("one_step_epochs", -1), ("one_step_epochs", 2.0)])
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=rf"UnrolledMGNConfig\.{field} must be an int"):
        UnrolledMGNConfig(**{field: value})


def test_window_longer_than_the_data_is_refused():
    model, data = build(rod_arrays(B=1, T=4), unroll=4)
    assert model.n_training_samples(data) == 0
    with pytest.raises(ValueError, match="unroll = 4 needs trajectories of more than 4 frames"):
        model.training_loss(data, torch.arange(1), torch.Generator())


def test_presets_are_mgns_with_the_window():
    from meshodenet.gnn.mgn import mgn_presets

    for preset in ("paper", "quick", "smoke"):
        for kind in ("line", "triangle"):
            t, c = unrolled_mgn_presets(preset, kind)
            t0, c0 = mgn_presets(preset, kind)
            assert t == t0
            assert c0 == MeshGraphNetConfig(**{k: v for k, v in dataclasses.asdict(c).items()
                                               if k not in ("unroll", "one_step_epochs")})
            assert c.unroll == (3 if preset == "smoke" else UnrolledMGNConfig.unroll)
            assert c.one_step_epochs == {"paper": 0, "smoke": 1}.get(
                preset, t.lr_milestones[0] if preset == "quick" else None)
    assert get_model_spec("mgn_unrolled").model_cls is UnrolledMGN
