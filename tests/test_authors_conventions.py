"""MeshODENet's switches to the authors' code's conventions (the A/B against their code, docs/AB.md):
the decoder's output de-normalised with the velocity's scale (``acc_scale="velocity"``), the
root-mean-square loss (``loss="rms"``), their feature layout (``layout="authors"``) and their
normalisation (``normalizer="authors"``; the fast path against the reference with them:
tests/test_fast.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.mesh.data import Mesh, Trajectories
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


def in_plane_strip(**kw):
    """``strip_arrays`` moving in its own plane: its sag along y instead of z (z exactly 0),
    like ``plate_cantilever``."""
    a = strip_arrays(**kw)
    for key in ("pos", "vel"):
        a[key][..., 1] += a[key][..., 2]
        a[key][..., 2] = 0.0
    a["force"] = a["force"][:, [0, 2, 1]]
    return a


def test_authors_normalizer_statistics_and_the_live_out_of_plane_direction():
    """``normalizer="authors"``: the unbiased std of every feature clamped at 1e-8 in the
    authors' units (velocities per their time unit of 0.1 per frame, so 1e-8 * 0.1 / dt in
    m/s), the one-hot as it is, the output scale the clamped velocity std per 10 intervals;
    on an in-plane strip its rollout leaves the plane by a hair (the decoder's z output
    times that scale) while ``ours`` stays exactly planar."""
    arrays = in_plane_strip(B=2, T=6)
    mesh, tr = Mesh.from_arrays(arrays), Trajectories.from_arrays(arrays, torch.float64)
    cfg = dict(hidden=8, layout="authors", acc_scale="velocity", loss="rms")
    torch.manual_seed(0)
    model = MeshODENet(mesh, MeshODENetConfig(**cfg, normalizer="authors"), tr).double()
    dt = float(np.mean(np.diff(arrays["t"])))
    s = model.stats
    v = torch.as_tensor(arrays["vel"]).reshape(-1, 3)
    want_v = v.std(0, correction=1).clamp_min(1e-8 * 0.1 / dt)
    torch.testing.assert_close(s.node.std[3:], want_v, rtol=1e-10, atol=0)
    assert s.node.std[5] == pytest.approx(1e-8 * 0.1 / dt, rel=1e-12)  # z: the clamp
    assert s.node.mean[1:3].tolist() == [0.0, 0.0] and s.node.std[1:3].tolist() == [1.0, 1.0]
    y = torch.as_tensor(arrays["youngs"]).repeat_interleave(mesh.n_nodes * 6)  # every frame
    assert float(s.node.std[0]) == pytest.approx(float(y.std(correction=1)), rel=1e-10)
    assert float(s.edge.std[3]) == 1e-8 and float(s.edge.std[7]) == 1e-8  # rest and current z
    torch.testing.assert_close(s.acc.std, want_v / (10 * dt), rtol=1e-12, atol=0)
    assert torch.equal(s.acc.mean, torch.zeros(3, dtype=torch.float64))
    ours = MeshODENet(mesh, MeshODENetConfig(**cfg), tr).double()
    ours.gnn.load_state_dict(model.gnn.state_dict())
    x0, v0, t = tr.pos[:, 0], tr.vel[:, 0], tr.t - tr.t[0]
    with torch.no_grad():
        xa, _ = model.rollout(x0, v0, tr.youngs, t)
        xo, _ = ours.rollout(x0, v0, tr.youngs, t)
    assert not xo[..., 2].any()
    z = xa[..., 2].abs().max()
    assert 0 < z < 1e-8  # out of the plane, by far less than the loss can see
    torch.testing.assert_close(xa[..., :2], xo[..., :2], rtol=0, atol=1e-3)


@pytest.mark.parametrize("fields, name", [
    (dict(acc_scale="velocities"), "acc_scale"), (dict(loss="l1"), "loss"),
    (dict(loss="rms", frame_weight=0.5), "frame_weight"), (dict(layout="theirs"), "layout"),
    (dict(layout="authors", mlp_hidden_layers=0), "mlp_hidden_layers"),
    (dict(normalizer="theirs"), "normalizer"), (dict(normalizer="authors"), "normalizer")])
def test_bad_settings_name_the_field(fields, name):
    with pytest.raises(ValueError, match=f"MeshODENetConfig.{name}"):
        MeshODENetConfig(**fields)


def test_paper_preset_takes_the_authors_conventions_on_triangles_only():
    """The A/B against their code: the plate's ``paper`` preset is the authors' code's conventions; the
    rod's keeps ours (its committed runs)."""
    from meshodenet.gnn.meshodenet import meshodenet_presets

    tri = meshodenet_presets("paper", "triangle")[1]
    assert (tri.acc_scale, tri.loss, tri.layout, tri.normalizer) == ("velocity", "rms",
                                                                      "authors", "authors")
    assert meshodenet_presets("paper", "line")[1] == MeshODENetConfig()
    for kind in ("line", "triangle"):  # quick keeps our conventions
        q = meshodenet_presets("quick", kind)[1]
        assert (q.acc_scale, q.loss, q.layout, q.normalizer) == ("acceleration", "mse", "ours",
                                                                  "ours")
