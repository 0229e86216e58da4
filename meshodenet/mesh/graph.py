"""Graphs: directed edges, rod hinges, and the disjoint batch of many trajectories.

Index tensors are built once per (mesh, number of graphs, device) and reused by every
evaluation of a rollout; only positions and velocities change between evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from meshodenet.mesh.data import DataError, Mesh


def directed_edges(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each undirected edge as two directed ones: ``senders, receivers (2E,)``.

    Edge ``k`` of ``edges`` gives ``k: i -> j`` and ``E + k: j -> i``.
    """
    edges = np.asarray(edges, np.int64)
    return (np.concatenate([edges[:, 0], edges[:, 1]]),
            np.concatenate([edges[:, 1], edges[:, 0]]))


def rod_hinges(edges: np.ndarray, n_nodes: int) -> np.ndarray:
    """Hinges ``(H, 3)`` of a line mesh: ``(prev, node, next)`` for every node of degree 2.

    The chain is walked from its end node of lowest index, so ``prev -> node -> next`` keeps
    one orientation along the rod and the signed turning angle has a consistent sign.
    Raises ``DataError`` for a branching mesh (a node with more than two edges).
    """
    nbrs = [[] for _ in range(n_nodes)]
    for i, j in np.asarray(edges, np.int64):
        nbrs[i].append(int(j))
        nbrs[j].append(int(i))
    deg = np.array([len(n) for n in nbrs])
    if deg.max(initial=0) > 2:
        raise DataError(f"line mesh: node {int(np.argmax(deg))} has {int(deg.max())} edges; "
                        "the angle feature needs unbranched rods")
    hinges, seen = [], np.zeros(n_nodes, bool)
    starts = [k for k in range(n_nodes) if deg[k] == 1] + [k for k in range(n_nodes) if deg[k]]
    for start in starts:  # ends first, then closed loops
        if seen[start]:
            continue
        prev, node = -1, start
        while node != -1 and not seen[node]:
            seen[node] = True
            nxt = next((j for j in nbrs[node] if j != prev and not seen[j]), -1)
            if prev != -1 and nxt != -1:
                hinges.append((prev, node, nxt))
            prev, node = node, nxt
    return np.array(hinges, np.int64).reshape(-1, 3)


def triangle_hinges(cells: np.ndarray) -> np.ndarray:
    """Hinges ``(H, 4)`` of a triangle mesh: ``(i, j, k, l)`` for every edge ``i < j`` shared by
    exactly two triangles ``(i, j, k)`` and ``(i, j, l)`` (in either orientation), the
    triangle of lower index first; sorted by ``(i, j)``. Boundary edges (one triangle) and
    non-manifold edges (three or more) have none."""
    cells = np.asarray(cells, np.int64).reshape(-1, 3)
    sides = np.concatenate([cells[:, [0, 1, 2]], cells[:, [1, 2, 0]], cells[:, [2, 0, 1]]])
    tri = np.tile(np.arange(len(cells)), 3)
    pairs = np.sort(sides[:, :2], axis=1)
    order = np.lexsort((tri, pairs[:, 1], pairs[:, 0]))  # by edge, then by triangle
    pairs, opposite = pairs[order], sides[order, 2]
    if not len(pairs):
        return np.zeros((0, 4), np.int64)
    start = np.flatnonzero(np.r_[True, np.any(pairs[1:] != pairs[:-1], axis=1)])
    count = np.diff(np.r_[start, len(pairs)])
    two = start[count == 2]
    return np.stack([pairs[two, 0], pairs[two, 1], opposite[two], opposite[two + 1]], 1)


@dataclass(frozen=True)
class GraphBatch:
    """``n_graphs`` copies of one mesh as a disjoint graph of ``n_graphs * n_per_graph`` nodes.

    Node ``b * n_per_graph + i`` is node ``i`` of copy ``b``. Shapes (``M`` = all nodes,
    ``D`` = all directed edges): ``senders, receivers (D,)``, ``hinges (H_all, 3)``,
    ``free (M, 1)`` (1 free, 0 clamped), ``force (M, 3)``, ``damping (M, 1)``,
    ``node_type (M,)``, ``rest_vec (D, 3)`` (rest x_j - x_i along each directed edge),
    ``rest_pos (M, 3)`` (rest positions).
    """

    n_graphs: int
    n_per_graph: int
    senders: torch.Tensor
    receivers: torch.Tensor
    hinges: torch.Tensor
    free: torch.Tensor
    force: torch.Tensor
    damping: torch.Tensor
    node_type: torch.Tensor
    rest_vec: torch.Tensor
    rest_pos: torch.Tensor

    @property
    def n_nodes(self) -> int:
        return self.n_graphs * self.n_per_graph


class GraphTopology:
    """One mesh, ready to be batched: holds numpy index arrays and caches ``GraphBatch``es.

    ``hinges`` may be given explicitly (tests relabel nodes); by default they are found by
    ``rod_hinges`` for line meshes and are empty for triangle meshes.
    """

    def __init__(self, mesh: Mesh, hinges: np.ndarray | None = None):
        self.mesh = mesh
        self.kind = mesh.kind
        self.senders, self.receivers = directed_edges(mesh.edges)
        if hinges is None:
            hinges = rod_hinges(mesh.edges, mesh.n_nodes) if self.kind == "line" \
                else np.zeros((0, 3), np.int64)
        self.hinges = np.asarray(hinges, np.int64).reshape(-1, 3)
        self._cache: dict = {}

    def batch(self, n_graphs: int, device, dtype) -> GraphBatch:
        key = (n_graphs, str(device), dtype)
        if key not in self._cache:
            self._cache[key] = self._build(n_graphs, device, dtype)
        return self._cache[key]

    def _build(self, n_graphs: int, device, dtype) -> GraphBatch:
        m = self.mesh
        N = m.n_nodes
        off = np.arange(n_graphs, dtype=np.int64)[:, None] * N
        idx = lambda a: torch.as_tensor((a[None] + off.reshape(-1, *([1] * a.ndim))).reshape(
            -1, *a.shape[1:]), dtype=torch.long, device=device)
        tile = lambda a: torch.as_tensor(np.tile(a, (n_graphs,) + (1,) * (a.ndim - 1)),
                                         dtype=dtype, device=device)
        rest = m.rest_pos[self.receivers] - m.rest_pos[self.senders]
        return GraphBatch(
            n_graphs=n_graphs, n_per_graph=N,
            senders=idx(self.senders), receivers=idx(self.receivers), hinges=idx(self.hinges),
            free=tile((m.node_type == 0).astype(np.float64)[:, None]),
            force=tile(m.force), damping=tile(m.damping[:, None]),
            node_type=torch.as_tensor(np.tile(m.node_type, n_graphs), device=device),
            rest_vec=tile(rest), rest_pos=tile(m.rest_pos))


def band_order(pairs: np.ndarray, n: int) -> np.ndarray:
    """A reverse Cuthill-McKee order ``(n,)`` (new position -> old index) of ``n`` unknowns
    coupled by the index pairs ``pairs (m, 2)``: it makes their matrix banded and narrow."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    i, j = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n)).tocsr()
    return np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), np.int64)
