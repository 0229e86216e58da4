"""Registries keyed by stable snake_case ids; the ids are exactly the strings in CSV columns."""

from __future__ import annotations

import re

from groundtruth.cases import InPlanePlateCase, PlateCase, RodCase, split_resolution_id
from meshbench_registry import RegistryError, lookup

__all__ = ["CASES", "RegistryError", "get_case", "lookup", "register_case", "safe_id"]

CASES: dict = {
    "rod_falling": RodCase(),
    # Check case for `meshbench crosscheck`: the rod's own section and mass (no spheres, no
    # fluid), clamped by its first two nodes, released from straight under gravity. At the
    # reference Y = 0.2 GPa, q L^3/EI = 1.37 and the first period is 0.2 s: 5 oscillations.
    # dt = 1 ms so that backward Euler (omega dt = 0.03) lets them be seen; the DER Newton is
    # tightened so that its tolerance is far below the cross-check's differences.
    "rod_cantilever": RodCase(
        id="rod_cantilever", lumping="line", mid_radius=None, rho_fluid=0.0, viscosity=0.0,
        clamped_nodes=(0, 1), t_end=1.0, save_dt=0.01, dt=1e-3, newton_rtol=1e-6,
        youngs_train=(0.1e9, 0.3e9), youngs_test=(0.12e9, 0.28e9), n_train=4, n_test=2,
        seed_train=4_000, seed_test=2_000),
    # The paper's case study 2 as its authors ran it: a strip sagging in its own plane
    # (docs/PLATE.md, README "Why case 2 is in-plane").
    "plate_cantilever": InPlanePlateCase(),
    # The sub-domain suite's plate (docs/SUBDOMAIN.md, "The subdomain suite"): the paper's
    # strip with 6 training trajectories instead of 30, refined to r = 8 (9,289 nodes) where a
    # trajectory costs about 2 minutes of one core. Its training seed is the first from
    # 30,000 whose 6 moduli span the range (lowest <= 3.0 MPa, highest >= 7.0 MPa, no gap
    # over 1.5 MPa: 2.84-7.07 MPa; seed 30,000's six left 5.6-7.5 MPa uncovered). Its test
    # split (seed, moduli, length) is plate_cantilever's, so a model trained on the paper's
    # mesh and transferred is rolled out on the same trajectories.
    "plate_cantilever_few": InPlanePlateCase(id="plate_cantilever_few", n_train=6,
                                             seed_train=30_040),
    # The paper's text read literally: gravity through the thickness, a heavy swinging chain.
    "plate_hanging": PlateCase(),
}


#: An id that names a file or directory (case, model, preset, suite, run tag, ...): letters,
#: digits, '_', '.', '-', '@' (a refined case, ``CASE@rN``); not starting with '.' or '@',
#: so never '..' or a hidden file; no path separator.
SAFE_ID = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.@-]*")


def safe_id(value, field: str) -> str:
    """``value`` if it is a non-empty ``SAFE_ID``, else ``ValueError`` naming ``field``: ids
    become directory and file names under the data, runs and results directories, and one
    with a path separator or '..' could write outside them."""
    if not isinstance(value, str) or not SAFE_ID.fullmatch(value):
        raise ValueError(f"{field} must be an id of letters, digits, '_', '.', '-' and '@' that "
                         f"does not start with '.' or '@' (it names a directory), got {value!r}")
    return value


#: Refined cases built by ``get_case``: ``(base id, r) -> (base case, refined case)``; an entry
#: whose base case is no longer the registered one (``register_case(..., overwrite=True)``) is
#: rebuilt.
_REFINED: dict = {}


def get_case(case_id: str):
    """The registered case ``case_id``, or for ``CASE@rN`` the case ``CASE`` refined N times
    (``CASE.refined(N)``, built once and cached; ``CASE@r1`` is ``CASE``; docs/SCALE.md).
    ``RegistryError`` for an unknown ``CASE``, ``ValueError`` for a bad N or a case that
    cannot be refined."""
    if not isinstance(case_id, str) or "@" not in case_id:
        return lookup(CASES, case_id, "case")
    base_id, r = split_resolution_id(case_id)
    base = lookup(CASES, base_id, "case")
    if r == 1:
        return base
    hit = _REFINED.get((base_id, r))
    if hit is None or hit[0] is not base:
        if not callable(getattr(base, "refined", None)):
            raise ValueError(f"case {base_id!r} cannot be refined ({case_id!r} asks for "
                             f"resolution {r}): its class {type(base).__name__} defines no "
                             "refined(r) method (docs/SCALE.md)")
        hit = _REFINED[(base_id, r)] = (base, base.refined(r))
    return hit[1]


def register_case(case, overwrite: bool = False):
    """Add a case object (with an ``id``, a ``safe_id`` without '@') to ``CASES``; refuses to
    replace one silently."""
    safe_id(getattr(case, "id", None), "case id")
    if "@" in case.id:
        raise ValueError(f"case id {case.id!r}: '@' marks a derived id (CASE@rN, made by "
                         "get_case from the registered CASE); register the base case")
    if case.id in CASES and not overwrite:
        raise ValueError(f"case id {case.id!r} is already registered; pass overwrite=True")
    CASES[case.id] = case
    return case


# The torch side's registries, re-exported without importing torch until first used, so that
# data commands (generate, simulate, export) run where torch is not installed.
_TORCH_SIDE = {"MODELS": "meshodenet.registry", "INTEGRATORS": "meshodenet.integrators.explicit"}


def __getattr__(name: str):
    if name in _TORCH_SIDE:
        import importlib

        return getattr(importlib.import_module(_TORCH_SIDE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
