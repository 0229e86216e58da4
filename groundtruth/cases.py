"""Cases: frozen dataclasses that say what to simulate and how to sample the datasets.

A case builds a ``MechanicalSystem`` for a Young's modulus, knows its mesh, rest shape, save
times and solver settings, samples the moduli of its train/test splits from fixed seeds, and
has a stable hash of everything that determines its data. Cases are registered by id in
``benchmarks.suite.registry.CASES``; variants are made with ``dataclasses.replace``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
from dataclasses import dataclass

import numpy as np

from groundtruth import implicit
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
from groundtruth.rod import rod_terms
from groundtruth.stretch import StretchTerm
from groundtruth.system import MechanicalSystem

# Bump when a solver change alters the trajectories of an unchanged case: invalidates caches.
SOLVER_VERSION = 1
SPLITS = ("train", "test")


def _check_positive(obj, *names):
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ValueError(f"{type(obj).__name__}.{name} must be a positive finite number, "
                             f"got {v!r}")


def _check_nonneg(obj, *names):
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{type(obj).__name__}.{name} must be a finite number >= 0, got {v!r}")


def _check_ints(obj, **lows):
    """Each ``name=low``: ``obj.name`` must be an int >= low."""
    for name, low in lows.items():
        n = getattr(obj, name)
        if isinstance(n, bool) or not isinstance(n, int) or n < low:
            raise ValueError(f"{type(obj).__name__}.{name} must be an int >= {low}, got {n!r}")


def _check_choice(obj, name, choices):
    v = getattr(obj, name)
    if v not in choices:
        raise ValueError(f"{type(obj).__name__}.{name} must be one of {tuple(choices)}, got {v!r}")


def _check_range(obj, name):
    v = getattr(obj, name)
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{type(obj).__name__}.{name} must be a (low, high) pair, got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"{type(obj).__name__}.{name} must satisfy 0 < low <= high, got {v!r}")


def check_youngs(youngs) -> float:
    """Validate a Young's modulus (Pa) and return it as a float."""
    try:
        y = float(youngs)
    except (TypeError, ValueError):
        raise ValueError(f"youngs must be a number in Pa, got {youngs!r}") from None
    if not math.isfinite(y) or y <= 0:
        raise ValueError(f"youngs must be a positive finite modulus in Pa, got {youngs!r}")
    return y


class CaseBase:
    """Behaviour shared by all cases. Subclasses are frozen dataclasses that define
    ``id``, ``t_end``, ``save_dt``, ``dt``, ``newton_rtol``, ``youngs_train``, ``youngs_test``,
    ``n_train``, ``n_test``, ``seed_train``, ``seed_test`` and the methods ``rest_positions``,
    ``mesh``, ``system`` and ``initial_state``."""

    kind = "base"

    def _check_common(self):
        if not isinstance(self.id, str) or not self.id.replace("_", "").isalnum() or not self.id:
            raise ValueError(f"{type(self).__name__}.id must be a snake_case identifier, "
                             f"got {self.id!r}")
        _check_positive(self, "t_end", "save_dt", "dt", "newton_rtol")
        if self.dt > self.save_dt * (1 + 1e-9):
            raise ValueError(f"{type(self).__name__}.dt ({self.dt!r}) must not exceed "
                             f"save_dt ({self.save_dt!r})")
        n_frames = self.t_end / self.save_dt
        if abs(n_frames - round(n_frames)) > 1e-6:
            raise ValueError(f"{type(self).__name__}.t_end ({self.t_end!r}) must be a multiple "
                             f"of save_dt ({self.save_dt!r})")
        for split in SPLITS:
            _check_range(self, f"youngs_{split}")
            object.__setattr__(self, f"youngs_{split}",
                               tuple(float(x) for x in getattr(self, f"youngs_{split}")))
            _check_ints(self, **{f"n_{split}": 0})

    # --- time, sampling, provenance -------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return int(round(self.t_end / self.save_dt)) + 1

    def t_save(self, t_end: float | None = None) -> np.ndarray:
        """Saved times ``(T,)`` from 0 to ``t_end`` (default the case's) every ``save_dt``."""
        t_end = self.t_end if t_end is None else t_end
        n = int(round(t_end / self.save_dt))
        return np.arange(n + 1) * self.save_dt

    def sample_youngs(self, split: str) -> np.ndarray:
        """Moduli ``(n_split,)`` in Pa, uniform on the split's range, from the split's seed."""
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        lo, hi = getattr(self, f"youngs_{split}")
        rng = np.random.default_rng(getattr(self, f"seed_{split}"))
        return rng.uniform(lo, hi, size=getattr(self, f"n_{split}"))

    @property
    def solver_settings(self) -> NewtonSettings:
        return NewtonSettings(dt=self.dt, rtol=self.newton_rtol)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["kind"] = self.kind
        return d

    def hash(self) -> str:
        """sha256 of the resolved parameters, the kind and ``SOLVER_VERSION``."""
        payload = json.dumps({"case": self.to_dict(), "solver_version": SOLVER_VERSION},
                             sort_keys=True, default=str)
        return hashlib.sha256(payload.encode()).hexdigest()

    # --- running ---------------------------------------------------------------------------
    def node_type(self) -> np.ndarray:
        return self.mesh()[2]

    def simulate(self, youngs: float, t_end: float | None = None, progress=None) -> dict:
        """One trajectory. Returns ``t (T,)``, ``pos, vel (T, N, 3)`` and solver statistics."""
        system = self.system(youngs)
        q0, v0 = self.initial_state()
        t = self.t_save(t_end)
        pos, vel, stats = implicit.simulate(system, q0.ravel(), v0.ravel(), t,
                                            self.solver_settings, progress)
        n = q0.shape[0]
        return {"t": t, "pos": pos.reshape(-1, n, 3), "vel": vel.reshape(-1, n, 3),
                "stats": dataclasses.asdict(stats)}

    def solve_static(self, youngs: float, n_load_steps: int = 10) -> np.ndarray:
        """Static equilibrium under the case's constant load, ``(N, 3)``."""
        system = self.system(youngs)
        q0, _ = self.initial_state()
        q = implicit.solve_static(system, q0.ravel(), self.solver_settings, n_load_steps)
        return q.reshape(-1, 3)

    def loads(self) -> dict:
        """``mass (N,)``, ``force (N, 3)``, ``damping (N,)`` as stored with the data."""
        s = self.system(self.reference_youngs)
        return {"mass": s.mass.copy(), "force": s.force.copy(), "damping": s.damping.copy()}

    @property
    def reference_youngs(self) -> float:
        lo, hi = self.youngs_train
        return 0.5 * (lo + hi)


@dataclass(frozen=True)
class RodCase(CaseBase):
    """A planar DER rod, straight along x at rest at t = 0, loaded in -y.

    ``lumping="spheres"`` is the paper's falling rod: node k is a sphere of radius
    ``R_k = node_radius_ratio * dL`` (``mid_radius`` for the middle node) with mass
    ``4/3 pi R^3 rho_metal``, weight minus buoyancy ``4/3 pi R^3 (rho_metal - rho_fluid) g`` and
    Stokes drag coefficient ``6 pi mu R``. ``lumping="line"`` gives the rod's own mass
    ``rho_metal A l_voronoi`` per node, gravity only and no fluid (cantilever checks).
    Nodes listed in ``clamped_nodes`` never move. Units SI.
    """

    id: str = "rod_falling"
    n_nodes: int = 21
    length: float = 0.10
    r0: float = 1e-3
    node_radius_ratio: float = 0.1
    mid_radius: float | None = 0.025
    rho_metal: float = 7000.0
    rho_fluid: float = 1000.0
    viscosity: float = 1000.0
    gravity: float = 9.81
    lumping: str = "spheres"
    clamped_nodes: tuple = ()
    t_end: float = 20.0
    save_dt: float = 0.1
    dt: float = 0.01
    newton_rtol: float = 1e-6
    youngs_train: tuple = (0.1e9, 1.5e9)
    youngs_test: tuple = (0.13e9, 1.43e9)
    n_train: int = 71
    n_test: int = 14
    seed_train: int = 71_000
    seed_test: int = 14_000

    kind = "rod"

    def __post_init__(self):
        _check_ints(self, n_nodes=3)
        _check_positive(self, "length", "r0", "node_radius_ratio", "rho_metal", "gravity")
        if self.mid_radius is not None:
            _check_positive(self, "mid_radius")
        _check_nonneg(self, "rho_fluid", "viscosity")
        _check_choice(self, "lumping", ("spheres", "line"))
        bad = [i for i in self.clamped_nodes if not (isinstance(i, int) and 0 <= i < self.n_nodes)]
        if bad:
            raise ValueError(f"RodCase.clamped_nodes must be node indices in [0, {self.n_nodes}), "
                             f"got {self.clamped_nodes!r}")
        object.__setattr__(self, "clamped_nodes", tuple(sorted(set(self.clamped_nodes))))
        self._check_common()

    # --- geometry and section ----------------------------------------------------------------
    @property
    def dL(self) -> float:
        return self.length / (self.n_nodes - 1)

    @property
    def area(self) -> float:
        return math.pi * self.r0**2

    @property
    def inertia(self) -> float:
        return math.pi * self.r0**4 / 4

    def rest_positions(self) -> np.ndarray:
        x = np.zeros((self.n_nodes, 3))
        x[:, 0] = np.linspace(0.0, self.length, self.n_nodes)
        return x

    def mesh(self):
        """``edges (N-1, 2)``, ``cells (0, 3)``, ``node_type (N,)``."""
        n = self.n_nodes
        edges = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1).astype(np.int64)
        node_type = np.zeros(n, np.int64)
        node_type[list(self.clamped_nodes)] = 1
        return edges, np.zeros((0, 3), np.int64), node_type

    def node_radius(self) -> np.ndarray:
        R = np.full(self.n_nodes, self.node_radius_ratio * self.dL)
        if self.mid_radius is not None:
            R[(self.n_nodes - 1) // 2] = self.mid_radius
        return R

    def initial_state(self):
        x = self.rest_positions()
        return x, np.zeros_like(x)

    # --- physics ---------------------------------------------------------------------------
    def _lumped(self):
        n, g = self.n_nodes, self.gravity
        if self.lumping == "spheres":
            R = self.node_radius()
            vol = 4.0 / 3.0 * math.pi * R**3
            mass = vol * self.rho_metal
            weight = -vol * (self.rho_metal - self.rho_fluid) * g
            drag = 6.0 * math.pi * self.viscosity * R
        else:
            lv = np.full(n, self.dL)
            lv[[0, -1]] = self.dL / 2
            mass = self.rho_metal * self.area * lv
            weight = -mass * g
            drag = np.zeros(n)
        force = np.zeros((n, 3))
        force[:, 1] = weight
        return mass, force, drag

    def system(self, youngs: float) -> MechanicalSystem:
        """The DER system for modulus ``youngs`` (Pa): EA = Y pi r0^2, EI = Y pi r0^4 / 4."""
        Y = check_youngs(youngs)
        EA, EI = Y * self.area, Y * self.inertia
        mass, force, drag = self._lumped()
        fixed = self.mesh()[2] == 1
        # Newton tolerance scale: the mean nodal load. (EI/L^2, the DER course's scale, is
        # larger than the weight of the small spheres and would leave them unconverged.)
        scale = float(np.mean(np.linalg.norm(force, axis=1))) or EI / self.length**2
        return MechanicalSystem(rod_terms(self.rest_positions(), EA, EI), mass, drag, force,
                                fixed, force_scale=scale)

    # --- exact anchors ---------------------------------------------------------------------
    def terminal_velocity(self) -> float:
        """Rigid terminal speed (m/s, downward) of the free rod in Stokes flow, any Y:
        v_T = (2/9)(rho_metal - rho_fluid) g sum R^3 / (mu sum R)."""
        R = self.node_radius()
        return (2.0 / 9.0) * (self.rho_metal - self.rho_fluid) * self.gravity \
            * np.sum(R**3) / (self.viscosity * np.sum(R))


@dataclass(frozen=True)
class PlateCase(CaseBase):
    """A Discrete Elastic Plates cantilever falling under gravity *through its thickness*: the
    paper's text read literally (registered as ``plate_hanging``; the paper's own case study 2
    is ``InPlanePlateCase``, registered as ``plate_cantilever``).

    The plate lies flat in the x-y plane at t = 0, ``|y| <= width / 2``, gravity along -z, one
    short edge clamped, the rest free. Units SI.

    Clamp and free length: a hinge model has no rotational dofs, so the clamp holds the last
    clamped *segment* flat, i.e. it imposes zero slope at that segment's midpoint. The clamp line
    x = 0 is therefore placed midway between the last two clamped rows, which sit at
    ``x = -clamp_gap / 2`` and ``+clamp_gap / 2`` (further clamped rows every ``clamp_gap``
    behind), and the free (cantilever) length is exactly ``length``, from x = 0 to the tip
    row at x = length. Measured from the last clamped row instead it is
    ``length - clamp_gap / 2`` (0.5 mm shorter by default).

    Mesh (``groundtruth.mesh.strip_mesh``): ``n_width`` intervals across (nodes numbered across
    the width first, so the band solver is used) and ``n_length`` row intervals along the free
    length, ``grading`` times finer at the clamp (2 mm by default) and relaxing to uniform
    (2.3 cm) over ``grading_layer`` (m): the static bending boundary layer at the clamp is
    sqrt(EI / (q L)) = 4-7 mm over the dataset's moduli, while the swinging dynamics need the
    rest of the strip resolved uniformly. Cells are cut by ``pattern`` diagonals. Defaults give
    3 x 50 = 150 nodes. Measured (docs/PLATE.md): static tip within 0.6 mm of the elastica
    (besides the physical stretch), dynamic tip trajectory within 0.5 cm rms (1.6 cm max) of a
    4x finer mesh.

    Time step: ``dt`` = 0.75 ms (4 backward-Euler steps per saved frame). Backward Euler is first
    order; against dt = 0.25 ms the tip trajectory differs by 1.1 cm rms (3.4 cm max) and all
    nodes by 0.55 cm rms, while the whole modulus range moves the tip by 2.2 cm rms; at the
    saving interval (3 ms) the difference would be 3.5 cm rms (docs/PLATE.md).

    Physics (``groundtruth.plate``): edge springs k_s = max((sqrt 3 / 2) Y h l0, Y h (A_A + A_B)
    / l0) (``spring_weights="area"``; ``"uniform"`` is the plain DEP constant), hinges
    k_b = D |e|^2 / (A_A + A_B) with D = Y h^3 / 12, times ``diagonal_stiffening`` on the cell
    diagonals; lumped mass rho A h / 3 per triangle corner; gravity -m g z; mass-proportional
    damping ``-c m v`` with ``c = damping_rate``. Why each calibration: see
    ``groundtruth.hinge.hinge_stiffness``, ``groundtruth.plate.spring_stiffness`` and
    ``diagonal_stiffening`` below.

    Attributes (beyond the common ones of ``CaseBase``):
        diagonal_stiffening: factor on the hinges of the cell diagonals. Right-triangle meshes
            couple bending to twist (a row hinge sees slopes sampled dy apart), which lets a
            strip of skinny cells bend too easily; stiff diagonals keep each cell nearly
            planar and remove that. Measured on the default mesh (small load): EI_eff / EI =
            0.935 with factor 1, 0.994 with 100, 0.9988 with 1000 (the uniform DEP hinge
            constant without any calibration: 0.34).
        damping_rate: c in 1/s. 0.5 gives the first hanging-chain mode
            (omega_1 = 1.2024 sqrt(g / L) = 3.77 rad/s) a damping ratio c / (2 omega_1) = 6.6 %:
            the amplitude decays by exp(-c t / 2) = 0.69 over the 1.5 s window, so the plate
            swings through to the far side (tip at x ~ -0.8 m) and back rather than creeping.
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
    """The paper's case study 2 as its authors ran it: a DEP strip sagging in its own plane.

    The strip ``[0, length] x [0, width]`` lies in the x-y plane (z = 0), every node on the
    short edge x = 0 is clamped, gravity acts in -y (in the plane), so the strip bends about
    its strong axis like a deep 2-D cantilever (EI = Y h w^3 / 12). Units SI.

    Mesh: ``scipy.spatial.Delaunay`` of a staggered point set (``groundtruth.mesh.
    staggered_strip_points``): ``n_rows`` node rows across, ``n_long`` intervals along the
    boundary rows (spacing L / n_long), interior odd rows staggered by half a spacing. Defaults
    5 x 35 give 182 nodes and near-equilateral triangles (dx = 28.6 mm, dy = 25 mm; equilateral
    would be 28.9 mm), close to the authors' unstructured 155-node mesh (5 rows, L/30, whose
    triangles are 33 x 25 mm): on equilateral triangles the per-triangle springs reproduce the
    constant-strain element exactly. Why Delaunay of a staggered set: it is the triangulation
    of maximal minimum angle of the points, deterministic, no mesher dependency, and the
    staggered rows give the authors' layout (rows across, offset interior rows).

    Physics (``groundtruth.plate``, ``groundtruth.hinge``): edge springs calibrated per
    triangle from its constant-strain plane-stress stiffness with ``poisson``
    (``cst_spring_stiffness``), then all multiplied by the mesh's bending calibration factor
    (``bending_calibration``): linear triangles with few rows across are too stiff in in-plane
    bending (shear locking: the network deflects 0.88 of beam theory at 5 rows), so the springs
    are softened by the ratio of the network's small-load static tip deflection to Timoshenko
    beam theory (measured on this mesh, a few ms). Hinges k_b = D |e|^2 / (A_A + A_B) (flat,
    idle in plane);
    lumped mass rho A h / 3 per triangle corner; gravity -m g y; mass-proportional damping
    ``-c m v`` with c = ``damping_rate`` (fitted to the authors' curve, docs/PLATE.md).

    The truth stays a 3-D DEP: positions are (N, 3) with z = 0 throughout (forces have no
    z-component on a flat strip). Physically such a strip would buckle sideways (lateral-
    torsional buckling load ~ 1e-3 of its weight); like the authors' data, it is kept planar.
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
        return MechanicalSystem(terms, mass, self.damping_rate * mass, force, fixed,
                                force_scale=scale)

    @property
    def solver_settings(self) -> NewtonSettings:
        return NewtonSettings(dt=self.dt, rtol=self.newton_rtol, predictor=self.newton_predictor)

    def solve_static(self, youngs: float, n_load_steps: int = 5) -> np.ndarray:
        """Static equilibrium under gravity ``(N, 3)``, m (load in ``n_load_steps`` steps)."""
        return super().solve_static(youngs, n_load_steps)
