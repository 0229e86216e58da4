"""MeshGraphNet: the one-step update against an oracle, permutation equivariance, training
noise, overfitting, rollouts (full horizon, clamps, divergence), presets and the registry."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from meshodenet.gnn.mgn import (
    PAPER_LAYERS,
    GraphNetBlock,
    MeshGraphNet,
    MeshGraphNetConfig,
    mgn_presets,
)
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.mesh.graph import rod_hinges
from meshodenet.training.train import TrainConfig, fit, make_optimizer
from tests.conftest import permuted_arrays, rod_arrays, strip_arrays

torch.set_num_threads(1)  # tiny graphs: threads only add overhead

SMALL = MeshGraphNetConfig(hidden=8, layers=2, mlp_hidden_layers=1, noise=0.0)


def build(arrays, config=SMALL, hinges=None, dtype=torch.float64, seed=0):
    torch.manual_seed(seed)
    data = Trajectories.from_arrays(arrays, dtype=dtype)
    model = MeshGraphNet(Mesh.from_arrays(arrays), config, data, hinges=hinges).to(dtype)
    return model, data


def true_accelerations(model, data):
    """``(B, T-1, N, 3)`` normalised ``(x_{k+1} - 2 x_k + x_{k-1}) / dt^2``, ``x_{-1}`` from
    the initial velocity (zero on clamped nodes), computed here independently of the model."""
    dt = float(data.t[1] - data.t[0])
    free = torch.as_tensor(model.mesh.node_type == 0, dtype=data.pos.dtype)[:, None]
    prev = torch.cat([(data.pos[:, 0] - data.vel[:, 0] * free * dt)[:, None],
                      data.pos[:, :-2]], dim=1)
    a = (data.pos[:, 1:] - 2 * data.pos[:, :-1] + prev) / dt ** 2
    std = model.stats.acc.std.to(a.dtype)
    return (a - model.stats.acc.mean.to(a.dtype)) / torch.where(std > 0, std, 1.0)


class Replay:
    """A stand-in for the network: hands out the given outputs in order, one per call."""

    def __init__(self, outputs):
        self.outputs, self.calls = list(outputs), []

    def __call__(self, x, x_prev, ctx, gnn=None):
        self.calls.append((x.detach().clone(), x_prev.detach().clone()))
        return self.outputs.pop(0)


# --- the one-step update --------------------------------------------------------------------

def test_oracle_accelerations_reproduce_the_trajectory(arrays):
    model, data = build(arrays)
    a = true_accelerations(model, data)
    model.forward = Replay([a[:, k].reshape(-1, 3) for k in range(data.n_frames - 1)])
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    torch.testing.assert_close(pos, data.pos, rtol=0, atol=1e-13)
    dt = float(data.t[1] - data.t[0])
    torch.testing.assert_close(vel[:, 1:], (data.pos[:, 1:] - data.pos[:, :-1]) / dt,
                               rtol=0, atol=1e-11)
    # and the training target is that same acceleration: the oracle's loss is zero
    n = model.n_training_samples(data)
    model.forward = Replay([a.reshape(-1, 3)])
    assert float(model.training_loss(data, torch.arange(n), torch.Generator())) < 1e-24
    flat = a.reshape(-1, model.mesh.n_nodes, 3)  # teacher-forced steps, 4 frames per call
    model.forward = Replay([flat[s:s + 4].reshape(-1, 3) for s in range(0, n, 4)])
    torch.testing.assert_close(model.one_step(data, batch_size=4), data.pos, rtol=0, atol=1e-15)


def test_block_sums_the_edge_mlp_output_and_keeps_residuals():
    torch.manual_seed(0)
    block = GraphNetBlock(4, 1, layer_norm=True).double()
    h, e = torch.randn(3, 4, dtype=torch.float64), torch.randn(4, 4, dtype=torch.float64)
    s, r = torch.tensor([0, 1, 2, 0]), torch.tensor([1, 2, 0, 2])
    m = block.edge_mlp(torch.cat([e, h[s], h[r]], -1))
    agg = torch.zeros_like(h).index_add_(0, r, m)
    h2, e2 = block(h, e, s, r)
    torch.testing.assert_close(e2, e + m)
    torch.testing.assert_close(h2, h + block.node_mlp(torch.cat([h, agg], -1)))


def test_layer_norm_on_every_mlp_but_the_decoder():
    model, _ = build(rod_arrays(), MeshGraphNetConfig(hidden=8, layers=3))
    gnn = model.gnn
    mlps = [gnn.node_encoder, gnn.edge_encoder] + \
        [m for blk in gnn.processor for m in (blk.edge_mlp, blk.node_mlp)]
    assert all(isinstance(m[-1], torch.nn.LayerNorm) for m in mlps)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in gnn.decoder)
    assert len(gnn.processor) == 3 and all(isinstance(b, GraphNetBlock) for b in gnn.processor)
    assert sum(isinstance(m, torch.nn.Linear) for m in gnn.decoder) == 3  # 2 hidden layers
    assert len({id(b.edge_mlp[0].weight) for b in gnn.processor}) == 3  # unshared


def test_permutation_equivariance(arrays):
    model, data = build(arrays)
    perm = np.random.default_rng(5).permutation(len(arrays["node_type"]))
    parr, inv = permuted_arrays(arrays, perm)
    hinges = inv[rod_hinges(arrays["edges"], len(perm))] if model.kind == "line" else None
    pmodel, pdata = build(parr, hinges=hinges, seed=1)
    pmodel.load_state_dict(model.state_dict())
    g = torch.Generator().manual_seed(3)  # off the data, so that every feature varies
    x = data.pos[:1, 2] + 1e-3 * torch.randn(data.pos[:1, 2].shape, generator=g,
                                              dtype=torch.float64)
    x_prev = data.pos[:1, 1]
    a = model(x.reshape(-1, 3), x_prev.reshape(-1, 3), model.context(data.youngs[:1]))
    pa = pmodel(x[:, perm].reshape(-1, 3), x_prev[:, perm].reshape(-1, 3),
                pmodel.context(pdata.youngs[:1]))
    torch.testing.assert_close(pa, a[perm], rtol=1e-10, atol=1e-12)
    pos, _ = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    ppos, _ = pmodel.rollout(pdata.pos[:, 0], pdata.vel[:, 0], pdata.youngs, pdata.t)
    torch.testing.assert_close(ppos, pos[:, :, perm], rtol=1e-10, atol=1e-12)


# --- training noise ---------------------------------------------------------------------------

def _noisy_inputs(model, data, samples, seed):
    """The positions the network saw in ``training_loss`` minus the clean ones."""
    model.forward = Replay([torch.zeros(len(samples) * model.mesh.n_nodes, 3,
                                        dtype=data.pos.dtype)])
    model.training_loss(data, samples, torch.Generator().manual_seed(seed))
    x, x_prev = model.forward.calls[0]
    _, clean_prev, clean, _ = model._frames(data, samples)
    del model.forward
    return (x - clean.reshape(-1, 3)).reshape(len(samples), -1, 3), \
        (x_prev - clean_prev.reshape(-1, 3))


def test_noise_per_sample_only_on_free_nodes_and_moving_directions():
    for arrays in (strip_arrays(), rod_arrays()):
        model, data = build(arrays, dataclasses.replace(SMALL, noise=0.5))
        samples = torch.tensor([1, 1, 2, 0])  # a sample drawn twice gets two draws
        torch.manual_seed(123)
        n, dprev = _noisy_inputs(model, data, samples, seed=7)
        torch.manual_seed(456)  # the global RNG plays no part: only the trainer's generator
        n2, _ = _noisy_inputs(model, data, samples, seed=7)
        n3, _ = _noisy_inputs(model, data, samples, seed=8)
        assert torch.equal(n, n2) and not torch.equal(n, n3)
        assert torch.all(dprev == 0)  # x_{k-1} is not perturbed
        clamped = torch.as_tensor(model.mesh.node_type == 1)
        active = model.active.bool()
        assert torch.all(n[:, clamped] == 0) and torch.all(n[..., ~active] == 0)
        free_active = n[:, ~clamped][..., active]
        assert torch.all(free_active != 0)
        assert not torch.allclose(n[0], n[1])
        off = dataclasses.replace(SMALL, noise=0.0)
        model0, _ = build(arrays, off)
        assert torch.all(_noisy_inputs(model0, data, samples, seed=7)[0] == 0)


def test_noise_scale_and_corrected_target():
    model, data = build(strip_arrays(B=2, T=5), dataclasses.replace(SMALL, noise=0.5,
                                                                     noise_gamma=0.3))
    samples = torch.arange(model.n_training_samples(data)).repeat(200)
    n, _ = _noisy_inputs(model, data, samples, seed=0)
    free = torch.as_tensor(model.mesh.node_type == 0)
    active = model.active.bool()
    std = float(n[:, free][..., active].std())
    assert abs(std / (0.5 * float(model.step_rms)) - 1) < 0.02
    # an oracle that knows the noise scores zero only with the documented target correction
    samples = torch.tensor([0, 3, 5, 5])
    n, _ = _noisy_inputs(model, data, samples, seed=1)
    _, x_prev, x, x_next = model._frames(data, samples)
    dt = float(model.dt)
    a = ((x_next + 0.7 * n) - 2 * (x + n) + x_prev) / dt ** 2
    std = torch.where(active, model.stats.acc.std, 1.0)
    model.forward = Replay([((a - model.stats.acc.mean) / std).reshape(-1, 3)])
    loss = model.training_loss(data, samples, torch.Generator().manual_seed(1))
    assert float(loss) < 1e-20


# --- training -------------------------------------------------------------------------------

def test_overfits_one_transition():
    arrays = strip_arrays(B=1, T=2)
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    model = MeshGraphNet(Mesh.from_arrays(arrays), MeshGraphNetConfig(hidden=32, layers=2,
                                                                      noise=0.0), data)
    assert model.n_training_samples(data) == 1
    opt, _ = make_optimizer(model, TrainConfig(lr=1e-3, weight_decay=0.0, lr_milestones=()))
    gen = torch.Generator().manual_seed(0)
    losses = []
    for _ in range(300):
        loss = model.training_loss(data, torch.zeros(1, dtype=torch.long), gen)
        losses.append(float(loss.detach()))
        if losses[-1] < losses[0] * 1e-4:
            break
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert losses[-1] < losses[0] * 1e-4, (losses[0], losses[-1])
    with torch.no_grad():
        pos, _ = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    err = float((pos[:, 1] - data.pos[:, 1]).norm(dim=-1).max())
    assert err < 1e-2 * float((data.pos[:, 1] - data.pos[:, 0]).norm(dim=-1).max())


def test_smoke_model_rolls_out_the_full_horizon(arrays, tmp_path):
    mesh = Mesh.from_arrays(arrays)
    train_cfg, cfg = mgn_presets("smoke", mesh.kind)
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    model = MeshGraphNet(mesh, cfg, data)
    res = fit(model, data.subset(slice(1, None)), data.subset(slice(0, 1)), train_cfg,
              tmp_path, progress=False)
    assert res.epochs_run == train_cfg.epochs and math.isfinite(res.best_val_rmse)
    pos, vel = model.rollout_all(data)
    assert pos.shape == data.pos.shape and torch.isfinite(pos).all() and \
        torch.isfinite(vel).all()
    assert torch.equal(pos[:, 0], data.pos[:, 0]) and model.diverged == {}


def test_clamped_nodes_are_held():
    model, data = build(strip_arrays(), dataclasses.replace(SMALL))
    clamped = torch.as_tensor(model.mesh.node_type == 1)
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0] + 1.0, data.youngs, data.t)
    assert clamped.any() and torch.all(pos[:, :, clamped] == data.pos[:, :1, clamped])
    assert torch.all(vel[:, :, clamped] == 0)


def test_planar_rod_stays_planar():
    model, data = build(rod_arrays(), dtype=torch.float32)
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    assert torch.all(pos[..., 2] == 0) and torch.all(vel[..., 2] == 0)


def test_divergence_names_the_step_and_spares_the_other_trajectories():
    model, data = build(rod_arrays(B=2, T=6))
    outs = [torch.zeros(2 * model.mesh.n_nodes, 3, dtype=torch.float64) for _ in range(5)]
    outs[2][model.mesh.n_nodes + 1, 1] = math.inf  # trajectory 1 blows up at step 3
    model.forward = Replay(outs)
    with pytest.warns(RuntimeWarning, match=r"diverged at step 3 \(t = 0\.3 s\) of 5.*\[1\]"):
        pos, _ = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    assert model.diverged == {1: 3}
    assert torch.isfinite(pos[0]).all() and torch.isfinite(pos[1, :3]).all()
    assert torch.isnan(pos[1, 3:]).all()


def test_rollout_refuses_another_frame_interval():
    model, data = build(rod_arrays())
    with pytest.raises(ValueError, match="trained to step 0.1 s"):
        model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t * 2)
    with pytest.raises(ValueError, match="not uniformly spaced"):
        model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t ** 2)


@pytest.mark.parametrize("field,value", [("layers", -1), ("hidden", 1.5), ("noise", -0.1),
                                         ("noise_gamma", 2.0), ("activation", "gelu")])
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        MeshGraphNetConfig(**{field: value})


# --- presets and registry ---------------------------------------------------------------------

def test_paper_preset_has_the_papers_layers_and_schedule():
    rod_t, rod = mgn_presets("paper", "line")
    plate_t, plate = mgn_presets("paper", "triangle")
    assert (rod.layers, plate.layers) == (15, 30) == (PAPER_LAYERS["line"],
                                                      PAPER_LAYERS["triangle"])
    for c in (rod, plate):
        assert (c.hidden, c.mlp_hidden_layers, c.activation) == (128, 2, "relu")
    assert (rod_t.epochs, rod_t.lr_milestones) == (400, (100, 200, 300))
    assert (plate_t.epochs, plate_t.lr_milestones) == (600, (200, 400))
    for t in (rod_t, plate_t):
        assert (t.lr, t.weight_decay, t.lr_gamma) == (1e-4, 5e-4, 0.1)
    for kind in ("line", "triangle"):
        for preset in ("quick", "smoke"):
            mgn_presets(preset, kind)
    with pytest.raises(ValueError, match="paper, quick, smoke"):
        mgn_presets("fast", "line")


def test_registry_builds_and_reloads_mgn(tmp_path):
    from meshodenet.registry import MODELS, get_model_spec, load_model

    assert "mgn" in MODELS and get_model_spec("mgn").model_cls is MeshGraphNet
    arrays = strip_arrays()
    spec = get_model_spec("mgn")
    train_cfg, cfg = spec.presets("smoke", "triangle")
    data = Trajectories.from_arrays(arrays)
    torch.manual_seed(0)
    model = spec.build(Mesh.from_arrays(arrays), cfg, data)
    fit(model, data, data.subset(slice(0, 0)), train_cfg, tmp_path, progress=False)
    loaded, ck = load_model(tmp_path / "last.pt")
    assert isinstance(loaded, MeshGraphNet) and ck["model_info"]["name"] == "mgn"
    a = model.rollout_all(data)[0]
    torch.testing.assert_close(loaded.rollout_all(data)[0], a, rtol=0, atol=0)


@pytest.mark.parametrize("model_id", ["mgn", "mgn_unrolled"])
def test_cli_train_reload_and_rollout(model_id, tiny_case, tmp_path, capsys):
    from benchmarks.cli import main
    from meshodenet.registry import load_model

    case, root = tiny_case
    run = tmp_path / "run"
    assert main(["train", "--case", case.id, "--model", model_id, "--preset", "smoke",
                 "--out", str(run), "--data-dir", str(root), "--threads", "1",
                 "--no-progress"]) == 0
    capsys.readouterr()
    config = json.loads((run / "config.json").read_text())
    assert config["model"] == model_id and config["model_config"]["layers"] == 2
    metrics = json.loads((run / "test_metrics.json").read_text())
    assert metrics["model"] == model_id and math.isfinite(metrics["rmse_m"])
    model, _ = load_model(run / "best.pt")
    assert model.name == model_id
    if model_id == "mgn_unrolled":  # smoke: one one-step epoch, one of 3-step windows
        assert config["model_config"]["unroll"] == model.config.unroll == 3
        assert len((run / "history.csv").read_text().splitlines()) == 3
    assert main(["rollout", "--run", str(run), "--out", str(tmp_path / "p.npz"),
                 "--data-dir", str(root), "--device", "cpu"]) == 0
