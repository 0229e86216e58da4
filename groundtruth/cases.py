"""Cases: frozen dataclasses that say what to simulate and how to sample the datasets.

A case builds a ``MechanicalSystem`` for a Young's modulus, knows its mesh, rest shape, save
times and solver settings, samples the moduli of its train/test splits from fixed seeds, and
has a stable hash of everything that determines its data. Cases are registered by id in
``benchmarks.registry.CASES``; variants are made with ``dataclasses.replace``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass

import numpy as np

from groundtruth import implicit
from groundtruth.implicit import NewtonSettings
from groundtruth.rod import rod_terms
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
            n = getattr(self, f"n_{split}")
            if isinstance(n, bool) or not isinstance(n, int) or n < 0:
                raise ValueError(f"{type(self).__name__}.n_{split} must be an int >= 0, got {n!r}")

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
        if isinstance(self.n_nodes, bool) or not isinstance(self.n_nodes, int) or self.n_nodes < 3:
            raise ValueError(f"RodCase.n_nodes must be an int >= 3, got {self.n_nodes!r}")
        _check_positive(self, "length", "r0", "node_radius_ratio", "rho_metal", "gravity")
        if self.mid_radius is not None:
            _check_positive(self, "mid_radius")
        for name in ("rho_fluid", "viscosity"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"RodCase.{name} must be a finite number >= 0, got {v!r}")
        if self.lumping not in ("spheres", "line"):
            raise ValueError(f"RodCase.lumping must be 'spheres' or 'line', got {self.lumping!r}")
        bad = [i for i in self.clamped_nodes if not (isinstance(i, int) and 0 <= i < self.n_nodes)]
        if bad:
            raise ValueError(f"RodCase.clamped_nodes must be node indices in [0, {self.n_nodes}), "
                             f"got {self.clamped_nodes!r}")
        object.__setattr__(self, "clamped_nodes", tuple(sorted(set(self.clamped_nodes))))
        object.__setattr__(self, "youngs_train", tuple(float(x) for x in self.youngs_train))
        object.__setattr__(self, "youngs_test", tuple(float(x) for x in self.youngs_test))
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
