"""The DER rod case (``rod_falling``, ``rod_cantilever``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from groundtruth.cases.base import (
    CaseBase,
    _check_choice,
    _check_ints,
    _check_nonneg,
    _check_positive,
    check_youngs,
)
from groundtruth.rod import rod_terms
from groundtruth.system import MechanicalSystem


@dataclass(frozen=True)
class RodCase(CaseBase):
    """A planar DER rod, straight along x at rest at t = 0, loaded in -y.

    ``lumping="spheres"`` is the paper's falling rod: node k is a sphere of radius
    ``R_k = node_radius_ratio * dL`` (``mid_radius`` for the middle node) with mass
    ``4/3 pi R^3 rho_metal``, weight minus buoyancy ``4/3 pi R^3 (rho_metal - rho_fluid) g`` and
    Stokes drag coefficient ``6 pi mu R``. ``lumping="line"`` gives the rod's own mass
    ``rho_metal A l_voronoi`` per node, gravity only and no fluid (cantilever checks).
    Nodes listed in ``clamped_nodes`` never move. Units SI.

    ``refined(r)`` (id ``CASE@rN``, docs/SCALE.md) has ``(n_nodes - 1) r + 1`` nodes and the
    same physics: the same clamped length of rod, and the small spheres' volumes times r^2
    (``resolution`` = r), so that mass, weight and drag per length are those of r = 1.
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
    resolution: int = 1

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
        """Sphere radii ``(N,)``, m: ``node_radius_ratio * dL``, ``mid_radius`` at the middle."""
        R = np.full(self.n_nodes, self.node_radius_ratio * self.dL)
        if self.mid_radius is not None:
            R[(self.n_nodes - 1) // 2] = self.mid_radius
        return R

    def volume_factor(self) -> np.ndarray:
        """``(N,)``: a node's volume (mass, weight, buoyancy) over its sphere's 4/3 pi R^3:
        ``resolution^2`` for the small spheres, 1 for the middle one. Their radius (so their
        drag) shrinks as 1/r with dL, their volume as 1/r^3; times r^2, r of them carry the
        volume of one sphere at r = 1, as drag per length already does (docs/SCALE.md)."""
        f = np.full(self.n_nodes, float(self.resolution**2))
        if self.mid_radius is not None:
            f[(self.n_nodes - 1) // 2] = 1.0
        return f

    def refined(self, r: int) -> RodCase:
        """This case with ``(n_nodes - 1) r + 1`` nodes, id ``CASE@rN`` (docs/SCALE.md); the
        same rod, loads, time step and clamped length; ``r = 1``: the case itself."""
        if self._check_refinable(r) == 1:
            return self
        if self.mid_radius is not None and (self.n_nodes - 1) % 2:
            raise ValueError(f"case {self.id!r} cannot be refined to resolution {r}: its "
                             f"middle sphere sits at node {(self.n_nodes - 1) // 2} of "
                             f"{self.n_nodes}, off the centre, and would move; use an odd "
                             "n_nodes")
        return self._refined_copy(r, n_nodes=(self.n_nodes - 1) * r + 1,
                                  clamped_nodes=refined_clamp(self.clamped_nodes, r))

    def initial_state(self):
        x = self.rest_positions()
        return x, np.zeros_like(x)

    # --- physics ---------------------------------------------------------------------------
    def _lumped(self):
        n, g = self.n_nodes, self.gravity
        if self.lumping == "spheres":
            R = self.node_radius()
            vol = 4.0 / 3.0 * math.pi * R**3 * self.volume_factor()
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
        v_T = (2/9)(rho_metal - rho_fluid) g sum f R^3 / (mu sum R), f = ``volume_factor``."""
        R = self.node_radius()
        return (2.0 / 9.0) * (self.rho_metal - self.rho_fluid) * self.gravity \
            * np.sum(R**3 * self.volume_factor()) / (self.viscosity * np.sum(R))


def refined_clamp(clamped_nodes, r: int) -> tuple:
    """The clamp of a rod refined r times: node i becomes node r i, and a segment whose two
    end nodes are clamped stays clamped along its length (nodes r i ... r (i + 1)), so the
    same length of rod is held: ``(0, 1)`` (one segment) becomes ``(0, 1, ..., r)``."""
    held = set(clamped_nodes)
    out = {r * i for i in held}
    for i in held & {j - 1 for j in held}:
        out.update(range(r * i, r * (i + 1) + 1))
    return tuple(sorted(out))
