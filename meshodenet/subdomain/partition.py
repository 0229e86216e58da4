"""A mesh's nodes cut into ``k`` parts by METIS, and each part grown into a patch: its inner
nodes and a halo, either every node within ``d`` hops over the mesh's edges (``graph_patches``:
the stencil of a message-passing network) or every node of the elements that touch an inner
node (``element_patches``: the stencil of an element energy's gradient and Hessian rows).

A patch keeps the whole mesh's numbering: ``Patch.nodes`` are global node ids in increasing
order (local ``i`` is global ``nodes[i]``), its edges, cells or elements are indices into the
whole mesh's arrays, kept in the whole mesh's order. Relabelled that way, a patch's edges run
in the same order as the whole mesh's, so the sums over a node's edges add in the same order.

METIS comes from ``pymetis`` (the optional dependency ``meshbench[subdomain]``), imported only
when ``k > 1``; one part needs no METIS.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from meshodenet.mesh.data import Mesh

#: METIS options of every partition: k-way, contiguous parts, imbalance at most 3 %
#: (``ufactor`` 30, METIS's k-way default), a fixed seed, so that a mesh is cut the same way
#: on every run.
METIS_OPTIONS = {"seed": 0, "ufactor": 30, "contig": 1}


def _pymetis():
    try:
        import pymetis
    except ImportError:
        raise ImportError("partitioning a mesh into k > 1 parts needs the package 'pymetis' "
                          "(METIS): pip install pymetis, or pip install "
                          "'meshbench[subdomain]'") from None
    return pymetis


def adjacency(edges: np.ndarray, n_nodes: int):
    """The node graph of undirected ``edges (E, 2)``: a symmetric scipy CSR matrix
    ``(n_nodes, n_nodes)`` of ones, without self-loops or repeated entries."""
    from scipy.sparse import coo_matrix

    e = np.asarray(edges, np.int64).reshape(-1, 2)
    e = e[e[:, 0] != e[:, 1]]
    i, j = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
    a = coo_matrix((np.ones(len(i), np.int8), (i, j)), shape=(n_nodes, n_nodes)).tocsr()
    a.data[:] = 1
    a.sort_indices()
    return a


def partition_nodes(edges: np.ndarray, n_nodes: int, k: int) -> np.ndarray:
    """The part ``(n_nodes,)`` (in ``[0, k)``) of every node of the graph of ``edges (E, 2)``,
    cut by METIS (``METIS_OPTIONS``) into ``k`` parts of nearly equal size with few edges
    between them; deterministic. ``k = 1`` puts every node in part 0 without METIS."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k <= n_nodes:
        raise ValueError(f"k must be an integer in [1, {n_nodes}] (the number of nodes), "
                         f"got {k!r}")
    if k == 1:
        return np.zeros(n_nodes, np.int64)
    pymetis = _pymetis()
    a = adjacency(edges, n_nodes)
    csr = getattr(pymetis, "CSRAdjacency", None)  # (pymetis >= 2025; before: xadj, adjncy)
    graph = dict(adjacency=csr(a.indptr, a.indices)) if csr else dict(xadj=a.indptr,
                                                                      adjncy=a.indices)
    _, parts = pymetis.part_graph(int(k), **graph, recursive=False,
                                  options=pymetis.Options(**METIS_OPTIONS))
    parts = np.asarray(parts, np.int64)
    if len(np.unique(parts)) != k:  # METIS may leave a part empty on a tiny graph
        raise ValueError(f"METIS left {k - len(np.unique(parts))} of {k} parts empty on a graph "
                         f"of {n_nodes} nodes; choose a smaller k")
    return parts


@dataclass(frozen=True)
class Patch:
    """One part of a mesh with its halo, in the whole mesh's numbering.

    - ``part``: the part's index; ``nodes (n,)`` global node ids, increasing (local ``i`` is
      global ``nodes[i]``); ``inner (n,)`` bool, the part's own nodes (each node of the mesh is
      inner in exactly one patch); ``hops (n,)`` each node's distance in edges from the
      inner nodes (0 inner; ``element_patches``: 1 for every halo node).
    - ``elements``: per name (``"edge"``, ``"cell"``, or an energy's element kinds) the
      indices ``(m,)``, increasing, of the whole mesh's elements the patch keeps.
    """

    part: int
    nodes: np.ndarray
    inner: np.ndarray
    hops: np.ndarray
    elements: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def inner_nodes(self) -> np.ndarray:
        """Global ids ``(n_inner,)`` of the inner nodes."""
        return self.nodes[self.inner]

    def local(self, global_ids: np.ndarray) -> np.ndarray:
        """Local ids of global node ids (any shape); ``ValueError`` for a node outside the
        patch."""
        g = np.asarray(global_ids, np.int64)
        at = np.searchsorted(self.nodes, g).clip(max=len(self.nodes) - 1)
        if g.size and not np.array_equal(self.nodes[at], g):
            raise ValueError(f"nodes {np.unique(g[self.nodes[at] != g])[:5].tolist()} are not "
                             f"in patch {self.part}")
        return at


def _rings(a, seeds: np.ndarray, depth: int) -> np.ndarray:
    """Hop distance ``(N,)`` from the nodes ``seeds`` (bool ``(N,)``) over the graph ``a``, up
    to ``depth``; -1 beyond."""
    hops = np.where(seeds, 0, -1)
    reached = seeds.copy()
    for d in range(1, depth + 1):
        new = (a @ reached.astype(np.int32) > 0) & ~reached
        if not new.any():
            break
        hops[new] = d
        reached |= new
    return hops


def graph_patches(mesh: Mesh, parts: np.ndarray, depth: int) -> list[Patch]:
    """Per part the patch of its nodes and every node within ``depth`` hops over the mesh's
    edges, with the edges and cells whose nodes all lie in the patch (``elements["edge"]``,
    ``elements["cell"]``)."""
    if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 0:
        raise ValueError(f"depth must be an integer >= 0 (hops), got {depth!r}")
    parts = np.asarray(parts, np.int64)
    a = adjacency(mesh.edges, mesh.n_nodes)
    out = []
    for p in range(int(parts.max()) + 1):
        hops = _rings(a, parts == p, int(depth))
        nodes = np.flatnonzero(hops >= 0)
        kept = hops >= 0
        elements = {"edge": np.flatnonzero(kept[mesh.edges].all(1)),
                    "cell": np.flatnonzero(kept[np.asarray(mesh.cells, np.int64)].all(1))
                    if len(mesh.cells) else np.zeros(0, np.int64)}
        out.append(Patch(p, nodes, parts[nodes] == p, hops[nodes], elements))
    return out


def element_patches(elements: dict, parts: np.ndarray) -> list[Patch]:
    """Per part the patch of its nodes and the elements that touch one of them, with all
    their nodes. ``elements``: per kind the element nodes ``(m, k)`` (global ids), e.g. an
    energy's edges, rod hinges, dihedral hinges; ``elements[kind]`` of a patch indexes them."""
    parts = np.asarray(parts, np.int64)
    out = []
    for p in range(int(parts.max()) + 1):
        inner = parts == p
        kept = {kind: np.flatnonzero(inner[np.asarray(e, np.int64)].any(1))
                for kind, e in elements.items()}
        touched = [np.asarray(elements[kind], np.int64)[i].reshape(-1) for kind, i in kept.items()]
        nodes = np.union1d(np.flatnonzero(inner), np.concatenate(touched + [np.zeros(0, int)]))
        own = inner[nodes]
        out.append(Patch(p, nodes, own, np.where(own, 0, 1), kept))
    return out


def driven_patches(mesh: Mesh, elements: dict, parts: np.ndarray, rings: int) -> list[Patch]:
    """Per part the patch of a solve with a driven boundary: its nodes and the nodes within
    ``rings - 1`` hops (the unknowns, ``hops < rings``), the elements of ``elements`` (per kind
    the element nodes ``(m, k)``, global ids) that touch an unknown, and all their nodes; the
    nodes beyond the unknowns (``hops >= rings``) are the halo, held where the data puts them.
    ``rings = 1``: the unknowns are the part's nodes, the patch is ``element_patches``'."""
    if isinstance(rings, bool) or not isinstance(rings, (int, np.integer)) or rings < 1:
        raise ValueError(f"rings must be an integer >= 1 (element rings of the halo), got "
                         f"{rings!r}")
    parts = np.asarray(parts, np.int64)
    a = adjacency(mesh.edges, mesh.n_nodes)
    out = []
    for p in range(int(parts.max()) + 1):
        hops = _rings(a, parts == p, int(rings) + 1)     # a rod hinge reaches 2 hops
        hops[hops < 0] = int(rings) + 2
        solved = hops < rings
        kept = {kind: np.flatnonzero(solved[np.asarray(e, np.int64)].any(1))
                for kind, e in elements.items()}
        touched = [np.asarray(elements[kind], np.int64)[i].reshape(-1) for kind, i in kept.items()]
        nodes = np.union1d(np.flatnonzero(solved), np.concatenate(touched + [np.zeros(0, int)]))
        out.append(Patch(p, nodes, parts[nodes] == p, hops[nodes], kept))
    return out


def patch_mesh(mesh: Mesh, patch: Patch) -> Mesh:
    """The sub-mesh of ``patch`` (``graph_patches``): the whole mesh's node arrays (types,
    rest positions, masses, loads, drag) at its nodes, its edges and cells in local ids."""
    e = mesh.edges[patch.elements["edge"]]
    c = np.asarray(mesh.cells, np.int64).reshape(-1, 3)[patch.elements["cell"]]
    n = patch.nodes
    return Mesh(edges=patch.local(e).reshape(-1, 2), cells=patch.local(c).reshape(-1, 3),
                node_type=mesh.node_type[n], rest_pos=mesh.rest_pos[n], mass=mesh.mass[n],
                force=mesh.force[n], damping=mesh.damping[n], case=mesh.case,
                case_hash=mesh.case_hash)
