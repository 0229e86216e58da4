"""The DEP plate cases: ``PlateCase`` (``plate_hanging``, gravity through the thickness) and
``InPlanePlateCase`` (``plate_cantilever``, gravity in the plane). docs/PLATE.md."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from groundtruth import implicit
from groundtruth.cases.base import (
    CaseBase,
    _check_choice,
    _check_ints,
    _check_nonneg,
    _check_positive,
    check_youngs,
)
from groundtruth.hinge import HingeTerm, hinge_stiffness
from groundtruth.implicit import PREDICTORS, NewtonSettings
from groundtruth.mesh import (
    PATTERNS,
    delaunay_mesh,
    graded_rows,
    is_cell_diagonal,
    mesh_edges,
    mesh_hinges,
    staggered_strip_points,
    strip_mesh,
    triangle_areas,
)
from groundtruth.plate import (
    clamp_mask,
    cst_spring_stiffness,
    drop_clamped,
    inplane_stiffness,
    lumped_mass,
    plate_terms,
)
from groundtruth.stretch import StretchTerm
from groundtruth.system import MechanicalSystem


@dataclass(frozen=True)
class PlateCase(CaseBase):
    """A Discrete Elastic Plates cantilever falling under gravity through its thickness
    (``plate_hanging``; docs/PLATE.md gives the choices below and their measurements).

    Flat in the x-y plane at t = 0, ``|y| <= width / 2``, gravity along -z. ``n_clamp_rows``
    clamped rows at ``x = clamp_gap (1/2 - k)`` hold the slope (the hinges have no rotational
    dofs), so the clamp line is x = 0 and the free length is ``length``. Mesh
    (``groundtruth.mesh.strip_mesh``): ``n_width`` intervals across, ``n_length`` rows along the
    free length, ``grading`` times finer at the clamp relaxing to uniform over ``grading_layer``
    (m), cells cut by ``pattern`` diagonals. Physics (``groundtruth.plate``): edge springs by
    ``spring_weights``, hinges k_b = D |e|^2 / (A_A + A_B) with D = Y h^3 / 12, times
    ``diagonal_stiffening`` on the cell diagonals; lumped mass rho A h / 3 per triangle corner;
    gravity -m g z; mass-proportional damping ``-c m v``, c = ``damping_rate`` (1/s). Units SI.

    ``refined(r)`` (id ``CASE@rN``, docs/SCALE.md): ``n_length`` and ``n_width`` times r on the
    same graded map, ``clamp_gap`` over r (the clamp line x = 0 and its slope stay).
    """

    id: str = "plate_hanging"
    length: float = 1.0
    width: float = 0.1
    thickness: float = 1e-3
    density: float = 1200.0
    gravity: float = 9.81
    damping_rate: float = 0.5
    n_length: int = 48
    n_width: int = 2
    grading: float = 16.0
    grading_layer: float = 0.03
    n_clamp_rows: int = 2
    clamp_gap: float = 1e-3
    pattern: str = "columns"
    diagonal_stiffening: float = 1000.0
    spring_weights: str = "area"
    t_end: float = 1.5
    save_dt: float = 0.003
    dt: float = 0.00075
    newton_rtol: float = 1e-4
    newton_predictor: str = "acceleration"
    youngs_train: tuple = (2.5e6, 7.5e6)
    youngs_test: tuple = (2.5e6, 7.5e6)
    n_train: int = 30
    n_test: int = 6
    seed_train: int = 30_000
    seed_test: int = 6_000
    resolution: int = 1

    kind = "plate"

    def __post_init__(self):
        _check_positive(self, "length", "width", "thickness", "density", "gravity", "grading",
                        "grading_layer", "clamp_gap", "diagonal_stiffening")
        if self.grading < 1:
            raise ValueError(f"PlateCase.grading must be >= 1 (rows finer at the clamp), "
                             f"got {self.grading!r}")
        _check_choice(self, "pattern", PATTERNS)
        _check_choice(self, "newton_predictor", PREDICTORS)
        _check_choice(self, "spring_weights", ("area", "uniform"))
        _check_nonneg(self, "damping_rate")
        _check_ints(self, n_length=1, n_width=1)
        n = self.n_clamp_rows
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError(f"PlateCase.n_clamp_rows must be an int >= 2 (the hinge model has no "
                             f"rotational dofs: the clamp must hold the slope), got {n!r}")
        x1 = graded_rows(self.length, self.n_length, self.grading, self.grading_layer)[1]
        if self.clamp_gap >= 2 * x1:
            raise ValueError(f"PlateCase.clamp_gap ({self.clamp_gap!r} m) must be smaller than "
                             f"twice the first free row spacing ({x1:.4g} m): the last clamped "
                             "row sits at x = clamp_gap / 2; pass a smaller clamp_gap")
        self._check_common()

    def refined(self, r: int) -> PlateCase:
        """This case on a mesh r times finer, id ``CASE@rN`` (docs/SCALE.md): ``n_length`` and
        ``n_width`` times r, the same ``grading`` and ``grading_layer`` (so the same graded
        map), ``clamp_gap`` over r; the same sheet, loads and time step; ``r = 1``: itself."""
        if self._check_refinable(r) == 1:
            return self
        return self._refined_copy(r, n_length=self.n_length * r, n_width=self.n_width * r,
                                  clamp_gap=self.clamp_gap / r)

    # --- geometry --------------------------------------------------------------------------
    def x_rows(self) -> np.ndarray:
        """Row positions ``(n_clamp_rows + n_length,)``, m: clamped rows at
        ``x = clamp_gap (1/2 - k)``, k = n_clamp_rows - 1 ... 0, then the graded free rows."""
        free = graded_rows(self.length, self.n_length, self.grading, self.grading_layer)[1:]
        clamp = self.clamp_gap * (0.5 - np.arange(self.n_clamp_rows - 1, -1, -1))
        return np.concatenate([clamp, free])

    @functools.cached_property
    def _mesh(self):
        nodes, tri = strip_mesh(self.x_rows(), self.width, self.n_width, self.pattern)
        fixed = clamp_mask(nodes, 0.5 * self.clamp_gap, min_rows=2)
        return nodes, tri, mesh_edges(tri), fixed

    def rest_positions(self) -> np.ndarray:
        return self._mesh[0].copy()

    def mesh(self):
        """``edges (E, 2)``, ``cells (M, 3)`` (counter-clockwise from +z), ``node_type (N,)``."""
        nodes, tri, edges, fixed = self._mesh
        return edges.copy(), tri.copy(), fixed.astype(np.int64)

    def initial_state(self):
        x = self.rest_positions()
        return x, np.zeros_like(x)

    def bending_rigidity(self, youngs: float) -> float:
        """EI = Y w h^3 / 12 of the strip, N m^2."""
        return check_youngs(youngs) * self.width * self.thickness**3 / 12.0

    @property
    def line_load(self) -> float:
        """Weight per unit length q = rho g h w, N/m."""
        return self.density * self.gravity * self.thickness * self.width

    @property
    def solver_settings(self) -> NewtonSettings:
        return NewtonSettings(dt=self.dt, rtol=self.newton_rtol, predictor=self.newton_predictor)

    def load_parameter(self, youngs: float) -> float:
        """alpha = q L^3 / EI of the free length (the elastica's uniform-load parameter)."""
        return self.line_load * self.length**3 / self.bending_rigidity(youngs)

    def solve_static(self, youngs: float, n_load_steps: int = 10) -> np.ndarray:
        """Static equilibrium under gravity ``(N, 3)``, m. The load rises geometrically from
        alpha = 10 (tip already deflected by ~0.7 L) to the full alpha, with the Newton
        tolerance relative to the applied load, so soft plates (alpha ~ 1e4-1e5) converge."""
        system = self.system(youngs)
        q0, _ = self.initial_state()
        first = min(1.0, 10.0 / self.load_parameter(youngs))
        q = implicit.solve_static(system, q0.ravel(), self.solver_settings, n_load_steps,
                                  first_load=first)
        return q.reshape(-1, 3)

    # --- physics ---------------------------------------------------------------------------
    def _hinge_factor(self, hinges: np.ndarray) -> np.ndarray:
        return np.where(is_cell_diagonal(hinges, self.n_width), self.diagonal_stiffening, 1.0)

    def system(self, youngs: float) -> MechanicalSystem:
        """The DEP system for modulus ``youngs`` (Pa)."""
        Y = check_youngs(youngs)
        nodes, tri, _, fixed = self._mesh
        mass = lumped_mass(nodes, tri, self.density, self.thickness)
        force = np.zeros((len(nodes), 3))
        force[:, 2] = -mass * self.gravity
        # Newton tolerances are relative to a node's weight, floored at 1e-10 Y h w: the residual
        # cannot drop below ~1e-15 Y h w in double precision (very stiff plates, tiny loads)
        weight = self.density * self.thickness * self.width * self.length * self.gravity
        scale = max(weight / len(nodes), 1e-10 * Y * self.thickness * self.width)
        terms = plate_terms(nodes, tri, Y, self.thickness, hinge_factor=self._hinge_factor,
                            spring_weights=self.spring_weights)
        terms = drop_clamped(terms, fixed)
        return MechanicalSystem(terms, mass,
                                self.damping_rate * mass, force, fixed, force_scale=scale)


@dataclass(frozen=True)
class InPlanePlateCase(CaseBase):
    """A DEP strip sagging in its own plane (``plate_cantilever``, the paper's case study 2 as
    its authors ran it; docs/PLATE.md gives the choices below and their measurements).

    The strip ``[0, length] x [0, width]`` lies in the x-y plane (z = 0), the nodes on x = 0
    are clamped, gravity acts in -y. Mesh: ``scipy.spatial.Delaunay`` of a staggered point set
    (``groundtruth.mesh.staggered_strip_points``), ``n_rows`` rows across (odd, so that a row
    carries the tip node) and ``n_long`` intervals along. Physics: edge springs from each
    triangle's constant-strain plane-stress stiffness with ``poisson``
    (``cst_spring_stiffness``), all times ``bending_calibration`` (the network's small-load tip
    deflection over Timoshenko's); hinges k_b = D |e|^2 / (A_A + A_B); lumped mass rho A h / 3
    per triangle corner; gravity -m g y; mass-proportional damping ``-c m v``,
    c = ``damping_rate``. Positions stay (N, 3) with z = 0 throughout. Units SI.

    ``refined(r)`` (id ``CASE@rN``, docs/SCALE.md): ``n_rows - 1`` and ``n_long`` times r, the
    same strip, clamp x = 0, loads and time step.
    """

    id: str = "plate_cantilever"
    length: float = 1.0
    width: float = 0.1
    thickness: float = 1e-3
    density: float = 1200.0
    gravity: float = 9.81
    poisson: float = 1.0 / 3.0
    shear_factor: float = 5.0 / 6.0
    damping_rate: float = 20.75
    n_rows: int = 5
    n_long: int = 35
    calibrate_bending: bool = True
    t_end: float = 1.5
    save_dt: float = 0.003
    dt: float = 0.0015
    newton_rtol: float = 1e-6
    newton_predictor: str = "acceleration"
    youngs_train: tuple = (2.5e6, 7.5e6)
    youngs_test: tuple = (2.5e6, 7.5e6)
    n_train: int = 30
    n_test: int = 6
    seed_train: int = 30_000
    seed_test: int = 6_000
    resolution: int = 1

    kind = "plate_inplane"

    def __post_init__(self):
        _check_positive(self, "length", "width", "thickness", "density", "gravity",
                        "shear_factor")
        if not (isinstance(self.poisson, (int, float)) and 0 <= self.poisson < 0.5):
            raise ValueError(f"InPlanePlateCase.poisson must be in [0, 0.5), got {self.poisson!r}")
        _check_nonneg(self, "damping_rate")
        _check_ints(self, n_rows=3, n_long=1)
        if self.n_rows % 2 == 0:
            raise ValueError(f"InPlanePlateCase.n_rows must be odd (a node row on the centre "
                             f"line carries the tip node), got {self.n_rows!r}")
        _check_choice(self, "newton_predictor", PREDICTORS)
        self._check_common()

    def refined(self, r: int) -> InPlanePlateCase:
        """This case on a mesh r times finer, id ``CASE@rN`` (docs/SCALE.md): ``(n_rows - 1) r
        + 1`` rows across, ``n_long r`` intervals along (the triangles keep their shape), the
        same strip, clamp, loads and time step; ``r = 1``: the case itself."""
        if self._check_refinable(r) == 1:
            return self
        return self._refined_copy(r, n_rows=(self.n_rows - 1) * r + 1, n_long=self.n_long * r)

    # --- geometry --------------------------------------------------------------------------
    @functools.cached_property
    def _mesh(self):
        nodes = staggered_strip_points(self.length, self.width, self.n_rows, self.n_long)
        tri = delaunay_mesh(nodes)
        fixed = clamp_mask(nodes, 0.0, min_rows=1)
        return nodes, tri, mesh_edges(tri), fixed

    def rest_positions(self) -> np.ndarray:
        return self._mesh[0].copy()

    def mesh(self):
        """``edges (E, 2)``, ``cells (M, 3)`` (counter-clockwise from +z), ``node_type (N,)``."""
        nodes, tri, edges, fixed = self._mesh
        return edges.copy(), tri.copy(), fixed.astype(np.int64)

    def initial_state(self):
        x = self.rest_positions()
        return x, np.zeros_like(x)

    def _node_at(self, x: float, y: float) -> int:
        p = self._mesh[0]
        i = int(np.argmin(np.hypot(p[:, 0] - x, p[:, 1] - y)))
        if np.hypot(p[i, 0] - x, p[i, 1] - y) > 1e-9 * self.length:
            raise ValueError(f"{self.id}: no mesh node at ({x}, {y}) m (n_rows must be odd)")
        return i

    @property
    def tip_node(self) -> int:
        """The node at the centre of the free edge, (L, w/2)."""
        return self._node_at(self.length, 0.5 * self.width)

    @property
    def corner_node(self) -> int:
        """The bottom corner of the free edge, (L, 0): the lowest node once the strip sags."""
        return self._node_at(self.length, 0.0)

    # --- beam theory -----------------------------------------------------------------------
    def bending_rigidity(self, youngs: float) -> float:
        """EI = Y h w^3 / 12 (in-plane, strong axis), N m^2."""
        return check_youngs(youngs) * self.thickness * self.width**3 / 12.0

    def shear_rigidity(self, youngs: float) -> float:
        """kappa G A = kappa Y / (2 (1 + nu)) w h (Timoshenko, kappa = ``shear_factor``), N."""
        return self.shear_factor * check_youngs(youngs) / (2.0 * (1.0 + self.poisson)) \
            * self.width * self.thickness

    def axial_rigidity(self, youngs: float) -> float:
        """EA = Y w h, N."""
        return check_youngs(youngs) * self.width * self.thickness

    @property
    def line_load(self) -> float:
        """Weight per unit length q = rho g h w, N/m."""
        return self.density * self.gravity * self.thickness * self.width

    def load_parameter(self, youngs: float) -> float:
        """alpha = q L^3 / EI."""
        return self.line_load * self.length**3 / self.bending_rigidity(youngs)

    def timoshenko_tip(self, youngs: float) -> float:
        """Small-load tip deflection q L^4 / (8 EI) + q L^2 / (2 kappa G A), m."""
        q, L = self.line_load, self.length
        return q * L**4 / (8 * self.bending_rigidity(youngs)) \
            + q * L**2 / (2 * self.shear_rigidity(youngs))

    # --- physics ---------------------------------------------------------------------------
    def _springs(self, youngs: float) -> np.ndarray:
        nodes, tri, edges, _ = self._mesh
        return cst_spring_stiffness(nodes, tri, edges, youngs, self.thickness, self.poisson)

    def linear_tip_deflection(self, youngs: float, calibrated: bool = True) -> float:
        """Small-load static deflection (m, downward) of ``tip_node`` of the spring network,
        from its linear stiffness about the rest shape (clamp and gravity of the case)."""
        import scipy.sparse.linalg

        nodes, tri, edges, fixed = self._mesh
        k = self._springs(youngs) * (self.bending_calibration if calibrated else 1.0)
        K = inplane_stiffness(nodes, edges, k)
        mass = lumped_mass(nodes, tri, self.density, self.thickness)
        f = np.zeros((len(nodes), 2))
        f[:, 1] = -mass * self.gravity
        free = np.flatnonzero(~np.repeat(fixed, 2))
        u = np.zeros(2 * len(nodes))
        u[free] = scipy.sparse.linalg.spsolve(K[free][:, free].tocsc(), f.ravel()[free])
        return -float(u[2 * self.tip_node + 1])

    @functools.cached_property
    def bending_calibration(self) -> float:
        """Factor on every spring: the uncalibrated network's small-load tip deflection over
        Timoshenko's (``timoshenko_tip``), 1 if ``calibrate_bending`` is off. Independent of Y."""
        if not self.calibrate_bending:
            return 1.0
        y = self.reference_youngs
        return self.linear_tip_deflection(y, calibrated=False) / self.timoshenko_tip(y)

    def system(self, youngs: float) -> MechanicalSystem:
        """The in-plane DEP system for modulus ``youngs`` (Pa)."""
        Y = check_youngs(youngs)
        nodes, tri, edges, fixed = self._mesh
        l0 = np.linalg.norm(nodes[edges[:, 1]] - nodes[edges[:, 0]], axis=1)
        stretch = StretchTerm(edges, l0, self._springs(Y) * self.bending_calibration)
        hinges, tris = mesh_hinges(tri)
        le = np.linalg.norm(nodes[hinges[:, 1]] - nodes[hinges[:, 0]], axis=1)
        k_b = hinge_stiffness(Y, self.thickness, le, triangle_areas(nodes, tri)[tris].sum(axis=1))
        terms = drop_clamped([stretch, HingeTerm.from_rest(hinges, nodes, k_b)], fixed)
        mass = lumped_mass(nodes, tri, self.density, self.thickness)
        force = np.zeros((len(nodes), 3))
        force[:, 1] = -mass * self.gravity
        scale = self.line_load * self.length / len(nodes)
        # z: no load, no velocity, and on a flat mesh no coupling (the hinge angle is 0
        # exactly and its gradient normal to the plane): z stays 0, the sparse solve skips it
        resting = np.zeros((len(nodes), 3), bool)
        resting[:, 2] = True
        return MechanicalSystem(terms, mass, self.damping_rate * mass, force, fixed,
                                force_scale=scale, resting_dofs=resting.ravel())

    @property
    def solver_settings(self) -> NewtonSettings:
        return NewtonSettings(dt=self.dt, rtol=self.newton_rtol, predictor=self.newton_predictor)

    def solve_static(self, youngs: float, n_load_steps: int = 5) -> np.ndarray:
        """Static equilibrium under gravity ``(N, 3)``, m (load in ``n_load_steps`` steps)."""
        return super().solve_static(youngs, n_load_steps)
