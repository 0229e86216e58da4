"""Strip meshes, edges, hinges and mesh validation (``groundtruth.mesh``)."""

from __future__ import annotations

import numpy as np
import pytest

from groundtruth.assembly import Assembler
from groundtruth.cases import PlateCase
from groundtruth.mesh import (
    PATTERNS,
    check_mesh,
    edge_area_sums,
    graded_rows,
    is_cell_diagonal,
    mesh_edges,
    mesh_hinges,
    strip_mesh,
    triangle_areas,
)


def signed_areas(nodes, tri):
    x = nodes[tri]
    d1, d2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


class TestGradedRows:
    def test_endpoints_monotone_and_grading(self):
        x = graded_rows(1.0, 48, 16.0, 0.03)
        assert x[0] == 0.0 and x[-1] == 1.0
        dx = np.diff(x)
        assert np.all(dx > 0) and np.all(np.diff(dx) > -1e-15)
        # fine rows: the spacing at the clamp is `grading` times the spacing far from it
        fine = np.diff(graded_rows(1.0, 4000, 16.0, 0.03))
        assert fine[-1] / fine[0] == pytest.approx(16.0, rel=0.01)
        # and the refinement is confined to a few `layer` lengths
        assert fine[-1] / fine[len(fine) // 4] == pytest.approx(1.0, abs=5e-3)

    def test_uniform(self):
        np.testing.assert_allclose(graded_rows(2.0, 4, 1.0), [0, 0.5, 1, 1.5, 2])

    def test_refinement_nests(self):
        """Doubling n at fixed grading adds one row between each pair (uniform refinement)."""
        np.testing.assert_allclose(graded_rows(1.0, 48, 16.0, 0.03)[::2],
                                   graded_rows(1.0, 24, 16.0, 0.03), atol=1e-14)

    @pytest.mark.parametrize("n, grading", [(0, 1.0), (2.5, 1.0), (4, 0.0), (4, np.nan), (4, 0.5)])
    def test_bad_input(self, n, grading):
        with pytest.raises(ValueError, match="graded_rows"):
            graded_rows(1.0, n, grading)


class TestStripMesh:
    @pytest.mark.parametrize("pattern", PATTERNS)
    @pytest.mark.parametrize("n_width", [1, 2, 4])
    def test_counts_orientation_topology(self, pattern, n_width):
        rows = graded_rows(1.0, 7, 3.0, 0.1)
        nodes, tri = strip_mesh(rows, 0.1, n_width, pattern)
        R = rows.size
        assert nodes.shape == (R * (n_width + 1), 3) and tri.shape == (2 * (R - 1) * n_width, 3)
        assert np.all(signed_areas(nodes, tri) > 0), "triangles must be counter-clockwise"
        check_mesh(nodes, tri)
        edges = mesh_edges(tri)
        assert len(nodes) - len(edges) + len(tri) == 1          # Euler: a disk
        boundary = 2 * (R - 1) + 2 * n_width
        hinges, _ = mesh_hinges(tri)
        assert len(hinges) == len(edges) - boundary
        assert np.allclose(triangle_areas(nodes, tri).sum(), 0.1 * 1.0)

    def test_width_first_numbering_is_banded(self):
        case = PlateCase()
        system = case.system(5e6)
        assert isinstance(system.assembler, Assembler) and system.assembler.banded
        # hinges reach two rows apart: 3 dofs x (2 rows x 3 nodes + 2) - 1
        assert system.assembler.bandwidth <= 3 * (2 * (case.n_width + 1) + 2) - 1

    @pytest.mark.parametrize("pattern", ["columns", "mirror"])
    def test_mirror_symmetric_for_even_width(self, pattern):
        nodes, tri = strip_mesh(np.linspace(0, 1, 6), 0.1, 4, pattern)
        mirror = nodes * [1, -1, 1]
        # map every node to its mirror image, then every triangle must exist (reversed order)
        lookup = {tuple(np.round(p, 12)): i for i, p in enumerate(nodes)}
        image = np.array([lookup[tuple(np.round(p, 12))] for p in mirror])
        key = {tuple(sorted(t)) for t in tri.tolist()}
        assert {tuple(sorted(image[t])) for t in tri.tolist()} == key

    def test_hinge_orientation(self):
        nodes, tri = strip_mesh(np.linspace(0, 1, 5), 0.1, 2)
        hinges, pair = mesh_hinges(tri)
        for (x0, x1, x2, x3), (a, b) in zip(hinges, pair, strict=True):
            ta, tb = tri[a].tolist(), tri[b].tolist()
            # A traverses x0 -> x1 (cyclically) and holds x2; B traverses x1 -> x0 and holds x3
            ia, ib = ta.index(x0), tb.index(x1)
            assert ta[(ia + 1) % 3] == x1 and ta[(ia + 2) % 3] == x2
            assert tb[(ib + 1) % 3] == x0 and tb[(ib + 2) % 3] == x3

    def test_cell_diagonals(self):
        nodes, tri = strip_mesh(np.linspace(0, 1, 5), 0.1, 2)
        edges = mesh_edges(tri)
        diag = is_cell_diagonal(edges, 2)
        assert diag.sum() == 4 * 2
        d = nodes[edges[diag, 1]] - nodes[edges[diag, 0]]
        assert np.all(np.abs(d[:, 0]) > 0) and np.all(np.abs(d[:, 1]) > 0)

    def test_edge_area_sums(self):
        nodes, tri = strip_mesh(graded_rows(1.0, 6, 4.0, 0.1), 0.1, 2)
        edges = mesh_edges(tri)
        area = triangle_areas(nodes, tri)
        sums = edge_area_sums(tri, area, edges)
        assert sums.sum() == pytest.approx(3 * area.sum())
        # each triangle has exactly one edge along x: those edges carry the whole area once
        along_x = np.abs(nodes[edges[:, 1], 1] - nodes[edges[:, 0], 1]) < 1e-12
        assert sums[along_x].sum() == pytest.approx(area.sum())

    @pytest.mark.parametrize("kw, match", [
        (dict(x_rows=[0.0, 0.0, 1.0]), "strictly increasing"),
        (dict(n_width=0), "n_width"),
        (dict(pattern="zigzag"), "pattern must be one of"),
    ])
    def test_bad_input(self, kw, match):
        args = dict(x_rows=np.linspace(0, 1, 4), width=0.1, n_width=2, pattern="columns") | kw
        with pytest.raises(ValueError, match=match):
            strip_mesh(**args)


class TestCheckMesh:
    def base(self):
        return strip_mesh(np.linspace(0, 1, 4), 0.1, 2)

    def test_degenerate_triangle(self):
        nodes, tri = self.base()
        nodes = nodes.copy()
        a, b, c = tri[3]
        nodes[c] = 0.5 * (nodes[a] + nodes[b])       # collapse triangle 3 onto its edge a-b
        with pytest.raises(ValueError, match="degenerate triangle 3"):
            check_mesh(nodes, tri)

    def test_repeated_node_is_degenerate(self):
        nodes, tri = self.base()
        tri = tri.copy()
        tri[0, 2] = tri[0, 1]
        with pytest.raises(ValueError, match="degenerate triangle 0"):
            check_mesh(nodes, tri)

    def test_inconsistent_orientation(self):
        nodes, tri = self.base()
        tri = tri.copy()
        tri[1] = tri[1, ::-1]
        with pytest.raises(ValueError, match="inconsistently oriented"):
            check_mesh(nodes, tri)

    def test_non_manifold_edge(self):
        nodes, tri = self.base()
        x0, x1 = mesh_hinges(tri)[0][0, :2]              # an interior edge, already shared by two
        extra = np.array([[x1, x0, len(nodes)]])
        nodes = np.vstack([nodes, [[0.0, 0.0, 1.0]]])
        with pytest.raises(ValueError, match="non-manifold"):
            check_mesh(nodes, np.vstack([tri, extra]))

    @pytest.mark.parametrize("bad", ["index", "shape", "nan"])
    def test_bad_arrays(self, bad):
        nodes, tri = self.base()
        if bad == "index":
            tri = tri + len(nodes)
        elif bad == "shape":
            nodes = nodes[:, :2]
        else:
            nodes = nodes.copy()
            nodes[0, 0] = np.nan
        with pytest.raises(ValueError, match="mesh"):
            check_mesh(nodes, tri)
