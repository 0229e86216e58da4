"""What every case shares: the splits, the solver version, field checks and ``CaseBase``
(save times, modulus sampling, the hash of the parameters, simulate / solve_static)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re

import numpy as np

from groundtruth import implicit
from groundtruth.implicit import NewtonSettings

# Bump when a solver change alters the trajectories of an unchanged case: invalidates caches.
SOLVER_VERSION = 1
SPLITS = ("train", "test")

#: A derived case id ``CASE@rN``: the registered case ``CASE`` on a mesh N times finer
#: (``refined(N)``, docs/SCALE.md). ``CASE@r1`` is ``CASE`` itself.
RESOLUTION_MARK = "@r"


def check_resolution(r, where: str = "resolution") -> int:
    """A refinement factor: an int >= 1, else ``ValueError`` naming ``where`` and the value."""
    if isinstance(r, bool) or not isinstance(r, int) or r < 1:
        raise ValueError(f"{where} must be an int >= 1 (1: the case itself), got {r!r}")
    return r


def resolution_id(base_id: str, r: int) -> str:
    """The id of case ``base_id`` at resolution ``r``: ``base_id`` for 1, else ``base_id@rN``."""
    return base_id if check_resolution(r) == 1 else f"{base_id}{RESOLUTION_MARK}{r}"


def split_resolution_id(case_id: str) -> tuple[str, int]:
    """``("plate_cantilever", 8)`` for ``"plate_cantilever@r8"``, ``(case_id, 1)`` for an id
    without '@'. ``ValueError`` naming the id and the bad resolution for anything after '@'
    that is not ``rN`` with N a positive integer written without leading zeros."""
    base, at, suffix = case_id.partition("@")
    if not at:
        return case_id, 1
    text = suffix[1:] if suffix.startswith("r") else suffix
    if not suffix.startswith("r") or not re.fullmatch(r"[0-9]+", text) or int(text) < 1:
        raise ValueError(f"case id {case_id!r}: the resolution after '{RESOLUTION_MARK}' must "
                         f"be a positive integer (CASE{RESOLUTION_MARK}N, N >= 1), got {text!r}")
    if text != str(int(text)):
        raise ValueError(f"case id {case_id!r}: write the resolution without leading zeros, "
                         f"{resolution_id(base, int(text))!r}")
    return base, int(text)


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
        name = type(self).__name__
        if not isinstance(self.id, str):
            raise ValueError(f"{name}.id must be a snake_case identifier, got {self.id!r}")
        base, r = split_resolution_id(self.id)
        if not base.replace("_", "").isalnum():
            raise ValueError(f"{name}.id must be a snake_case identifier (with '@rN' for a "
                             f"refined case), got {self.id!r}")
        _check_ints(self, resolution=1)
        if self.id != resolution_id(base, self.resolution):
            raise ValueError(f"{name}.id {self.id!r} does not match resolution="
                             f"{self.resolution!r}: a case at resolution N > 1 has the id "
                             f"CASE{RESOLUTION_MARK}N, one at 1 no suffix (make it with "
                             "refined(N))")
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

    #: How many times finer than the registered case the mesh is (``refined``); a field of
    #: the cases that can be refined, this default for the others.
    resolution = 1

    def _check_refinable(self, r) -> int:
        """``r`` checked for ``refined(r)``; only a case at resolution 1 is refined."""
        r = check_resolution(r, f"{type(self).__name__}.refined: the resolution r")
        if r > 1 and self.resolution != 1:
            base = split_resolution_id(self.id)[0]
            raise ValueError(f"case {self.id!r} is already refined (resolution "
                             f"{self.resolution}); refine its base case instead: "
                             f"{resolution_id(base, self.resolution * r)!r}")
        return r

    def _refined_copy(self, r: int, **fields):
        """``dataclasses.replace`` with the id ``CASE@rN``, ``resolution = r`` and ``fields``."""
        return dataclasses.replace(self, id=resolution_id(self.id, r), resolution=r, **fields)

    def to_dict(self) -> dict:
        """The parameters, ``kind`` added; ``resolution`` only where it is not 1, so that a
        case at resolution 1 has the dict (and hash) it had before resolutions existed."""
        d = dataclasses.asdict(self)
        if d.get("resolution") == 1:
            del d["resolution"]
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
