"""A learner evaluated patch by patch (``meshodenet.subdomain.partition``), each patch's inner
nodes stitched into the whole mesh's result: the same numbers as one evaluation on the whole
mesh, to round-off (``tests/test_partition.py``; the halo rule: ``meshodenet.subdomain``).

What a patch evaluation keeps from the whole mesh, never recomputed on the patch:

- MeshGraphNet and MeshODENet: the model's normalisation statistics (``FeatureStats``, MGN's
  ``dt``), read from the model; each node's type (clamped or free), rest position (an
  absolute coordinate where ``rest_position``), mass, load and drag; the trajectory's Young's
  modulus; the rod hinges with the whole rod's orientation (``rod_hinges`` walks a chain
  from its end of lowest index, so a piece of the rod may be walked the other way round,
  flipping the sign of ``sin a``).
- Implicit-Energy: every element's static features (standardised over all the whole mesh's
  elements, sizes relative to its mean edge length and area, edge counts and cotangents
  from all its triangles), rest measures, stiffness factors; the element types of the whole
  mesh (``planar``), ``sigma``, the modulus statistics and ``qrange``, all read from the model.
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from meshodenet.energy.model import ImplicitEnergy
from meshodenet.gnn.features import authors_nodes, graph_context
from meshodenet.gnn.meshodenet import MeshODENet
from meshodenet.gnn.mgn import MeshGraphNet, StepContext
from meshodenet.mesh.graph import GraphTopology
from meshodenet.subdomain.partition import (
    Patch,
    element_patches,
    graph_patches,
    partition_nodes,
    patch_mesh,
)

#: The learners this module evaluates on patches.
LEARNERS = (MeshGraphNet, MeshODENet, ImplicitEnergy)


def _check_learner(model) -> None:
    if not isinstance(model, LEARNERS):
        raise TypeError(f"patch evaluation is defined for {', '.join(c.__name__ for c in LEARNERS)}"
                        f"; got {type(model).__name__}")


def feature_hops(model) -> int:
    """Hops the node features of a GNN reach: 1 on rods (the turning angle at a node needs
    its two neighbours' positions), 0 on triangle meshes and with the authors' layout (whose
    nodes see their velocity only). Edge features are their edge's own."""
    line = model.mesh.kind == "line"
    return int(line and not authors_nodes(getattr(model.config, "layout", "ours")))


def halo_depth(model) -> int:
    """The halo (hops over the mesh's edges) that makes one evaluation of a GNN on a patch
    exact at its inner nodes: its message-passing layers (``config.layers``) plus
    ``feature_hops``. ``ValueError`` for Implicit-Energy, whose patches are element-based."""
    _check_learner(model)
    if isinstance(model, ImplicitEnergy):
        raise ValueError("Implicit-Energy's patches are element-based (element_patches), "
                         "not a halo of hops")
    return int(model.config.layers) + feature_hops(model)


def energy_elements(model: ImplicitEnergy) -> dict:
    """Per element kind of the energy its element nodes ``(m, k)`` (numpy, global ids)."""
    return {k: getattr(model, f"{k}_nodes").cpu().numpy() for k in model.kinds}


def model_patches(model, k: int, depth: int | None = None) -> list[Patch]:
    """The mesh of ``model`` cut into ``k`` parts (``partition_nodes``) and grown into the
    patches its evaluation needs: for a GNN a halo of ``depth`` hops (default
    ``halo_depth(model)``), for Implicit-Energy the elements touching the inner nodes."""
    _check_learner(model)
    mesh = model.mesh
    parts = partition_nodes(mesh.edges, mesh.n_nodes, k)
    if isinstance(model, ImplicitEnergy):
        if depth is not None:
            raise ValueError("Implicit-Energy's patches are element-based; leave depth None")
        return element_patches(energy_elements(model), parts)
    return graph_patches(mesh, parts, halo_depth(model) if depth is None else depth)


def _stitch(patches: list[Patch], n_nodes: int, evaluate, node_dim: int) -> torch.Tensor:
    """The whole mesh's result from ``evaluate(patch)`` (a tensor whose axis ``node_dim``
    runs over the patch's nodes): each patch's inner rows at their global ids."""
    out = None
    for patch in patches:
        y = evaluate(patch)
        if out is None:
            shape = list(y.shape)
            shape[node_dim] = n_nodes
            out = y.new_zeros(shape)
        at = torch.as_tensor(patch.inner_nodes, device=y.device)
        inner = torch.as_tensor(np.flatnonzero(patch.inner), device=y.device)
        out.index_copy_(node_dim, at, y.index_select(node_dim, inner))
    return out


# --- the GNNs -------------------------------------------------------------------------------
def patch_topology(model, patch: Patch) -> GraphTopology:
    """The graph of ``patch`` for GNN ``model``: the sub-mesh's arrays (``patch_mesh``) and the
    whole mesh's rod hinges whose three nodes lie in the patch, in local ids."""
    hinges = model.topology.hinges
    keep = np.isin(hinges, patch.nodes).all(1)
    return GraphTopology(patch_mesh(model.mesh, patch), hinges=patch.local(hinges[keep]))


def _gather(patch: Patch, *xs: torch.Tensor):
    """``(B, N, 3)`` tensors at the patch's nodes, flattened to ``(B n, 3)``."""
    idx = torch.as_tensor(patch.nodes, device=xs[0].device)
    return [x.index_select(1, idx).reshape(-1, 3) for x in xs]


def meshodenet_field(model: MeshODENet, patches: list[Patch], x: torch.Tensor,
                     v: torch.Tensor, youngs: torch.Tensor) -> torch.Tensor:
    """MeshODENet's vector field ``dz/dt = [v, a]`` ``(2, B, N, 3)`` at positions and
    velocities ``x, v (B, N, 3)`` of trajectories of moduli ``youngs (B,)``, evaluated on each
    of ``patches`` and stitched (``model.vector_field`` on the whole mesh's ``(2, B N, 3)``)."""
    B, N, _ = x.shape

    def evaluate(patch):
        topo = patch_topology(model, patch)
        ctx = graph_context(model.stats, topo, youngs, x.dtype)
        z = torch.stack(_gather(patch, x, v))
        return model.vector_field(z, ctx).reshape(2, B, patch.n_nodes, 3)

    return _stitch(patches, N, evaluate, 2)


def _mgn_on_patches(model, patches, x, x_prev, youngs, fn):
    B, N, _ = x.shape

    def evaluate(patch):
        topo = patch_topology(model, patch)
        ctx = graph_context(model.stats, topo, youngs, x.dtype, StepContext, dt=float(model.dt))
        return fn(*_gather(patch, x, x_prev), ctx).reshape(B, patch.n_nodes, 3)

    return _stitch(patches, N, evaluate, 1)


def mgn_acceleration(model: MeshGraphNet, patches: list[Patch], x: torch.Tensor,
                     x_prev: torch.Tensor, youngs: torch.Tensor) -> torch.Tensor:
    """MeshGraphNet's network output, the normalised acceleration ``(B, N, 3)``, from the
    positions ``x, x_prev (B, N, 3)`` of frames ``k`` and ``k - 1`` (``model.forward``), on
    each of ``patches`` and stitched."""
    return _mgn_on_patches(model, patches, x, x_prev, youngs, model.forward)


def mgn_step(model: MeshGraphNet, patches: list[Patch], x: torch.Tensor, x_prev: torch.Tensor,
             youngs: torch.Tensor) -> torch.Tensor:
    """MeshGraphNet's one step, the positions of frame ``k + 1`` ``(B, N, 3)``
    (``model.step``), on each of ``patches`` and stitched."""
    return _mgn_on_patches(model, patches, x, x_prev, youngs, model.step)


# --- Implicit-Energy --------------------------------------------------------------------------
def patch_system(system, patch: Patch):
    """The ``EnergySystem`` ``system`` of the whole mesh restricted to the elements of
    ``patch`` (``element_patches``), their nodes in local ids: the same element data (static
    features, rest measures, stiffness factors), the same terms and statistics."""
    sub = copy.copy(system)
    sub.elems, sub.prior = {}, dict(system.prior)
    for kind, (nodes, static, rest, l0) in system.elems.items():
        i = torch.as_tensor(patch.elements[kind], device=nodes.device)
        local = torch.as_tensor(patch.local(nodes.cpu().numpy()[patch.elements[kind]]),
                                device=nodes.device).reshape(-1, nodes.shape[1])
        sub.elems[kind] = (local, static[i], rest[i], l0[i])
        if kind in sub.prior:
            sub.prior[kind] = system.prior[kind][i]
    return sub


def energy_gradient(model: ImplicitEnergy, patches: list[Patch], x: torch.Tensor,
                    youngs: torch.Tensor) -> torch.Tensor:
    """``dU/dx (B, N, 3)`` of the learned energy at ``x (B, N, 3)`` (float64, m) for moduli
    ``youngs (B,)``, each patch's inner rows from its own elements, stitched
    (``EnergySystem.gradient`` on the whole mesh)."""
    system = model.system(youngs)

    def evaluate(patch):
        idx = torch.as_tensor(patch.nodes, device=x.device)
        return patch_system(system, patch).gradient(x.index_select(1, idx))

    return _stitch(patches, x.shape[1], evaluate, 1)


def _element_hessian_rows(sub, patch: Patch, xp: torch.Tensor):
    """``(rows, cols, values (B, m))`` of the patch system ``sub``'s element Hessians
    (``EnergySystem.element_hessians``) in global coordinates ``3 node + axis``,
    the rows of inner coordinates only (duplicates not summed)."""
    nodes_g = torch.as_tensor(patch.nodes, device=xp.device)
    inner = torch.as_tensor(patch.inner, device=xp.device)
    rows, cols, vals = [], [], []
    for kind, he in sub.element_hessians(xp).items():                  # (B, m, 3k, 3k)
        local = sub.elems[kind][0]
        dof = (3 * nodes_g[local][:, :, None] + torch.arange(3, device=xp.device)).flatten(1)
        own = inner[local].repeat_interleave(3, 1)                       # (m, 3k)
        r, c = torch.broadcast_tensors(dof[:, :, None], dof[:, None, :])
        keep = own[:, :, None].expand_as(r)
        rows.append(r[keep])
        cols.append(c[keep])
        vals.append(he[:, keep])
    return torch.cat(rows), torch.cat(cols), torch.cat(vals, 1)


def energy_hessian_rows(model: ImplicitEnergy, patches: list[Patch], x: torch.Tensor,
                        youngs: torch.Tensor) -> torch.Tensor:
    """``d2U/dx2`` at ``x (B, N, 3)`` (float64) as a coalesced sparse COO tensor
    ``(B, 3N, 3N)`` (coordinates ``3 node + axis``), each patch giving the rows of its inner
    coordinates, every column, from its own elements (``EnergySystem.hessian`` on the whole
    mesh, dense)."""
    system = model.system(youngs)
    B, N, _ = x.shape
    rows, cols, vals = [], [], []
    for patch in patches:
        idx = torch.as_tensor(patch.nodes, device=x.device)
        r, c, v = _element_hessian_rows(patch_system(system, patch), patch,
                                        x.index_select(1, idx))
        rows.append(r)
        cols.append(c)
        vals.append(v)
    r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals, 1)
    b = torch.arange(B, device=x.device).repeat_interleave(len(r))
    index = torch.stack([b, r.repeat(B), c.repeat(B)])
    return torch.sparse_coo_tensor(index, v.reshape(-1), (B, 3 * N, 3 * N),
                                   check_invariants=False).coalesce()  # valid by construction
