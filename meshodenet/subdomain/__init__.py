"""Sub-domains: a mesh cut by METIS into ``k`` parts, each evaluated as a patch (its inner nodes
and a halo) and the inner nodes' results stitched; the same numbers as one evaluation on the
whole mesh, to round-off (float64; float32 within 1e-6 of the largest value).

The halo is the stencil of one evaluation, read from the code:

- MeshGraphNet's one step (``mgn_step``, ``mgn_acceleration``) and MeshODENet's vector field
  (``meshodenet_field``): ``halo_depth(model) = config.layers + feature_hops(model)`` hops
  over the mesh's edges. An edge's features are those of its two nodes; a message-passing
  layer (``InteractionLayer``, ``GraphNetBlock``) updates an edge from its two nodes and a node
  from its incoming edges, so after ``L`` layers a node has seen the nodes within ``L`` hops
  (encoder, decoder and LayerNorm act on one node or edge at a time). The node features reach
  ``feature_hops`` further: 1 on rods (the turning angle at a node, from its two neighbours),
  0 on triangle meshes. One hop less and the inner nodes at the edge of a part are wrong
  (tested). MeshODENet's ``dz/dt = [v, GNN]`` adds nothing: its velocity half is the node's.
- Implicit-Energy's gradient and Hessian rows (``energy_gradient``, ``energy_hessian_rows``):
  the elements (edges, rod hinges, dihedral hinges) that touch an inner node, with all their
  nodes (``element_patches``): the gradient and the Hessian row of a coordinate sum over the
  elements that hold its node.

A patch keeps from the whole mesh everything but the topology, never recomputed on the patch
(``meshodenet.subdomain.evaluate``): node types, per-node arrays, normalisation statistics,
the modulus, element features standardised over the whole mesh, rod hinge orientation.

Training on patches (``PatchTraining``, ``meshodenet.subdomain.training``): every optimizer step
sees patches of a fixed node budget plus their halo, the loss on their inner nodes; exact for
MeshGraphNet, a driven (Dirichlet from the data) halo for Implicit-Energy's one-step solve, a
halo driven by the data's interpolant at every Runge-Kutta stage for MeshODENet's windows
(``meshodenet.subdomain.driven``).

METIS comes from ``pymetis`` (``pip install 'meshbench[subdomain]'``), needed for ``k > 1``.
"""

from meshodenet.subdomain.evaluate import (
    energy_gradient,
    energy_hessian_rows,
    feature_hops,
    halo_depth,
    meshodenet_field,
    mgn_acceleration,
    mgn_step,
    model_patches,
)
from meshodenet.subdomain.partition import (
    Patch,
    driven_patches,
    element_patches,
    graph_patches,
    partition_nodes,
    patch_mesh,
)
from meshodenet.subdomain.training import (
    PatchTraining,
    energy_residual,
    energy_view,
    patch_count,
    training_patches,
)

__all__ = ["PatchTraining", "driven_patches", "energy_residual", "energy_view", "patch_count",
           "training_patches",
           "Patch", "element_patches", "energy_gradient", "energy_hessian_rows", "feature_hops",
           "graph_patches", "halo_depth", "meshodenet_field", "mgn_acceleration", "mgn_step",
           "model_patches", "partition_nodes", "patch_mesh"]
