"""MeshODENet's switches to the authors' code's conventions (issue 37's A/B, docs/AB.md):
the decoder's output de-normalised with the velocity's scale (``acc_scale="velocity"``), the
root-mean-square loss (``loss="rms"``) and their feature layout (``layout="authors"``; the fast
path against the reference with it: tests/test_fast.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshodenet.data import Mesh, Trajectories
from meshodenet.models.meshodenet import MeshODENet, MeshODENetConfig
from tests.conftest import rod_arrays, strip_arrays


@pytest.mark.parametrize("arrays", [rod_arrays(B=3, T=7), strip_arrays(B=2, T=6)],
                         ids=["rod", "strip"])
def test_velocity_scale_is_the_velocity_std_per_ten_intervals(arrays):
    """Zero mean; std = the population std of every node's stored velocity over every frame of
    the training trajectories, per component, divided by 10 sampling intervals; a component
    that never moves (the planar rod's z) decodes to exactly 0."""
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
    model = MeshODENet(mesh, MeshODENetConfig(hidden=8, acc_scale="velocity"), tr).double()
    dt = float(np.mean(np.diff(arrays["t"])))
    want = arrays["vel"].reshape(-1, 3).std(0) / (10 * dt)
    assert torch.equal(model.stats.acc.mean, torch.zeros(3, dtype=torch.float64))
    np.testing.assert_allclose(model.stats.acc.std.numpy(), want, rtol=1e-10, atol=0)
    if not arrays["vel"][..., 2].any():
        assert model.stats.acc.std[2] == 0
        B = len(arrays["youngs"])
        x0, v0 = tr.pos[:, 0], tr.vel[:, 0]
        with torch.no_grad():
            x, _ = model.rollout(x0, v0, tr.youngs, tr.t[:3] - tr.t[0])
        assert x.shape == (B, 3, mesh.n_nodes, 3) and not x[..., 2].any()
    default = MeshODENet(mesh, MeshODENetConfig(hidden=8), tr)
    assert not torch.allclose(default.stats.acc.std, model.stats.acc.std)


def test_rms_loss_is_the_mean_over_windows_of_each_windows_root():
    """With the rollout replaced by standing still, each trajectory's loss relative to
    standing still is known: ``rms`` averages the roots of the per-window values, ``mse``
    the values themselves (both 1 on average over the split's scale)."""
    arrays = rod_arrays(B=3, T=6)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
    models = {k: MeshODENet(mesh, MeshODENetConfig(hidden=8, loss=k), tr).double()
              for k in ("mse", "rms")}
    pos = arrays["pos"]
    per_traj = ((pos[:, 1:] - pos[:, :1]) ** 2).sum(-1).mean(axis=(1, 2))
    scale = per_traj.mean()  # whole rollouts: the no-motion loss of the split
    want = {"mse": (per_traj / scale).mean(), "rms": np.sqrt(per_traj / scale).mean()}
    assert want["rms"] < 1 - 1e-3  # the trajectories differ: the two really differ
    for key, model in models.items():
        model.rollout = lambda x0, v0, youngs, t: (x0[:, None].expand(-1, len(t), -1, -1),
                                                   None)
        got = float(model.training_loss(tr, torch.arange(3)))
        assert got == pytest.approx(want[key], rel=1e-12), key


def test_rms_loss_of_one_trajectory_is_the_root_of_the_mse_one_and_trains():
    """One whole trajectory: rms = sqrt(mse), and its gradient is mse's over 2 sqrt(mse)."""
    arrays = rod_arrays(B=2, T=6)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
    torch.manual_seed(0)
    a = MeshODENet(mesh, MeshODENetConfig(hidden=8, loss="rms"), tr).double()
    b = MeshODENet(mesh, MeshODENetConfig(hidden=8), tr).double()
    b.load_state_dict(a.state_dict())
    la, lb = a.training_loss(tr, torch.tensor([1])), b.training_loss(tr, torch.tensor([1]))
    assert la.item() == pytest.approx(lb.item() ** 0.5, rel=1e-12)
    la.backward()
    lb.backward()
    ga = torch.cat([p.grad.flatten() for p in a.parameters()])
    gb = torch.cat([p.grad.flatten() for p in b.parameters()])
    assert ga.abs().max() > 0
    torch.testing.assert_close(ga, gb / (2 * lb.item() ** 0.5), rtol=1e-10, atol=1e-14)


def test_authors_layout_features():
    """Velocity alone into the node encoder, the static node features beside the latent into
    the decoder, ``[l, x_j - x_i]`` on the edges (rest and current)."""
    arrays = strip_arrays(B=2, T=5)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
    model = MeshODENet(mesh, MeshODENetConfig(hidden=8, layout="authors"), tr).double()
    n_static = 3  # modulus, node type one-hot
    assert model.gnn.node_encoder[0].in_features == 3
    assert model.gnn.decoder[0].in_features == 8 + n_static
    ctx = model.field_context(tr.youngs)
    x, v = tr.pos[:, 3].reshape(-1, 3), tr.vel[:, 3].reshape(-1, 3)
    node_in, edge_in = ctx.inputs(x, v)
    s = model.stats
    torch.testing.assert_close(node_in, (v - s.node.mean[n_static:]) / s.node.std[n_static:])
    torch.testing.assert_close(ctx.decoder_static, ctx.node_static)
    b = ctx.batch
    vec = x[b.receivers] - x[b.senders]
    raw = torch.cat([b.rest_vec.norm(dim=-1, keepdim=True), b.rest_vec,
                     vec.norm(dim=-1, keepdim=True), vec], -1)
    torch.testing.assert_close(edge_in, (raw - s.edge.mean) / s.edge.std)
    ours = MeshODENet(mesh, MeshODENetConfig(hidden=8), tr).double()
    assert ours.field_context(tr.youngs).decoder_static is None
    assert ours.gnn.node_encoder[0].in_features == n_static + 6
    # the two halves (the A/B's bisection)
    nodes = MeshODENet(mesh, MeshODENetConfig(hidden=8, layout="authors_nodes"), tr).double()
    edges = MeshODENet(mesh, MeshODENetConfig(hidden=8, layout="authors_edges"), tr).double()
    assert nodes.gnn.node_encoder[0].in_features == 3
    assert edges.gnn.node_encoder[0].in_features == n_static + 6
    assert edges.field_context(tr.youngs).decoder_static is None
    torch.testing.assert_close(edges.field_context(tr.youngs).inputs(x, v)[1], edge_in)
    n_edge = nodes.field_context(tr.youngs).inputs(x, v)[1]
    torch.testing.assert_close(n_edge, ours.field_context(tr.youngs).inputs(x, v)[1])


@pytest.mark.parametrize("fields, name", [
    (dict(acc_scale="velocities"), "acc_scale"), (dict(loss="l1"), "loss"),
    (dict(loss="rms", frame_weight=0.5), "frame_weight"), (dict(layout="theirs"), "layout"),
    (dict(layout="authors", mlp_hidden_layers=0), "mlp_hidden_layers")])
def test_bad_settings_name_the_field(fields, name):
    with pytest.raises(ValueError, match=f"MeshODENetConfig.{name}"):
        MeshODENetConfig(**fields)


def test_paper_preset_takes_the_authors_conventions_on_triangles_only():
    """Issue 37's A/B: the plate's ``paper`` preset is the authors' code's conventions; the
    rod's keeps ours (its committed runs)."""
    from meshodenet.models.meshodenet import meshodenet_presets

    tri = meshodenet_presets("paper", "triangle")[1]
    assert (tri.acc_scale, tri.loss, tri.layout) == ("velocity", "rms", "authors")
    assert meshodenet_presets("paper", "line")[1] == MeshODENetConfig()
    for kind in ("line", "triangle"):  # quick keeps our conventions
        q = meshodenet_presets("quick", kind)[1]
        assert (q.acc_scale, q.loss, q.layout) == ("acceleration", "mse", "ours")
