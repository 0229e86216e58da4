"""Discrete Elastic Plates (DEP): a triangle mesh with stretching springs and bending hinges.

For a plate of Young's modulus Y (Pa), thickness h (m) and density rho (kg/m^3) meshed by
counter-clockwise triangles:

- stretching: every edge is a spring (``groundtruth.stretch``),
  E_s = 1/2 k_s l0 (|e|/l0 - 1)^2,  k_s = max((sqrt 3 / 2) Y h l0, Y h (A_A + A_B) / l0),
  which is the DEP constant (sqrt 3 / 2) Y h l0 on equilateral triangles (see
  ``spring_stiffness`` for why it is weighted by the areas of the edge's triangles);
- bending: every interior edge is a hinge (``groundtruth.hinge``),
  E_b = 1/2 k_b (theta - theta_bar)^2,  k_b = D |e|^2 / (A_A + A_B),  D = Y h^3 / 12,
  which is the DEP constant (2 / sqrt 3) Y h^3 / 12 on equilateral triangles (see
  ``hinge_stiffness`` for the calibration on other triangles);
- lumped mass: each triangle's rho A h split 1/3 to each of its nodes.
"""

from __future__ import annotations

import numpy as np

from groundtruth.hinge import HingeTerm, hinge_stiffness
from groundtruth.mesh import check_mesh, edge_area_sums, mesh_edges, mesh_hinges, triangle_areas
from groundtruth.stretch import StretchTerm


def _check_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def spring_stiffness(youngs: float, thickness: float, rest_length: np.ndarray,
                     area_sum: np.ndarray | None = None) -> np.ndarray:
    """Edge spring stiffness ``k_s (E,)`` (N) for E_s = 1/2 k_s l0 (|e|/l0 - 1)^2.

    Without ``area_sum`` it is the Discrete Elastic Plates value k_s = (sqrt 3 / 2) Y h l0.
    With the summed rest area of the triangles that share each edge (one triangle on the
    boundary) it is k_s = max((sqrt 3 / 2) Y h l0, Y h (A_A + A_B) / l0), i.e. the DEP value
    times the calibration factor max(1, psi), psi = (2 / sqrt 3)(A_A + A_B) / l0^2, which is 1 on
    interior edges of equilateral triangles.
    On a row mesh (``groundtruth.mesh.strip_mesh``) every triangle has exactly one edge along x,
    so the edges along x of a strip carry exactly its tensile stiffness Y h w whatever the row
    spacing dx; the uniform value gives (n_width + 1)(sqrt 3 / 2) Y h dx instead, which vanishes
    as the rows are refined (1/19 of Y h w at the clamp of the default plate mesh). The ``max``
    keeps the DEP value on long edges (the width of skinny cells would otherwise be nearly free,
    which made Newton fail on finely graded meshes).
    """
    Y = _check_positive("youngs", youngs)
    h = _check_positive("thickness", thickness)
    l0 = np.asarray(rest_length, float)
    k_dep = np.sqrt(3.0) / 2.0 * Y * h * l0
    if area_sum is None:
        return k_dep
    return np.maximum(k_dep, Y * h * np.asarray(area_sum, float) / l0)


def plate_terms(nodes: np.ndarray, triangles: np.ndarray, youngs: float, thickness: float,
                hinge_factor=None, spring_weights: str = "area") -> list:
    """``[StretchTerm, HingeTerm]`` of a DEP plate whose rest shape is ``nodes (N, 3)`` (m).

    ``spring_weights`` is ``"area"`` (calibrated, the default) or ``"uniform"`` (the DEP
    constant), see ``spring_stiffness``.

    ``hinge_factor``, if given, maps the hinges ``(H, 4)`` to factors ``(H,)`` that multiply
    their stiffness (``PlateCase`` stiffens the cell diagonals of its strip mesh with it).

    Raises ``ValueError`` for a non-positive modulus or thickness or an unusable mesh
    (``groundtruth.mesh.check_mesh``).
    """
    Y = _check_positive("youngs", youngs)
    h = _check_positive("thickness", thickness)
    check_mesh(nodes, triangles)
    x = np.asarray(nodes, float)
    edges = mesh_edges(triangles)
    l0 = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
    area = triangle_areas(x, triangles)
    if spring_weights not in ("area", "uniform"):
        raise ValueError(f"spring_weights must be 'area' or 'uniform', got {spring_weights!r}")
    area_sum = edge_area_sums(triangles, area, edges) if spring_weights == "area" else None
    stretch = StretchTerm(edges, l0, spring_stiffness(Y, h, l0, area_sum))
    hinges, tris = mesh_hinges(triangles)
    le = np.linalg.norm(x[hinges[:, 1]] - x[hinges[:, 0]], axis=1)
    k_b = hinge_stiffness(Y, h, le, area[tris].sum(axis=1))
    if hinge_factor is not None:
        k_b = k_b * np.asarray(hinge_factor(hinges), float)
    return [stretch, HingeTerm.from_rest(hinges, x, k_b)]


def drop_clamped(terms: list, fixed_nodes: np.ndarray) -> list:
    """The terms without the elements whose nodes are all clamped: such elements never change,
    so they add nothing to the free residual or tangent (their energy stays at its rest value,
    zero), and dropping them saves work and the very stiff hinges inside a thin clamp strip."""
    fixed = np.asarray(fixed_nodes, bool)
    out = []
    for t in terms:
        if isinstance(t, StretchTerm):
            keep = ~fixed[t.edges].all(axis=1)
            out.append(StretchTerm(t.edges[keep], t.l0[keep], t.k[keep]))
        elif isinstance(t, HingeTerm):
            keep = ~fixed[t.hinges].all(axis=1)
            out.append(HingeTerm(t.hinges[keep], t.theta_bar[keep], t.k_b[keep]))
        else:
            raise TypeError(f"drop_clamped: unknown term {type(t).__name__}")
    return out


def lumped_mass(nodes: np.ndarray, triangles: np.ndarray, density: float, thickness: float):
    """Node masses ``(N,)`` (kg): each triangle's ``rho A h`` split 1/3 to each of its nodes."""
    rho = _check_positive("density", density)
    h = _check_positive("thickness", thickness)
    t = np.asarray(triangles, np.int64)
    m_tri = rho * h * triangle_areas(nodes, t) / 3.0
    return np.bincount(t.ravel(), weights=np.repeat(m_tri, 3), minlength=len(nodes))


def clamp_mask(nodes: np.ndarray, x_clamp: float, min_rows: int = 2, tol: float = 1e-12):
    """Boolean ``(N,)``: the nodes with ``x <= x_clamp`` (m). The hinge model has no rotational
    dofs, so a clamp must hold at least ``min_rows`` distinct rows ``x = const``; otherwise a
    ``ValueError`` says what the clamp caught."""
    x = np.asarray(nodes, float)[:, 0]
    fixed = x <= x_clamp + tol * max(1.0, np.ptp(x))
    if not fixed.any():
        raise ValueError(f"the clamp x <= {x_clamp!r} m fixes no node (mesh x from {x.min():.4g} "
                         f"to {x.max():.4g} m); move the clamp or add clamp rows")
    rows = np.unique(np.round(x[fixed], 12)).size
    if rows < min_rows:
        raise ValueError(f"the clamp x <= {x_clamp!r} m fixes {rows} row(s) of nodes; a hinge "
                         f"plate needs at least {min_rows} clamped rows to hold the slope")
    return fixed


def plane_stress_matrix(youngs: float, poisson: float) -> np.ndarray:
    """Plane-stress elasticity ``D (3, 3)`` (Pa) in Voigt form ``(s_xx, s_yy, s_xy) = D (e_xx,
    e_yy, 2 e_xy)``: ``Y / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]]``."""
    Y = _check_positive("youngs", youngs)
    if not (0.0 <= float(poisson) < 0.5):
        raise ValueError(f"poisson must be in [0, 0.5), got {poisson!r}")
    nu = float(poisson)
    return Y / (1.0 - nu**2) * np.array([[1.0, nu, 0.0], [nu, 1.0, 0.0],
                                         [0.0, 0.0, 0.5 * (1.0 - nu)]])


def edge_strain_map(nodes: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``T (M, 3, 3)``: row i maps a triangle's Voigt strain ``(e_xx, e_yy, 2 e_xy)`` to the
    strain ``t_i . e t_i`` of its edge i (edges ``(t0, t1), (t1, t2), (t2, t0)``, unit
    directions ``t_i`` in the x-y plane): ``[tx^2, ty^2, tx ty]``."""
    x = np.asarray(nodes, float)[:, :2]
    t = np.asarray(triangles, np.int64)
    d = x[np.roll(t, -1, axis=1)] - x[t]                               # (M, 3, 2)
    d = d / np.linalg.norm(d, axis=2, keepdims=True)
    return np.stack([d[..., 0] ** 2, d[..., 1] ** 2, d[..., 0] * d[..., 1]], axis=2)


def cst_spring_stiffness(nodes: np.ndarray, triangles: np.ndarray, edges: np.ndarray,
                         youngs: float, thickness: float, poisson: float = 1.0 / 3.0):
    """Edge spring stiffness ``k_s (E,)`` (N) calibrated per triangle from its constant-strain
    plane-stress stiffness.

    A triangle of rest area A under a uniform small strain e stores ``1/2 A h e^T D e``
    (``plane_stress_matrix``). Its three edge strains ``eps = T e`` (``edge_strain_map``)
    determine e, so this energy is ``1/2 eps^T K_e eps`` with ``K_e = T^-T A h D T^-1``. Three
    springs store ``1/2 sum_i c_i eps_i^2``: they take ``c_i = (K_e)_ii``, and each edge sums
    the ``c_i`` of its one or two triangles; ``k_s = c / l0`` for
    ``E_s = 1/2 k_s l0 eps^2``. On an equilateral triangle with nu = 1/3, K_e is diagonal and
    the springs reproduce the constant-strain element exactly (each edge gets
    ``(sqrt 3 / 4) Y h l0`` per triangle, the DEP constant for two triangles); on other
    triangles the off-diagonal couplings are dropped (a spring network has nu = 1/3 and no
    more freedom). K_e is positive definite, so every c_i > 0.
    """
    Y = _check_positive("youngs", youngs)
    h = _check_positive("thickness", thickness)
    x = np.asarray(nodes, float)
    t = np.asarray(triangles, np.int64)
    T = edge_strain_map(x, t)
    Ti = np.linalg.inv(T)
    A = triangle_areas(x, t)
    K = np.einsum("mji,jk,mkl->mil", Ti, plane_stress_matrix(Y, poisson), Ti) \
        * (A * h)[:, None, None]
    c = np.einsum("mii->mi", K)                                        # (M, 3)
    half = np.sort(np.stack([t, np.roll(t, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    e = np.asarray(edges, np.int64)
    n = int(max(half.max(), e.max())) + 1
    pos = np.searchsorted(e[:, 0] * n + e[:, 1], half[:, 0] * n + half[:, 1])
    c_edge = np.bincount(pos, weights=c.ravel(), minlength=len(e))
    l0 = np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
    return c_edge / l0


def inplane_stiffness(nodes: np.ndarray, edges: np.ndarray, k_s: np.ndarray):
    """Linear in-plane stiffness ``K (2N, 2N)`` (CSR, N/m; dofs x0, y0, x1, ...) of edge
    springs ``E_s = 1/2 k_s l0 eps^2`` about the rest shape: ``(k_s / l0) t t^T`` per edge."""
    import scipy.sparse

    x = np.asarray(nodes, float)[:, :2]
    e = np.asarray(edges, np.int64)
    d = x[e[:, 1]] - x[e[:, 0]]
    l0 = np.linalg.norm(d, axis=1)
    t = d / l0[:, None]
    kk = (np.asarray(k_s, float) / l0)[:, None, None] * t[:, :, None] * t[:, None, :]
    blk = np.concatenate([np.concatenate([kk, -kk], 2), np.concatenate([-kk, kk], 2)], 1)
    dofs = np.concatenate([2 * e[:, :1] + np.arange(2), 2 * e[:, 1:] + np.arange(2)], axis=1)
    rows = np.repeat(dofs, 4, axis=1).ravel()
    cols = np.tile(dofs, (1, 4)).ravel()
    n = 2 * len(x)
    return scipy.sparse.csr_matrix((blk.ravel(), (rows, cols)), shape=(n, n))
