"""Sub-domains (``meshodenet.subdomain``): a mesh cut by METIS into k parts, each evaluated as a
patch with the halo of its learner's stencil, the inner nodes stitched, equals one evaluation on
the whole mesh: MeshGraphNet's step, MeshODENet's vector field, Implicit-Energy's gradient and
Hessian rows, on ``plate_cantilever@r4`` (2,405 nodes) for k = 1, 2, 8, to round-off in float64
(``RTOL64`` of the largest value) and within ``RTOL32`` in float32.

The partition itself: every node inner in exactly one part, the halo exactly the nodes within
``d`` hops (against scipy's shortest paths), parts balanced to METIS's 3 %, the same cut on
every call. The halo rule is tested both ways: the inner outputs' gradient reaches exactly
``halo_depth`` hops (autograd, at the preset depths), and a halo one hop too shallow breaks
exactness; recomputing Implicit-Energy's element features on the patch breaks it too.

Untrained models of small width (the stencil does not depend on it) with weights away from
their zero-output start. Without ``pymetis`` the tests of k > 1 skip.
"""

from __future__ import annotations

import dataclasses
import math
import sys

import numpy as np
import pytest
import torch
from scipy.sparse.csgraph import dijkstra

from meshodenet.energy.config import EnergyConfig
from meshodenet.energy.core import static_features
from meshodenet.energy.model import ImplicitEnergy
from meshodenet.gnn.meshodenet import MeshODENet, meshodenet_presets
from meshodenet.gnn.mgn import MeshGraphNet, mgn_presets
from meshodenet.mesh.data import Mesh, Trajectories
from meshodenet.subdomain import (
    element_patches,
    energy_gradient,
    energy_hessian_rows,
    graph_patches,
    halo_depth,
    meshodenet_field,
    mgn_acceleration,
    mgn_step,
    model_patches,
    partition_nodes,
)
from meshodenet.subdomain.partition import METIS_OPTIONS, adjacency, patch_mesh

torch.set_num_threads(1)

KS = (1, 2, 8)
RTOL64, RTOL32 = 1e-12, 1e-6
DTYPES = {"float64": (torch.float64, RTOL64), "float32": (torch.float32, RTOL32)}
#: message-passing layers of the presets on this case (triangle meshes): the real halos
MGN_LAYERS = mgn_presets("quick", "triangle")[1].layers  # 30
ODE_LAYERS = meshodenet_presets("quick", "triangle")[1].layers  # 1


def need_metis(k: int) -> None:
    if k > 1:
        pytest.importorskip("pymetis", reason="partitions into k > 1 parts need pymetis (METIS)")


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    """``max |a - b| / max |b|``."""
    return float((a.double() - b.double()).abs().max() / b.double().abs().max())


def case_mesh(case_id: str) -> Mesh:
    from benchmarks.suite.registry import get_case

    case = get_case(case_id)
    edges, cells, node_type = case.mesh()
    return Mesh(edges=np.asarray(edges, np.int64), cells=np.asarray(cells, np.int64),
                node_type=np.asarray(node_type, np.int64), rest_pos=case.rest_positions(),
                case=case.id, **case.loads())


def synthetic(mesh: Mesh, frames: int = 4, dt: float = 3e-3, planar: bool = True):
    """Two seeded trajectories near the rest shape (free nodes move; z stays 0 when
    ``planar``): statistics for the models and the states they are evaluated at."""
    rng = np.random.default_rng(0)
    vel = 0.05 * rng.standard_normal((2, frames, mesh.n_nodes, 3))
    vel *= (mesh.node_type == 0)[None, None, :, None]
    if planar:
        vel[..., 2] = 0.0
    pos = mesh.rest_pos + np.cumsum(vel, 1) * dt
    t = torch.arange(frames, dtype=torch.float64) * dt
    return Trajectories(t, torch.as_tensor(pos), torch.as_tensor(vel),
                        torch.tensor([3.0e6, 6.5e6], dtype=torch.float64))


def lively(model: torch.nn.Module, seed: int = 0, scale: float = 0.3) -> torch.nn.Module:
    """Every parameter moved by seeded noise (a decoder or energy MLP that starts at zero
    output would hide its inputs)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g, dtype=torch.float64).to(p.dtype))
    return model


@pytest.fixture(scope="module")
def plate():
    """``plate_cantilever@r4``, its synthetic trajectories, and the state evaluated."""
    mesh = case_mesh("plate_cantilever@r4")
    data = synthetic(mesh)
    return mesh, data


@pytest.fixture(scope="module")
def parts(plate):
    mesh = plate[0]
    cache = {}

    def get(k):
        need_metis(k)
        if k not in cache:
            cache[k] = partition_nodes(mesh.edges, mesh.n_nodes, k)
        return cache[k]

    return get


def hop_distance(mesh: Mesh, nodes: np.ndarray) -> np.ndarray:
    """Hops from the set ``nodes`` to every node (scipy's shortest paths, inf unreached)."""
    return dijkstra(adjacency(mesh.edges, mesh.n_nodes), unweighted=True, indices=nodes,
                    min_only=True)


# --- the partition ----------------------------------------------------------------------------
@pytest.mark.parametrize("k", KS)
def test_every_node_is_inner_in_exactly_one_balanced_part(plate, parts, k):
    mesh = plate[0]
    p = parts(k)
    patches = graph_patches(mesh, p, 2)
    count = np.zeros(mesh.n_nodes, int)
    for patch in patches:
        np.add.at(count, patch.inner_nodes, 1)
        assert np.all(np.diff(patch.nodes) > 0)
    assert len(patches) == k and np.all(count == 1)
    sizes = np.bincount(p, minlength=k)
    # METIS's imbalance bound (ufactor 30: 3 %) on the nearly equal share
    assert sizes.max() <= math.ceil((1 + METIS_OPTIONS["ufactor"] / 1000) * mesh.n_nodes / k)
    assert np.array_equal(p, partition_nodes(mesh.edges, mesh.n_nodes, k))


@pytest.mark.parametrize("k,depth", [(2, 0), (2, 1), (8, 3), (8, MGN_LAYERS)])
def test_halo_is_the_nodes_within_depth_hops(plate, parts, k, depth):
    mesh = plate[0]
    for patch in graph_patches(mesh, parts(k), depth):
        dist = hop_distance(mesh, patch.inner_nodes)
        assert np.array_equal(patch.nodes, np.flatnonzero(dist <= depth))
        assert np.array_equal(patch.hops, dist[patch.nodes])
        inside = np.isin(mesh.edges, patch.nodes).all(1)
        assert np.array_equal(patch.elements["edge"], np.flatnonzero(inside))
        sub = patch_mesh(mesh, patch)  # the whole mesh's edges, relabelled, in its order
        assert np.array_equal(patch.nodes[sub.edges], mesh.edges[inside])
        assert np.array_equal(sub.rest_pos, mesh.rest_pos[patch.nodes])


@pytest.mark.parametrize("k", (2, 8))
def test_element_patch_holds_the_elements_touching_its_inner_nodes(plate, parts, k):
    mesh = plate[0]
    p = parts(k)
    cells = {"edge": mesh.edges, "cell": mesh.cells}
    for patch in element_patches(cells, p):
        for kind, e in cells.items():
            touching = (p[e] == patch.part).any(1)
            assert np.array_equal(patch.elements[kind], np.flatnonzero(touching))
        want = np.union1d(patch.inner_nodes, np.concatenate(
            [e[(p[e] == patch.part).any(1)].ravel() for e in cells.values()]))
        assert np.array_equal(patch.nodes, want)


def test_one_part_needs_no_metis_and_more_name_the_package(plate, monkeypatch):
    mesh = plate[0]
    monkeypatch.setitem(sys.modules, "pymetis", None)  # as if it were not installed
    assert np.array_equal(partition_nodes(mesh.edges, mesh.n_nodes, 1), np.zeros(mesh.n_nodes))
    with pytest.raises(ImportError, match="pymetis"):
        partition_nodes(mesh.edges, mesh.n_nodes, 2)
    for bad in (0, mesh.n_nodes + 1, 2.0, True):
        with pytest.raises(ValueError, match="k must be an integer"):
            partition_nodes(mesh.edges, mesh.n_nodes, bad)


# --- the GNNs ---------------------------------------------------------------------------------
def gnn(plate, cls, dtype, **changes):
    """An untrained ``cls`` (MeshGraphNet or MeshODENet) of the ``quick`` preset on triangle
    meshes (its depth, width, rest positions as features) with ``changes``, the statistics of
    the synthetic trajectories, in ``dtype``."""
    mesh, data = plate
    presets = mgn_presets if cls is MeshGraphNet else meshodenet_presets
    cfg = dataclasses.replace(presets("quick", mesh.kind)[1], **changes)
    torch.manual_seed(0)
    return lively(cls(mesh, cfg, data).double()).to(dtype)


def states(plate, dtype):
    """``x, x_prev, v (B, N, 3)`` of the last two synthetic frames, ``youngs (B,)``."""
    data = plate[1]
    cast = lambda a: a.to(dtype)
    return cast(data.pos[:, -1]), cast(data.pos[:, -2]), cast(data.vel[:, -1]), cast(data.youngs)


def whole_mgn(model, x, x_prev, youngs):
    B, N, _ = x.shape
    ctx = model.context(youngs, x.dtype)
    args = (x.reshape(-1, 3), x_prev.reshape(-1, 3), ctx)
    return model(*args).reshape(B, N, 3), model.step(*args).reshape(B, N, 3)


def whole_field(model, x, v, youngs):
    B, N, _ = x.shape
    ctx = model.field_context(youngs, x.dtype)
    z = torch.stack([x.reshape(-1, 3), v.reshape(-1, 3)])
    return model.vector_field(z, ctx).reshape(2, B, N, 3)


@pytest.fixture(scope="module")
def mgn_models(plate):
    """MeshGraphNet at the preset's depth, per dtype."""
    return {name: gnn(plate, MeshGraphNet, dtype) for name, (dtype, _) in DTYPES.items()}


@pytest.mark.parametrize("dtype", sorted(DTYPES))
@pytest.mark.parametrize("k", KS)
def test_mgn_step_on_parts_equals_the_whole(plate, parts, mgn_models, k, dtype):
    model, rtol = mgn_models[dtype], DTYPES[dtype][1]
    patches = model_patches(model, k)
    assert halo_depth(model) == MGN_LAYERS
    assert max(int(p.hops.max()) for p in patches) == (MGN_LAYERS if k > 1 else 0)
    x, x_prev, _, youngs = states(plate, DTYPES[dtype][0])
    with torch.no_grad():
        acc, step = whole_mgn(model, x, x_prev, youngs)
        assert rel(mgn_acceleration(model, patches, x, x_prev, youngs), acc) <= rtol
        assert rel(mgn_step(model, patches, x, x_prev, youngs), step) <= rtol


@pytest.mark.parametrize("layers", sorted({ODE_LAYERS, 3}))
@pytest.mark.parametrize("dtype", sorted(DTYPES))
@pytest.mark.parametrize("k", KS)
def test_meshodenet_field_on_parts_equals_the_whole(plate, parts, k, dtype, layers):
    torch_dtype, rtol = DTYPES[dtype]
    model = gnn(plate, MeshODENet, torch_dtype, layers=layers)
    assert halo_depth(model) == layers == model.config.layers
    x, _, v, youngs = states(plate, torch_dtype)
    with torch.no_grad():
        whole = whole_field(model, x, v, youngs)
        field = meshodenet_field(model, model_patches(model, k), x, v, youngs)
    assert rel(field[1], whole[1]) <= rtol  # the acceleration
    assert torch.equal(field[0], whole[0])  # the velocity of free nodes


@pytest.mark.parametrize("k", (2, 8))
@pytest.mark.parametrize("cls,layers", [(MeshGraphNet, 3), (MeshODENet, ODE_LAYERS),
                                        (MeshODENet, 3)])
def test_a_halo_one_hop_too_shallow_is_not_exact(plate, parts, cls, layers, k):
    model = gnn(plate, cls, torch.float64, layers=layers, hidden=8)
    x, x_prev, v, youngs = states(plate, torch.float64)
    shallow = model_patches(model, k, halo_depth(model) - 1)
    with torch.no_grad():
        if cls is MeshGraphNet:
            err = rel(mgn_acceleration(model, shallow, x, x_prev, youngs),
                      whole_mgn(model, x, x_prev, youngs)[0])
        else:
            err = rel(meshodenet_field(model, shallow, x, v, youngs)[1],
                      whole_field(model, x, v, youngs)[1])
    assert err > 1e-4


@pytest.mark.parametrize("cls,layers", [(MeshGraphNet, MGN_LAYERS), (MeshODENet, ODE_LAYERS)])
def test_the_stencil_is_exactly_the_halo_depth(plate, parts, cls, layers):
    """The gradient of a part's inner outputs w.r.t. the positions is nonzero at every node
    ``halo_depth`` hops away and exactly zero beyond (float64; MGN's influence falls about
    20-fold a hop, so one hop short its error, ~1e-30 here, hides under round-off)."""
    mesh = plate[0]
    model = gnn(plate, cls, torch.float64, layers=layers)
    depth = halo_depth(model)
    x, x_prev, v, youngs = states(plate, torch.float64)
    x = x.clone().requires_grad_(True)
    inner = np.flatnonzero(parts(8) == 0)
    out = whole_mgn(model, x, x_prev, youngs)[0] if cls is MeshGraphNet \
        else whole_field(model, x, v, youngs)[1]
    out[:, inner].square().sum().backward()
    reached = x.grad.abs().amax((0, 2)).numpy() > 0
    dist = hop_distance(mesh, inner)
    assert reached[dist == depth].all() and not reached[dist > depth].any()


def test_rods_add_the_turning_angle_hop(parts):
    """On a rod the node features see the neighbours (turning angle): MeshODENet's halo is
    ``layers + 1``, exact there, not with ``layers``."""
    need_metis(2)
    mesh = case_mesh("rod_falling")
    data = synthetic(mesh)
    model = gnn((mesh, data), MeshODENet, torch.float64, layers=2, rest_position=False)
    assert halo_depth(model) == 3
    x, _, v, youngs = states((mesh, data), torch.float64)
    with torch.no_grad():
        whole = whole_field(model, x, v, youngs)[1]
        exact = meshodenet_field(model, model_patches(model, 2), x, v, youngs)[1]
        short = meshodenet_field(model, model_patches(model, 2, 2), x, v, youngs)[1]
    assert rel(exact, whole) <= RTOL64 and rel(short, whole) > 1e-4


# --- Implicit-Energy --------------------------------------------------------------------------
#: ``sigma`` of the test energies: ``qhat`` of order 1 at the synthetic states
SIGMA = {"edge": 3e-2, "dihedral": 1e-2}


def energy(mesh: Mesh, prior: str = "features", clamp: bool = True) -> ImplicitEnergy:
    """An untrained Implicit-Energy on ``mesh`` (float64) with its statistics set by hand
    (``sigma`` of the stretches and bending measures seen here), seeded weights, random
    per-element stiffness factors and a ``qrange`` that clamps some elements."""
    torch.manual_seed(0)
    cfg = EnergyConfig(hidden=8, layers=2, stiffness_prior=prior, clamp_q=clamp)
    model = lively(ImplicitEnergy(mesh, cfg), scale=0.5)
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        model.ystats.copy_(torch.tensor([5e6, math.log(5e6), 0.4, 1.0]))
        for k in model.kinds:
            getattr(model, f"{k}_sigma").fill_(SIGMA[k])
            if prior == "features":
                p = getattr(model, f"{k}_prior")
                p.copy_(torch.exp(0.5 * torch.randn(p.shape, generator=g, dtype=p.dtype)))
            if clamp:
                getattr(model, f"{k}_qrange").copy_(torch.tensor([-2.0, 2.0]))
    return model


@pytest.fixture(scope="module")
def plate_energy(plate):
    return energy(plate[0])


@pytest.fixture(scope="module")
def plate_energy_uniform(plate):
    """Without stiffness factors or clamps: an energy built on a patch's own mesh differs
    from it by the element features alone."""
    return energy(plate[0], prior="uniform", clamp=False)


def test_energy_depends_on_every_element_datum(plate, plate_energy):
    """The test model's gradient changes with the static features and the stiffness factors
    (so the equality below checks that patches keep them), and some elements are clamped."""
    model, (x, *_, youngs) = plate_energy, states(plate, torch.float64)
    sys_ = model.system(youngs)
    g = sys_.gradient(x)
    nodes, static, rest, l0 = sys_.elems["edge"]
    sys_.elems = {"edge": (nodes, static.flip(0), rest, l0)}
    assert rel(sys_.gradient(x), g) > 1e-3
    q = sys_.geometry(x, second=False)["edge"][0] / SIGMA["edge"]
    assert 0.01 < float((q.abs() > 2).double().mean()) < 0.9


@pytest.fixture(scope="module")
def plate_hessian(plate, plate_energy):
    """The whole mesh's dense Hessian of the first trajectory: 7,215^2 float64, 416 MB."""
    x, _, _, youngs = states(plate, torch.float64)
    return plate_energy.system(youngs[:1]).hessian(x[:1])


def assert_same_hessian(H: torch.Tensor, dense: torch.Tensor) -> None:
    """The sparse ``H`` equals ``dense`` where it has entries, and ``dense`` has none elsewhere
    (without a second dense copy)."""
    i = H.indices()
    at = dense[i[0], i[1], i[2]]
    scale = max(float(dense.max()), -float(dense.min()))
    assert float((H.values() - at).abs().max()) <= RTOL64 * scale
    total = float(torch.linalg.vector_norm(dense, 1))
    assert total - float(at.abs().sum()) <= RTOL64 * total


@pytest.mark.parametrize("k", KS)
def test_energy_gradient_and_hessian_rows_on_parts_equal_the_whole(plate, plate_energy,
                                                                   plate_hessian, k):
    need_metis(k)
    model = plate_energy
    x, _, _, youngs = states(plate, torch.float64)
    patches = model_patches(model, k)
    assert rel(energy_gradient(model, patches, x, youngs),
               model.system(youngs).gradient(x)) <= RTOL64
    assert_same_hessian(energy_hessian_rows(model, patches, x[:1], youngs[:1]), plate_hessian)


@pytest.mark.parametrize("k", KS)
def test_bending_energy_on_parts_equals_the_whole(k):
    """``plate_hanging`` (r = 1, 182 nodes) moves in 3-D: edges and dihedral hinges, whose
    four nodes reach two hops across their edge."""
    need_metis(k)
    mesh = case_mesh("plate_hanging")
    model = energy(mesh)
    assert model.kinds == ["edge", "dihedral"]
    data = synthetic(mesh, planar=False)
    x, youngs = data.pos[:, -1], data.youngs
    patches = model_patches(model, k)
    assert max(int(hop_distance(mesh, p.inner_nodes)[p.nodes].max()) for p in patches) == 2 \
        or k == 1
    whole = model.system(youngs)
    assert rel(energy_gradient(model, patches, x, youngs), whole.gradient(x)) <= RTOL64
    assert_same_hessian(energy_hessian_rows(model, patches, x, youngs), whole.hessian(x))


@pytest.mark.parametrize("k", (2, 8))
def test_element_features_recomputed_on_the_patch_are_not_exact(plate, parts,
                                                                plate_energy_uniform, k):
    """An energy built on the patch's own mesh (features standardised over its elements,
    sizes against its mean, boundary edges with one triangle) differs at the inner nodes:
    the patch must keep the whole mesh's."""
    mesh = plate[0]
    model = plate_energy_uniform
    x, _, _, youngs = states(plate, torch.float64)
    patch = graph_patches(mesh, parts(k), 1)[0]  # 1 hop: every edge touching an inner node
    own = patch_mesh(mesh, patch)
    naive = ImplicitEnergy(own, model.config)
    naive.load_state_dict({n: t for n, t in model.state_dict().items()
                           if n not in model.mesh_state_keys()}, strict=False)
    assert not np.allclose(static_features(own)["edge"][1],
                           static_features(mesh)["edge"][1][patch.elements["edge"]])
    xp = x[:, patch.nodes]
    inner = torch.as_tensor(patch.inner)
    got = naive.system(youngs).gradient(xp)[:, inner]
    ours = energy_gradient(model, model_patches(model, k)[:1], x, youngs)  # part 0 only
    want = model.system(youngs).gradient(x)[:, patch.inner_nodes]
    assert rel(ours[:, patch.inner_nodes], want) <= RTOL64
    assert rel(got, want) > 1e-3
