"""Cross-check of the ground-truth solvers (DER, DEP) against the scikit-fem continuum.

A cross-check runs the same mechanical problem twice: the *reference side* (the DER or DEP
solver of a case) and the *FEM side* (``groundtruth.fem``, total-Lagrangian St. Venant–Kirchhoff
on the same free length, cross-section, material, load and time step). Both sides return a
``SideResult``: the tip displacement over time and the positions of material points of the
centreline. The comparison reports

    l2_rel        = ||tip_ref - tip_fem||_2 / ||tip_fem||_2     over all saved frames and both
                    displacement components (a relative L2 difference of the tip trajectory);
    max_shape_m   = max over frames and centreline points of |x_ref - x_fem| (m);
    max_shape_rel = max_shape_m / max over frames |tip_fem|.

Cross-checks are registered by case id in ``CROSSCHECKS``. A check is a list of
``Resolution`` rows (the first one is the default) and two callables: ``der_side`` /
``rod_fem_side`` for ``rod_cantilever``, ``dep_side`` / ``plate_strip_crosscheck``'s FEM strip for
``plate_strip`` (the through-thickness ``plate_hanging``), ``inplane_dep_side`` /
``inplane_fem_side`` for ``plate_cantilever`` (the in-plane plate, dynamic and static).
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from groundtruth.implicit import NewtonSettings

RESULTS_DIR = Path("results") / "crosscheck"


@dataclass(frozen=True)
class Resolution:
    """One row of a cross-check study.

    Attributes:
        variant: ``"default"``, ``"refine"`` (the refinement series with the default), or a
            named variant such as ``"fem_newmark"``.
        ref_nodes: DER nodes along the rod (DEP: a mesh-size parameter of the plate side).
        fem_nx, fem_ny: FEM elements along the length and through the height.
        integrator: FEM time integrator (``groundtruth.fem.INTEGRATORS``).
        poisson: Poisson ratio of the FEM material.
        dt_scale: both sides' time step relative to the case's.
        static: compare static equilibria (frames: rest, equilibrium) instead of trajectories.
    """

    variant: str
    ref_nodes: int
    fem_nx: int
    fem_ny: int = 1
    integrator: str = "backward_euler"
    poisson: float = 0.0
    dt_scale: float = 1.0
    static: bool = False


@dataclass
class SideResult:
    """One solver's answer.

    Attributes:
        t: saved times ``(T,)``, s.
        tip: tip displacement ``(T, 2)`` (x, y), m.
        points: reference x-coordinates of compared centreline points ``(n,)``, m.
        shape: their positions ``(T, n, 2)``, m.
        wall_s: wall time of the solve, s.
        info: solver statistics.
    """

    t: np.ndarray
    tip: np.ndarray
    points: np.ndarray
    shape: np.ndarray
    wall_s: float
    info: dict = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class CrossCheck:
    """A registered cross-check: ``reference(res) -> SideResult`` and
    ``fem(res, points) -> SideResult`` (``points`` are the reference side's centreline points,
    to be probed on the FEM side), the resolutions (first = default) and the target
    ``l2_rel`` at the default resolution."""

    case_id: str
    youngs: float
    reference: Callable[[Resolution], SideResult]
    fem: Callable[[Resolution, np.ndarray], SideResult]
    resolutions: tuple
    target_l2: float
    config: dict = dataclasses.field(default_factory=dict)

    @property
    def default(self) -> Resolution:
        return self.resolutions[0]


# --- metrics -------------------------------------------------------------------------------


def l2_rel(tip_ref: np.ndarray, tip_fem: np.ndarray) -> float:
    """``||tip_ref - tip_fem|| / ||tip_fem||`` over all frames and components."""
    return float(np.linalg.norm(tip_ref - tip_fem) / np.linalg.norm(tip_fem))


def max_shape_diff(shape_ref: np.ndarray, shape_fem: np.ndarray) -> float:
    """Largest distance (m) between the same material point in both solvers, any frame."""
    return float(np.max(np.linalg.norm(shape_ref - shape_fem, axis=-1)))


def compare(ref: SideResult, fem: SideResult) -> dict:
    if ref.t.shape != fem.t.shape or not np.allclose(ref.t, fem.t, rtol=0, atol=1e-9):
        raise ValueError("cross-check sides saved different times: "
                         f"{ref.t.shape} vs {fem.t.shape}")
    scale = float(np.max(np.linalg.norm(fem.tip, axis=1)))
    d = max_shape_diff(ref.shape, fem.shape)
    return {"l2_rel": l2_rel(ref.tip, fem.tip), "max_shape_m": d, "max_shape_rel": d / scale}


# --- the rod: DER vs FEM -------------------------------------------------------------------


def der_clamp_position(case) -> float:
    """Where the DER clamp acts (m): the midpoint of the last clamped edge.

    With nodes ``0..k`` fixed, node k's bending term is the first that can bend; it covers the
    Voronoi cell ``[x_k - dL/2, x_k + dL/2]`` and the moments at the nodes are exact (trapezoid
    loads), so the discrete rod is a midpoint-rule Euler–Bernoulli cantilever clamped at
    ``x_k - dL/2``. Measured (tests/test_crosscheck.py): the static small-load tip deflection
    gives x_c/dL = 0.513, 0.506, 0.503, 0.502 for N = 11, 21, 41, 81.
    """
    clamped = list(case.clamped_nodes)
    if len(clamped) < 2 or clamped != list(range(len(clamped))):
        raise ValueError(f"{case.id}: a DER clamp needs nodes 0..k (k >= 1) fixed, got "
                         f"clamped_nodes={case.clamped_nodes!r}")
    return (clamped[-1] - 0.5) * case.dL


def _resolved(case, res: Resolution):
    return dataclasses.replace(case, n_nodes=res.ref_nodes, dt=case.dt * res.dt_scale)


def der_side(case, youngs: float) -> Callable[[Resolution], SideResult]:
    """The DER rod of ``case`` with ``ref_nodes`` nodes (the clamp keeps its node indices)."""

    def run(res: Resolution) -> SideResult:
        c = _resolved(case, res)
        t0 = time.perf_counter()
        sim = c.simulate(youngs)
        wall = time.perf_counter() - t0
        pos = sim["pos"][..., :2]
        x = c.rest_positions()[:, 0]
        sel = x >= der_clamp_position(c) - 1e-12
        return SideResult(sim["t"], pos[:, -1] - pos[0, -1], x[sel], pos[:, sel], wall,
                          sim["stats"])

    return run


def rod_fem_side(case, youngs: float, rtol: float = 1e-8) -> Callable:
    """The FEM twin of a clamped DER rod: rectangle of height sqrt3 r0 and thickness
    pi r0/sqrt3 (the rod's A and I) from the DER's effective clamp to the tip, same density,
    gravity and time step (``case.dt``)."""
    from groundtruth import fem

    def run(res: Resolution, points: np.ndarray) -> SideResult:
        c = _resolved(case, res)
        x_c = der_clamp_position(c)
        height, thick = fem.rod_section(c.r0)
        mat = fem.Material(youngs, res.poisson, c.rho_metal, thick, "plane_stress")
        model = fem.cantilever(c.length - x_c, height, mat, res.fem_nx, res.fem_ny, x0=x_c,
                               gravity=c.gravity)
        t0 = time.perf_counter()
        u, _, stats = fem.simulate(model, c.t_save(), NewtonSettings(dt=c.dt, rtol=rtol),
                                   res.integrator)
        wall = time.perf_counter() - t0
        return fem_result(model, c.t_save(), u, points, wall, dataclasses.asdict(stats))

    return run


def fem_result(model, t, u, points, wall, info) -> SideResult:
    """Tip displacement and centreline positions (mid-height) of an FEM run."""
    from groundtruth import fem

    tip_ref = fem.tip_point(model)
    tip = model.positions(u, tip_ref)[:, 0] - tip_ref[:, 0]
    y_mid = float(tip_ref[1, 0])
    pts = np.clip(np.asarray(points, float), model.mesh.p[0].min(), model.mesh.p[0].max())
    shape = model.positions(u, np.vstack([pts, np.full_like(pts, y_mid)]))
    return SideResult(np.asarray(t), tip, pts, shape, wall, info)


ROD_STUDY = (
    Resolution("default", 21, 40),
    Resolution("refine", 11, 20),
    Resolution("refine", 41, 80),
    Resolution("refine", 81, 160),
    Resolution("fem_refined", 21, 80),
    Resolution("fem_newmark", 21, 40, integrator="newmark"),
    Resolution("fem_newmark", 21, 40, integrator="newmark", dt_scale=0.25),
    Resolution("poisson_0.3", 21, 40, poisson=0.3),
)


def rod_crosscheck(case, youngs: float | None = None,
                   resolutions: Sequence[Resolution] = ROD_STUDY,
                   target_l2: float = 0.02) -> CrossCheck:
    """DER rod vs FEM rectangle for a clamped ``RodCase`` (default modulus: the case's
    reference, the middle of its training range)."""
    y = float(case.reference_youngs if youngs is None else youngs)
    der_clamp_position(case)  # validates the clamp
    return CrossCheck(case.id, y, der_side(case, y), rod_fem_side(case, y), tuple(resolutions),
                      target_l2, {"case": case.to_dict(), "dt": case.dt,
                                  "fem_section": "sqrt3 r0 x pi r0/sqrt3",
                                  "fem_model": "plane_stress", "fem_element": "ElementQuad2",
                                  "clamp": "DER: nodes 0..k fixed; FEM: edge x = x_k - dL/2"})


# --- the plate strip: DEP vs FEM ------------------------------------------------------------


def plate_study(dep_default: int, dep_coarse: int, dep_fine: int) -> tuple:
    """Default, coarse and fine DEP resolutions paired with 200, 100 and 400 FEM elements
    (graded 4:1 towards the clamp; 100 already match the elastica's tip within 1.2 mm
    at q L^3/EI = 2.8e4)."""
    nu = 1.0 / 3.0
    return (Resolution("default", dep_default, 200, poisson=nu),
            Resolution("refine", dep_coarse, 100, poisson=nu),
            Resolution("refine", dep_fine, 400, poisson=nu))


def plate_strip_crosscheck(dep_side: Callable[[Resolution], SideResult], youngs: float,
                           damping: float, t_save: np.ndarray, dt: float,
                           resolutions: Sequence[Resolution], clamp_x: float = 0.0,
                           target_l2: float = 0.05, **plate) -> CrossCheck:
    """The ``plate_strip`` cross-check (``plate_crosscheck`` builds it for a ``PlateCase``).

    ``dep_side(res)`` must run the plate case's free strip (uniform width, load uniform across
    it) at the DEP resolution ``res.ref_nodes`` and return the tip displacement ``(T, 2)``
    (longitudinal, vertical) of the free edge's midline and midline positions at ``t_save``.
    ``clamp_x`` is where the DEP clamp acts (measure it: ``references.effective_clamp``
    on a small-load static solve). ``plate`` overrides the strip's L, h, w, rho, gravity.
    """
    from groundtruth import fem

    def fem_side(res: Resolution, points: np.ndarray) -> SideResult:
        out = fem.fem_plate_strip(youngs, t_save, damping, dt=dt * res.dt_scale, clamp_x=clamp_x,
                                  nx=res.fem_nx, ny=res.fem_ny, integrator=res.integrator,
                                  **plate)
        return fem_result(out["model"], t_save, out["u"], points, out["wall_s"], out["stats"])

    return CrossCheck("plate_strip", float(youngs), dep_side, fem_side, tuple(resolutions),
                      target_l2, {"damping": damping, "dt": dt, "clamp_x": clamp_x,
                                  "fem_model": "plane_strain, nu = 1/3, E = Y (1 - nu^2)",
                                  **plate})


# Where the DEP clamp acts (m), measured (tests/test_crosscheck.py) as for the rod: small-load
# (alpha = q L^3 / EI = 0.1) static tip deflection of the plate case, fitted with
# q (L - x_c)^4 / 8 EI (``references.effective_clamp``): x_c = -0.52, -0.26, -0.22 mm for
# 24, 48 (default), 96 rows. The nominal clamp line is x = 0, midway between the two clamped
# rows (docs/PLATE.md); the fit also absorbs the mesh's small bending-stiffness deficit
# (EI_eff / EI = 0.9988 at 48 rows, worth -0.3 mm).
DEP_CLAMP_X = -2.6e-4


def dep_clamp_position(case, youngs: float | None = None, alpha: float = 0.1) -> float:
    """Measure where the DEP clamp of a ``PlateCase`` acts (m): static tip (centre of the free
    edge) deflection at the small load ``alpha = q L^3 / EI`` (the modulus is chosen to give
    it), fitted with ``q (L - x_c)^4 / (8 EI)``."""
    from groundtruth import references

    y = case.line_load * case.length**3 / (alpha * case.bending_rigidity(1.0)) \
        if youngs is None else float(youngs)
    x0 = case.rest_positions()
    tip = _dep_tip_node(x0)
    q = case.solve_static(y)
    return references.effective_clamp(-(q[tip, 2] - x0[tip, 2]), case.line_load,
                                       case.bending_rigidity(y), case.length)


def _dep_tip_node(x0: np.ndarray) -> int:
    """The node at the centre of the free edge (largest x, y = 0)."""
    i = int(np.argmin(np.hypot(x0[:, 0] - x0[:, 0].max(), x0[:, 1])))
    if abs(x0[i, 1]) > 1e-12:
        raise ValueError("the DEP mesh has no node at the centre of its free edge "
                         "(n_width must be even)")
    return i


def dep_side(case, youngs: float) -> Callable[[Resolution], SideResult]:
    """The DEP plate of ``case`` with ``ref_nodes`` row intervals along the free length
    (``n_length``), time step ``case.dt * dt_scale``. Tip: the centre of the free edge,
    displacement (x, z); centreline: the nodes at y = 0 from the clamp line on, (x, z)."""

    def run(res: Resolution) -> SideResult:
        c = dataclasses.replace(case, n_length=res.ref_nodes, dt=case.dt * res.dt_scale)
        x0 = c.rest_positions()
        tip = _dep_tip_node(x0)
        t0 = time.perf_counter()
        sim = c.simulate(youngs)
        wall = time.perf_counter() - t0
        pos = sim["pos"][..., [0, 2]]
        line = np.flatnonzero((np.abs(x0[:, 1]) < 1e-12) & (x0[:, 0] >= DEP_CLAMP_X))
        line = line[np.argsort(x0[line, 0])]
        return SideResult(sim["t"], pos[:, tip] - pos[0, tip], x0[line, 0], pos[:, line], wall,
                          sim["stats"])

    return run


# DEP rows (default, coarse, fine) of the plate_strip study, paired with 200, 100, 400 FEM
# elements (``plate_study``).
PLATE_ROWS = (48, 24, 96)


def plate_crosscheck(case, youngs: float | None = None,
                     resolutions: Sequence[Resolution] | None = None,
                     clamp_x: float = DEP_CLAMP_X) -> CrossCheck:
    """DEP plate of a ``PlateCase`` (default modulus: the middle of its training range, 5 MPa)
    vs the plane-strain FEM strip clamped at ``clamp_x``, same damping, gravity, saved times
    (``case.t_save()``) and backward Euler with the same dt."""
    y = float(case.reference_youngs if youngs is None else youngs)
    res = plate_study(*PLATE_ROWS) if resolutions is None else tuple(resolutions)
    check = plate_strip_crosscheck(
        dep_side(case, y), y, damping=case.damping_rate, t_save=case.t_save(), dt=case.dt,
        resolutions=res, clamp_x=clamp_x, length=case.length, thickness=case.thickness,
        width=case.width, density=case.density, gravity=case.gravity)
    check.config["dep_case"] = case.to_dict()
    check.config["clamp"] = ("DEP: two clamped rows at x = -/+ clamp_gap/2 (slope held at "
                             f"x = 0), measured x_c = {clamp_x} m; FEM: edge x = x_c clamped")
    return check


# --- the in-plane plate: DEP vs a plane-stress FEM rectangle ---------------------------------


def inplane_study(fem_nx: int = 60, fem_ny: int = 4) -> tuple:
    """Default (5 rows across, 157 nodes), the refinement series (3, 9, 17 rows) against the same
    FEM (``fem_nx x fem_ny`` 9-node quadrilaterals, plane stress, the case's nu), a doubly
    refined FEM, and static equilibria at 5 and 9 rows."""
    nu = 1.0 / 3.0
    return (Resolution("default", 5, fem_nx, fem_ny, poisson=nu),
            Resolution("refine", 3, fem_nx, fem_ny, poisson=nu),
            Resolution("refine", 9, fem_nx, fem_ny, poisson=nu),
            Resolution("refine", 17, fem_nx, fem_ny, poisson=nu),
            Resolution("fem_refined", 5, 2 * fem_nx, 2 * fem_ny, poisson=nu),
            Resolution("static", 3, fem_nx, fem_ny, poisson=nu, static=True),
            Resolution("static", 5, fem_nx, fem_ny, poisson=nu, static=True),
            Resolution("static", 9, fem_nx, fem_ny, poisson=nu, static=True))


def _inplane_resolved(case, res: Resolution):
    from benchmarks.validation.plate_fidelity import refined

    return dataclasses.replace(refined(case, res.ref_nodes), dt=case.dt * res.dt_scale,
                               poisson=res.poisson)


def inplane_dep_side(case, youngs: float) -> Callable[[Resolution], SideResult]:
    """The in-plane DEP plate with ``ref_nodes`` rows across. Tip: the centre of the free edge;
    centreline: the nodes of the middle row y = w/2; both (x, y) and shifted to the FEM's
    frame (y measured from the centre line)."""

    def run(res: Resolution) -> SideResult:
        c = _inplane_resolved(case, res)
        x0 = c.rest_positions()
        line = np.flatnonzero(np.abs(x0[:, 1] - 0.5 * c.width) < 1e-12)
        line = line[np.argsort(x0[line, 0])]
        t0 = time.perf_counter()
        if res.static:
            q = c.solve_static(youngs)
            t, pos, info = np.array([0.0, 1.0]), np.stack([x0, q]), {}
        else:
            sim = c.simulate(youngs)
            t, pos, info = sim["t"], sim["pos"], sim["stats"]
        wall = time.perf_counter() - t0
        pos = pos[..., :2] - np.array([0.0, 0.5 * c.width])
        tip = c.tip_node
        return SideResult(t, pos[:, tip] - pos[0, tip], x0[line, 0], pos[:, line], wall, info)

    return run


def inplane_fem_side(case, youngs: float, rtol: float = 1e-8) -> Callable:
    """The same rectangle ``[0, L] x [-w/2, w/2]`` as a plane-stress SVK continuum (E = Y,
    thickness h, the case's density, gravity and mass-proportional damping), clamped on
    x = 0, backward Euler with the case's dt (dynamic) or load-stepped Newton (static)."""
    from groundtruth import fem

    def run(res: Resolution, points: np.ndarray) -> SideResult:
        c = _inplane_resolved(case, res)
        mat = fem.Material(youngs, res.poisson, c.density, c.thickness, "plane_stress")
        model = fem.cantilever(c.length, c.width, mat, res.fem_nx, res.fem_ny,
                               gravity=c.gravity, damping=c.damping_rate)
        settings = NewtonSettings(dt=c.dt, rtol=rtol)
        t0 = time.perf_counter()
        if res.static:
            u1 = fem.solve_static(model, settings, n_load_steps=5)
            t, u, stats = np.array([0.0, 1.0]), np.stack([np.zeros_like(u1), u1]), {}
        else:
            t = c.t_save()
            u, _, st = fem.simulate(model, t, settings, res.integrator)
            stats = dataclasses.asdict(st)
        wall = time.perf_counter() - t0
        return fem_result(model, t, u, points, wall, stats)

    return run


def inplane_crosscheck(case, youngs: float | None = None,
                       resolutions: Sequence[Resolution] | None = None,
                       target_l2: float = 0.03) -> CrossCheck:
    """In-plane DEP plate (``InPlanePlateCase``; default modulus: the middle of its training
    range, 5 MPa) vs the plane-stress FEM rectangle."""
    y = float(case.reference_youngs if youngs is None else youngs)
    res = inplane_study() if resolutions is None else tuple(resolutions)
    return CrossCheck(case.id, y, inplane_dep_side(case, y), inplane_fem_side(case, y), res,
                      target_l2, {"case": case.to_dict(), "dt": case.dt,
                                  "damping_rate": case.damping_rate,
                                  "fem_model": "plane_stress, E = Y, nu = case.poisson, "
                                               "thickness h", "fem_element": "ElementQuad2",
                                  "clamp": "DEP: all nodes on x = 0; FEM: edge x = 0"})


def _plate_cantilever(youngs: float | None = None) -> CrossCheck:
    from benchmarks.suite.registry import get_case

    return inplane_crosscheck(get_case("plate_cantilever"), youngs)


def _plate_strip(youngs: float | None = None) -> CrossCheck:
    from benchmarks.suite.registry import get_case

    return plate_crosscheck(get_case("plate_hanging"), youngs)


def _rod_cantilever(youngs: float | None = None) -> CrossCheck:
    from benchmarks.suite.registry import get_case

    return rod_crosscheck(get_case("rod_cantilever"), youngs)


# Cross-checks by case id: ``builder(youngs=None) -> CrossCheck`` (None: the default modulus).
CROSSCHECKS: dict[str, Callable[..., CrossCheck]] = {
    "rod_cantilever": _rod_cantilever,
    "plate_strip": _plate_strip,
    "plate_cantilever": _plate_cantilever,
}


def get_crosscheck(case_id: str, youngs: float | None = None) -> CrossCheck:
    from benchmarks.suite.registry import lookup

    return lookup(CROSSCHECKS, case_id, "cross-check")(youngs)


# --- running and writing -------------------------------------------------------------------


SUMMARY_COLUMNS = {
    "case": "{}", "variant": "{}", "ref_nodes": "{:d}", "fem_nx": "{:d}", "fem_ny": "{:d}",
    "integrator": "{}", "poisson": "{:.4f}", "dt": "{:.3e}", "youngs": "{:.6e}",
    "l2_rel": "{:.6e}", "max_shape_m": "{:.6e}", "max_shape_rel": "{:.6e}", "ref_wall_s": "{:.2f}",
    "fem_wall_s": "{:.2f}",
}
TRAJECTORY_COLUMNS = {
    "time": "{:.6f}", "ref_tip_ux": "{:.9e}", "ref_tip_uy": "{:.9e}", "fem_tip_ux": "{:.9e}",
    "fem_tip_uy": "{:.9e}", "diff_ux": "{:.9e}", "diff_uy": "{:.9e}", "diff_norm": "{:.9e}",
}


def run_resolution(check: CrossCheck, res: Resolution) -> tuple[dict, SideResult, SideResult]:
    ref = check.reference(res)
    fe = check.fem(res, ref.points)
    row = {"case": check.case_id, "variant": res.variant, "ref_nodes": res.ref_nodes,
           "fem_nx": res.fem_nx, "fem_ny": res.fem_ny, "integrator": res.integrator,
           "poisson": res.poisson, "dt": float(check.config.get("dt", 0.0)) * res.dt_scale,
           "youngs": check.youngs, **compare(ref, fe),
           "ref_wall_s": ref.wall_s, "fem_wall_s": fe.wall_s}
    return row, ref, fe


def write_csv(path: Path, rows: list[dict], columns: dict) -> None:
    """Atomic CSV with a fixed format per column."""
    from groundtruth.store import atomic_write

    lines = [",".join(columns)]
    lines += [",".join(fmt.format(r[c]) for c, fmt in columns.items()) for r in rows]
    text = "\n".join(lines) + "\n"
    atomic_write(Path(path), lambda f: f.write(text), mode="w")


def read_summary(path: Path) -> list[dict]:
    import csv

    if not Path(path).exists():
        return []
    types = {"ref_nodes": int, "fem_nx": int, "fem_ny": int}
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if rows and set(rows[0]) != set(SUMMARY_COLUMNS):
        raise ValueError(f"{path}: columns {sorted(rows[0])} are not a cross-check summary; "
                         "move the file away and run again")
    return [{k: (v if k in ("case", "variant", "integrator") else types.get(k, float)(v))
             for k, v in r.items()} for r in rows]


def _row_key(r: dict) -> tuple:
    """A summary row's case and resolution, its floats at the precision the file keeps: a
    row read back from ``summary.csv`` (Poisson 0.3333) and the same resolution run again
    (1/3) are one row."""
    def kept(col):
        return float(SUMMARY_COLUMNS[col].format(float(r[col])))

    return (r["case"], r["variant"] != "default", r["variant"], r["ref_nodes"], r["fem_nx"],
            r["fem_ny"], r["integrator"], kept("poisson"), -kept("dt"))


def update_summary(path: Path, new_rows: list[dict]) -> list[dict]:
    """Replace rows with the same case and resolution, keep the others, sort, write."""
    keep = {_row_key(r): r for r in read_summary(path)}
    for r in new_rows:
        keep[_row_key(r)] = r
    rows = [keep[k] for k in sorted(keep)]
    write_csv(path, rows, SUMMARY_COLUMNS)
    return rows


def trajectory_rows(ref: SideResult, fe: SideResult) -> list[dict]:
    d = ref.tip - fe.tip
    return [{"time": float(t), "ref_tip_ux": a[0], "ref_tip_uy": a[1], "fem_tip_ux": b[0],
             "fem_tip_uy": b[1], "diff_ux": e[0], "diff_uy": e[1], "diff_norm": math.hypot(*e)}
            for t, a, b, e in zip(ref.t, ref.tip, fe.tip, d, strict=True)]


def plot(path: Path, check: CrossCheck, ref: SideResult, fe: SideResult, rows: list[dict]):
    """Tip trajectories of both solvers, their difference, and the refinement study."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from groundtruth.store import atomic_write

    fig, ax = plt.subplots(3, 1, figsize=(7, 9), constrained_layout=True)
    for k, name in enumerate(("x", "y")):
        ax[0].plot(ref.t, ref.tip[:, k] * 1e3, "-", label=f"reference u_{name}")
        ax[0].plot(fe.t, fe.tip[:, k] * 1e3, "--", label=f"FEM u_{name}")
        ax[1].plot(ref.t, (ref.tip[:, k] - fe.tip[:, k]) * 1e3, label=f"difference u_{name}")
    ax[0].set(ylabel="tip displacement (mm)", title=f"{check.case_id}: Y = {check.youngs:.3g} Pa")
    ax[1].set(xlabel="time (s)", ylabel="reference - FEM (mm)")
    for a in ax[:2]:
        a.legend(fontsize=8)
        a.grid(alpha=0.3)
    ref_rows = sorted((r for r in rows if r["case"] == check.case_id
                       and r["variant"] in ("default", "refine")), key=lambda r: r["fem_nx"])
    if ref_rows:
        n = [r["ref_nodes"] or r["fem_nx"] for r in ref_rows]
        ax[2].loglog(n, [r["l2_rel"] for r in ref_rows], "o-", label="relative L2 tip difference")
        ax[2].loglog(n, [r["max_shape_rel"] for r in ref_rows], "s--",
                     label="max shape difference / max tip displacement")
        ax[2].axhline(check.target_l2, color="k", lw=0.8, ls=":", label="target")
        ax[2].set(xlabel="reference nodes (FEM elements scale with them)",
                  ylabel="difference", title="refinement")
        ax[2].legend(fontsize=8)
        ax[2].grid(alpha=0.3, which="both")
    atomic_write(Path(path), lambda f: fig.savefig(f, format="png", dpi=120))
    plt.close(fig)


def run_crosscheck(check: CrossCheck, out_dir: Path = RESULTS_DIR,
                   resolutions: Sequence[Resolution] | None = None,
                   progress: Callable[[str], None] | None = None) -> list[dict]:
    """Run ``resolutions`` (default: all of the check's), write ``CASE.csv`` (default
    resolution), ``CASE.png``, ``CASE.json`` and update ``summary.csv``; returns the new rows.
    The summary is updated after every resolution, so an interrupted run keeps its rows."""
    from groundtruth import store

    out_dir = Path(out_dir)
    todo = list(check.resolutions if resolutions is None else resolutions)
    load0 = os.getloadavg()
    # the code's state: its own outputs (committed files it rewrites, also by an earlier
    # case's run into the same directory) do not make the record say "dirty"
    sha = store.git_sha(exclude=[out_dir])
    new_rows, default_pair = [], None
    for res in todo:
        if progress:
            progress(f"{check.case_id}: {res.variant} ref_nodes={res.ref_nodes} "
                     f"fem={res.fem_nx}x{res.fem_ny} {res.integrator} nu={res.poisson:g}")
        row, ref, fe = run_resolution(check, res)
        new_rows.append(row)
        rows = update_summary(out_dir / "summary.csv", [row])
        if res == check.default:
            default_pair = (ref, fe)
            write_csv(out_dir / f"{check.case_id}.csv", trajectory_rows(ref, fe),
                      TRAJECTORY_COLUMNS)
        if progress:
            progress(f"  l2_rel = {row['l2_rel']:.3e}, max_shape_rel = {row['max_shape_rel']:.3e},"
                     f" wall {row['ref_wall_s']:.1f} s + {row['fem_wall_s']:.1f} s")
    if default_pair is not None:
        plot(out_dir / f"{check.case_id}.png", check, *default_pair, rows)
    store.save_json(out_dir / f"{check.case_id}.json", {
        "case_id": check.case_id, "youngs": check.youngs, "target_l2_rel": check.target_l2,
        "config": check.config, "resolutions": [dataclasses.asdict(r) for r in todo],
        "rows": new_rows, "git_sha": sha, "versions": _versions(),
        "threads": os.environ.get("OMP_NUM_THREADS"), "cpu_count": os.cpu_count(),
        "load_average_start": load0, "load_average_end": os.getloadavg(),
    })
    return new_rows


def _versions() -> dict:
    from groundtruth.store import library_versions

    v = dict(library_versions())
    try:
        import skfem

        v["scikit-fem"] = skfem.__version__
    except (ImportError, AttributeError):
        pass
    return v
