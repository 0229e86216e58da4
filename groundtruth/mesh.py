"""Structured triangulations of a strip, and the edges and hinges of a triangle mesh.

The strip mesh is made of rows: row ``i`` is the line ``x = x_i`` carrying ``n_width + 1``
nodes at ``y_j = -w/2 + j w / n_width``; node ``(i, j)`` has index ``i (n_width + 1) + j``, so
nodes are numbered across the width first and every element couples nodes at most two rows
apart (a narrow band, see ``groundtruth.assembly.Assembler.banded``). Each cell between two rows
is cut by one diagonal, alternating in a checkerboard, so the mesh is mirror symmetric about the
centre line ``y = 0`` when ``n_width`` is even and has no preferred diagonal direction.

Rows may be refined toward ``x = 0`` (``graded_rows``) with a spacing that is ``grading``
times finer at the clamp and relaxes to uniform over a boundary-layer length ``layer``; the map
is smooth, so refining ``n`` at fixed ``grading`` and ``layer`` refines uniformly.
"""

from __future__ import annotations

import numpy as np

PATTERNS = ("columns", "checker", "mirror", "uniform")


def graded_rows(length: float, n: int, grading: float = 1.0, layer: float = 0.02) -> np.ndarray:
    """``n + 1`` increasing row positions from 0 to ``length`` (m), refined near 0.

    The row spacing follows ``h(x) ~ 1 - (1 - 1/grading) exp(-x / layer)``: ``grading`` times
    finer at x = 0 than far away, relaxing to uniform over the length ``layer`` (m). Rows sit
    at equal steps of ``xi(x) = F(x) / F(length)``, ``F(x) = int_0^x dx' / h(x')
    = x + layer ln((1 - a e^(-x/layer)) / (1 - a))``, ``a = 1 - 1/grading``, so refining ``n``
    at fixed ``grading`` and ``layer`` is a uniform refinement in xi.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"graded_rows: n must be an int >= 1, got {n!r}")
    for name, v in (("grading", grading), ("layer", layer)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"graded_rows: {name} must be a positive number, got {v!r}")
    if grading < 1:
        raise ValueError(f"graded_rows: grading must be >= 1 (finer at x = 0), got {grading!r}")
    a = 1.0 - 1.0 / grading
    F = lambda x: x + layer * (np.log1p(-a * np.exp(-x / layer)) - np.log1p(-a))
    xi = np.arange(n + 1) / n * F(length)
    x = xi.copy()                                   # Newton on F(x) = xi, F' = 1/h >= 1
    for _ in range(60):
        h = 1.0 - a * np.exp(-x / layer)
        step = (F(x) - xi) * h
        x = np.clip(x - step, 0.0, length)
        if np.max(np.abs(step)) < 1e-15 * length:
            break
    x[0], x[-1] = 0.0, length
    return x


def strip_mesh(x_rows: np.ndarray, width: float, n_width: int, pattern: str = "checker"):
    """Triangulate the rows ``x_rows (R,)`` of a strip ``|y| <= width / 2`` lying in z = 0.

    Returns ``nodes (R (n_width + 1), 3)`` and counter-clockwise ``triangles (2 (R-1) n_width, 3)``.
    """
    if pattern not in PATTERNS:
        raise ValueError(f"strip_mesh: pattern must be one of {PATTERNS}, got {pattern!r}")
    x = np.asarray(x_rows, float)
    if x.ndim != 1 or x.size < 2 or np.any(np.diff(x) <= 0):
        raise ValueError(f"strip_mesh: x_rows must be >= 2 strictly increasing positions, "
                         f"got {x!r}")
    if not (isinstance(n_width, (int, np.integer)) and n_width >= 1):
        raise ValueError(f"strip_mesh: n_width must be an int >= 1, got {n_width!r}")
    nj = n_width + 1
    y = np.linspace(-width / 2, width / 2, nj)
    X, Y = np.meshgrid(x, y, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    i, j = np.meshgrid(np.arange(x.size - 1), np.arange(n_width), indexing="ij")
    i, j = i.ravel(), j.ravel()
    n00, n01 = i * nj + j, i * nj + j + 1
    n10, n11 = n00 + nj, n01 + nj
    up = {"columns": j % 2 == 0, "checker": (i + j) % 2 == 0, "mirror": 2 * j + 1 < n_width,
          "uniform": np.ones(i.size, bool)}[pattern]                      # diagonal n00-n11
    tri = np.empty((2 * i.size, 3), np.int64)
    tri[0::2] = np.where(up[:, None], np.stack([n00, n10, n11], 1), np.stack([n00, n10, n01], 1))
    tri[1::2] = np.where(up[:, None], np.stack([n00, n11, n01], 1), np.stack([n10, n11, n01], 1))
    return nodes, tri


def is_cell_diagonal(edges: np.ndarray, n_width: int) -> np.ndarray:
    """Boolean ``(E,)``: which edges ``(E, >=2)`` of a ``strip_mesh`` join nodes of different rows
    and different columns (the diagonals that cut each rectangular cell in two)."""
    e = np.asarray(edges, np.int64)
    r0, c0 = np.divmod(e[:, 0], n_width + 1)
    r1, c1 = np.divmod(e[:, 1], n_width + 1)
    return (r0 != r1) & (c0 != c1)


def triangle_areas(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Areas ``(M,)`` of the triangles (m^2), from the 3-D node positions."""
    x = np.asarray(nodes, float)[np.asarray(triangles)]
    return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)


def check_mesh(nodes: np.ndarray, triangles: np.ndarray, rel_area_tol: float = 1e-10) -> None:
    """Raise ``ValueError`` for a triangle mesh that DEP cannot use: bad shapes or indices,
    a degenerate triangle (area <= ``rel_area_tol`` x longest edge^2), an edge shared by more
    than two triangles, or two neighbours that traverse their shared edge the same way
    (inconsistent orientation)."""
    x = np.asarray(nodes)
    t = np.asarray(triangles)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise ValueError(f"mesh nodes must be a finite (N, 3) array, got shape {x.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] == 0:
        raise ValueError(f"mesh triangles must be a non-empty (M, 3) int array, "
                         f"got shape {t.shape}")
    if t.min() < 0 or t.max() >= x.shape[0]:
        raise ValueError(f"mesh triangles refer to nodes outside [0, {x.shape[0]})")
    area = triangle_areas(x, t)
    edge2 = np.max(np.sum((x[t] - x[np.roll(t, 1, axis=1)]) ** 2, axis=2), axis=1)
    bad = np.flatnonzero(area <= rel_area_tol * edge2)
    if bad.size:
        k = bad[0]
        raise ValueError(f"degenerate triangle {k} (nodes {t[k].tolist()}, area {area[k]:.3g} m^2)"
                         f" and {bad.size - 1} more: every triangle needs a positive area; "
                         "remove or re-mesh it")
    half = _half_edges(t)
    key = np.sort(half, axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    if count.max() > 2:
        e = key[np.flatnonzero(count[inv.ravel()] > 2)[0]]
        raise ValueError(f"non-manifold mesh: edge {e.tolist()} is shared by more than two "
                         "triangles")
    _, c2 = np.unique(half, axis=0, return_counts=True)
    if c2.max() > 1:
        raise ValueError("inconsistently oriented mesh: two triangles traverse a shared edge in "
                         "the same direction; orient all triangles counter-clockwise")


def _half_edges(triangles: np.ndarray) -> np.ndarray:
    """``(3M, 2)`` directed edges ``(t0, t1), (t1, t2), (t2, t0)`` of every triangle, in order."""
    t = np.asarray(triangles, np.int64)
    return np.stack([t, np.roll(t, -1, axis=1)], axis=2).reshape(-1, 2)


def mesh_edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)``, ``edges[:, 0] < edges[:, 1]``, sorted."""
    return np.unique(np.sort(_half_edges(triangles), axis=1), axis=0)


def edge_area_sums(triangles: np.ndarray, areas: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """For each edge of ``edges`` (as from ``mesh_edges``), the summed area of the one or two
    triangles that contain it, ``(E,)``."""
    half = np.sort(_half_edges(triangles), axis=1)
    n = int(max(half.max(), np.max(edges))) + 1
    pos = np.searchsorted(edges[:, 0] * n + edges[:, 1], half[:, 0] * n + half[:, 1])
    return np.bincount(pos, weights=np.repeat(areas, 3), minlength=len(edges))


def mesh_hinges(triangles: np.ndarray):
    """Hinges of the interior edges: ``hinges (H, 4)`` as ``(x0, x1, x2, x3)`` (edge x0 -> x1
    traversed by triangle A = (x0, x1, x2), x1 -> x0 by triangle B = (x1, x0, x3)) and the two
    triangle indices ``(H, 2)`` (A, B). Assumes a consistently oriented manifold mesh."""
    t = np.asarray(triangles, np.int64)
    half = _half_edges(t)
    opposite = np.roll(t, 1, axis=1).ravel()        # vertex opposite each half-edge
    tri_of = np.repeat(np.arange(t.shape[0]), 3)
    n = int(t.max()) + 1
    key_fwd = half[:, 0] * n + half[:, 1]
    key_rev = half[:, 1] * n + half[:, 0]
    order = np.argsort(key_fwd)
    pos = np.searchsorted(key_fwd[order], key_rev)
    pos = np.minimum(pos, half.shape[0] - 1)
    twin = order[pos]
    has_twin = key_fwd[twin] == key_rev
    a = np.flatnonzero(has_twin & (half[:, 0] < half[:, 1]))
    b = twin[a]
    hinges = np.stack([half[a, 0], half[a, 1], opposite[a], opposite[b]], axis=1)
    srt = np.lexsort((hinges[:, 1], hinges[:, 0]))
    return hinges[srt], np.stack([tri_of[a], tri_of[b]], axis=1)[srt]


def staggered_strip_points(length: float, width: float, n_rows: int, n_long: int) -> np.ndarray:
    """The point set of an unstructured strip mesh ``[0, length] x [0, width]`` in z = 0.

    ``n_rows`` rows at ``y_j = j width / (n_rows - 1)``. The two boundary rows (and every even
    row) carry ``n_long + 1`` nodes at ``x = k dx``, ``dx = length / n_long``; odd interior rows
    are staggered by ``dx / 2`` (nodes at ``(k + 1/2) dx``) plus one node at each short edge, so
    every row ends on both short edges (the clamp x = 0 holds all rows). With
    ``dx ~ (2 / sqrt 3) dy`` the triangles are near-equilateral. Points are sorted by x, then y,
    so a Delaunay mesh of them has a narrow band (``groundtruth.assembly``).
    """
    if not (isinstance(n_rows, (int, np.integer)) and n_rows >= 2):
        raise ValueError(f"staggered_strip_points: n_rows must be an int >= 2, got {n_rows!r}")
    if not (isinstance(n_long, (int, np.integer)) and n_long >= 1):
        raise ValueError(f"staggered_strip_points: n_long must be an int >= 1, got {n_long!r}")
    dx = length / n_long
    pts = []
    for j in range(n_rows):
        y = j * width / (n_rows - 1)
        if j % 2 == 0 or j == n_rows - 1:
            xs = np.arange(n_long + 1) * dx
        else:
            xs = np.concatenate([[0.0], (np.arange(n_long) + 0.5) * dx, [length]])
        pts.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    p = np.concatenate(pts)
    p = p[np.lexsort((p[:, 1], p[:, 0]))]
    return np.concatenate([p, np.zeros((len(p), 1))], axis=1)


def delaunay_mesh(points: np.ndarray, rel_area_tol: float = 1e-9):
    """Delaunay triangulation (``scipy.spatial.Delaunay``, Qhull) of planar ``points (N, 3)``
    (z ignored), triangles counter-clockwise from +z; flat triangles that Qhull may leave on
    collinear hull points (area <= ``rel_area_tol`` x longest edge^2) are dropped.
    Returns ``triangles (M, 3)``; ``check_mesh`` validates the result."""
    from scipy.spatial import Delaunay

    p = np.asarray(points, float)[:, :2]
    tri = Delaunay(p).simplices.astype(np.int64)
    d1, d2 = p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]
    signed = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    tri[signed < 0] = tri[signed < 0][:, [0, 2, 1]]
    edge2 = np.max(np.sum((p[tri] - p[np.roll(tri, 1, axis=1)]) ** 2, axis=2), axis=1)
    tri = tri[np.abs(signed) > rel_area_tol * edge2]
    check_mesh(np.asarray(points, float), tri)
    return tri
