"""The vector field: gradcheck, permutation equivariance, translation invariance, clamps,
batching, normalisers and config validation, on a tiny rod and a tiny clamped strip."""

import numpy as np
import pytest
import torch

from meshodenet.gnn.features import Normalizer
from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.mesh.data import DataError, Mesh, Trajectories
from meshodenet.mesh.graph import rod_hinges
from tests.conftest import permuted_arrays

torch.set_num_threads(1)  # tiny graphs: threads only add overhead

SMALL = MeshODENetConfig(hidden=8, mlp_hidden_layers=1)


def build(arrays, config=SMALL, hinges=None, dtype=torch.float64, seed=0):
    torch.manual_seed(seed)
    mesh = Mesh.from_arrays(arrays)
    data = Trajectories.from_arrays(arrays, dtype=dtype)
    model = MeshODENet(mesh, config, data, hinges=hinges).to(dtype)
    return model, data


def state(data, b=slice(None), k=2):
    x, v = data.pos[b, k], data.vel[b, k]
    g = torch.Generator().manual_seed(3)  # off the data, so that every feature varies
    x = x + 1e-3 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    v = v + 1e-3 * torch.randn(v.shape, generator=g, dtype=v.dtype)
    return torch.stack([x.reshape(-1, 3), v.reshape(-1, 3)])


def test_gradcheck_float64(arrays):
    model, data = build(arrays)
    ctx = model.field_context(data.youngs[:1])
    z = state(data, slice(0, 1)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: model.vector_field(z, ctx), (z,), eps=1e-7,
                                    atol=1e-6, rtol=1e-4)


def test_gradcheck_parameters_float64(arrays):
    model, data = build(arrays)
    ctx = model.field_context(data.youngs[:1])
    z = state(data, slice(0, 1))
    names = ["gnn.processor.0.edge_mlp.0.weight", "gnn.decoder.2.bias"]
    params = dict(model.named_parameters())

    def f(*values):
        return torch.func.functional_call(model, dict(zip(names, values, strict=True)), (z, ctx))

    inputs = tuple(params[n].detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-7, atol=1e-6, rtol=1e-4)


def test_permutation_equivariance(arrays):
    model, data = build(arrays)
    perm = np.random.default_rng(5).permutation(len(arrays["node_type"]))
    parr, inv = permuted_arrays(arrays, perm)
    hinges = None
    if model.kind == "line":
        hinges = inv[rod_hinges(arrays["edges"], len(perm))]
    pmodel, pdata = build(parr, hinges=hinges)
    pmodel.load_state_dict(model.state_dict())
    ctx, pctx = model.field_context(data.youngs[:1]), pmodel.field_context(pdata.youngs[:1])
    dz = model.vector_field(state(data, slice(0, 1)), ctx)
    z_p = state(data, slice(0, 1))[:, perm]
    dz_p = pmodel.vector_field(z_p, pctx)
    torch.testing.assert_close(dz_p, dz[:, perm], rtol=1e-10, atol=1e-12)


def test_translation_leaves_accelerations_unchanged(arrays):
    model, data = build(arrays)
    ctx = model.field_context(data.youngs[:2])
    z = state(data, slice(0, 2))
    shifted = z.clone()
    shifted[0] += torch.tensor([0.3, -1.7, 0.25], dtype=z.dtype)
    torch.testing.assert_close(model.vector_field(shifted, ctx), model.vector_field(z, ctx),
                               rtol=1e-9, atol=1e-10)


def test_clamped_nodes_do_not_move():
    from tests.conftest import strip_arrays

    arrays = strip_arrays()
    model, data = build(arrays)
    clamped = torch.as_tensor(arrays["node_type"] == 1)
    z = state(data, slice(0, 1))
    dz = model.vector_field(z, model.field_context(data.youngs[:1]))
    assert clamped.any() and torch.all(dz[:, clamped] == 0)
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0] + 1.0, data.youngs, data.t)
    assert torch.all(pos[:, :, clamped] == data.pos[:, :1, clamped])
    assert torch.all(vel[:, :, clamped] == 0)


def test_batch_equals_one_by_one(arrays):
    model, data = build(arrays)
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    for b in range(len(data)):
        p, v = model.rollout(data.pos[b:b + 1, 0], data.vel[b:b + 1, 0], data.youngs[b:b + 1],
                             data.t)
        torch.testing.assert_close(p[0], pos[b], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(v[0], vel[b], rtol=1e-12, atol=1e-14)


def test_planar_rod_stays_planar():
    from tests.conftest import rod_arrays

    model, data = build(rod_arrays(), dtype=torch.float32)
    pos, vel = model.rollout(data.pos[:, 0], data.vel[:, 0], data.youngs, data.t)
    assert torch.all(pos[..., 2] == 0) and torch.all(vel[..., 2] == 0)
    assert pos.shape == data.pos.shape and torch.equal(pos[:, 0], data.pos[:, 0])


def test_normalizer_constant_features():
    n_in, n_out = Normalizer(3), Normalizer(3, output=True)
    mean, std = torch.tensor([0.0, 5.0, 1.0]), torch.tensor([0.0, 0.0, 2.0])
    n_in.set_stats(mean, std)
    n_out.set_stats(mean, std)
    torch.testing.assert_close(n_in.std, torch.tensor([1.0, 5.0, 2.0], dtype=torch.float64))
    torch.testing.assert_close(n_out.inverse(torch.ones(3, dtype=torch.float64)),
                               torch.tensor([0.0, 5.0, 3.0], dtype=torch.float64))


def test_stats_come_from_the_given_trajectories_only(arrays):
    model, data = build(arrays)
    other, _ = build({**arrays, "youngs": arrays["youngs"] * 3})
    assert not torch.equal(model.stats.node.mean, other.stats.node.mean)
    fresh = MeshODENet(Mesh.from_arrays(arrays), SMALL).double()
    fresh.load_state_dict(model.state_dict())  # statistics travel with the state_dict
    torch.testing.assert_close(fresh.stats.node.std, model.stats.node.std)


@pytest.mark.parametrize("field,value,match", [
    ("hidden", 0, "hidden"), ("integrator", "rk45", "integrator"),
    ("grad_mode", "reverse", "grad_mode"), ("rtol", 1e-3, "rtol"),
    ("activation", "gelu", "activation"), ("shooting", -1, "shooting"),
])
def test_config_errors_name_the_field(field, value, match):
    with pytest.raises(ValueError, match=match):
        MeshODENetConfig(**{field: value})


def test_wrong_shapes_are_clear(arrays):
    bad = dict(arrays, vel=arrays["vel"][:, :-1])
    with pytest.raises(DataError, match="vel has shape"):
        Trajectories.from_arrays(bad)
    with pytest.raises(DataError, match="pos has shape"):
        Mesh.from_arrays(dict(arrays, pos=arrays["pos"][0]))
    with pytest.raises(DataError, match="missing arrays"):
        Mesh.from_arrays({k: v for k, v in arrays.items() if k != "damping"})


def test_mesh_from_another_case_is_refused():
    from tests.conftest import rod_arrays, strip_arrays

    model, _ = build(rod_arrays())
    with pytest.raises(DataError, match="tiny_strip.*trained on case 'tiny_rod'"):
        model.check_mesh(Mesh.from_arrays(strip_arrays()))
    with pytest.raises(DataError, match="trained on case"):
        model.check_mesh(Mesh.from_arrays(rod_arrays(n_nodes=6)))
