"""Mesh convergence of a case's ground truth: the same trajectory at resolutions r = 1, 2, 4, ...

Each resolution ``CASE@rN`` (docs/SCALE.md, "Cases by resolution") is the same physical problem
on a mesh N times finer, so its trajectories should converge as r grows. The study simulates
one modulus (the case's reference modulus unless given) at every r and follows one material
point, the *probe*: the node of the r = 1 mesh (initial positions) farthest along the length (a plate's
``tip_node``, a rod's free end), found on every refined mesh at the same rest position. Its
displacement ``u(t) = x(t) - X`` is compared between neighbouring resolutions:

    rel_diff(r) = max_t |u_r(t) - u_2r(t)| / max_t |u_2r(t)|     (a relative sup-norm),
    final_rel_diff(r) = |u_r(t_end) - u_2r(t_end)| / |u_2r(t_end)|.

A case without a clamp (``rod_falling`` falls freely) measures its probe against the mass
centre, ``u(t) = (x(t) - x_c(t)) - (X - X_c)``: the fall is the same at every r to 1e-12 by
construction, the bending is what the mesh resolves.

Each resolution's trajectory is cached as ``CACHE/CASE@rN-Y.npz`` (atomic), so an interrupted
study resumes where it stopped; the cache key holds the case hash, so a changed case is
simulated again.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from groundtruth import store

SUMMARY_COLUMNS = ("case", "r", "nodes", "youngs_pa", "t_end_s", "probe_rest_x_m",
                   "probe_rest_y_m", "probe_rest_z_m", "relative_to", "max_displacement_m",
                   "final_displacement_m", "next_r", "rel_diff", "final_rel_diff", "cpu_s",
                   "cpu_s_per_step", "newton_iterations", "steps", "linear_solver", "git_sha")


def probe_node(case) -> int:
    """The probe node of a case's mesh at r = 1 (see the module docstring)."""
    tip = getattr(case, "tip_node", None)
    if tip is not None:
        return int(tip)
    rest = np.asarray(case.initial_state()[0], float)
    x = rest[:, 0]
    far = np.flatnonzero(np.isclose(x, x.max(), rtol=0, atol=1e-9 * max(1.0, np.ptp(x))))
    return int(far[np.argmin(np.abs(rest[far, 1] - np.median(rest[:, 1])))])


def node_at(rest: np.ndarray, point: np.ndarray, scale: float) -> int:
    """The node of ``rest (N, 3)`` at ``point``; ``ValueError`` if none lies within 1e-9 scale."""
    d = np.linalg.norm(rest - point, axis=1)
    i = int(np.argmin(d))
    if d[i] > 1e-9 * scale:
        raise ValueError(f"no node at rest position {point.tolist()} m (nearest {d[i]:.3g} m "
                         "away): the refined mesh does not keep this material point")
    return i


def _displacement(pos: np.ndarray, node: int, mass: np.ndarray | None) -> np.ndarray:
    """``(T, 3)`` displacement of ``node`` from ``pos (T, N, 3)``, relative to the mass centre
    when ``mass`` is given."""
    x = pos[:, node, :]
    if mass is not None:
        x = x - np.einsum("n,tnk->tk", mass, pos) / mass.sum()
    return x - x[0]


def simulate_cached(case, youngs: float, t_end: float, cache: Path | None,
                    progress: Callable[[str], None] | None = None) -> dict:
    """The case's trajectory at ``youngs`` to ``t_end``, from ``cache`` if it holds it."""
    path = None
    if cache is not None:
        path = Path(cache) / f"{case.id}-Y{youngs:.6g}-t{t_end:.6g}-{case.hash()[:12]}.npz"
        if path.exists():
            with np.load(path, allow_pickle=False) as f:
                return {k: f[k] for k in f.files}
    t0 = time.process_time()
    step = [0]

    def tick(t):
        step[0] += 1
        if progress is not None and step[0] % 50 == 0:
            progress(f"  {case.id}: t = {t:.4g} / {t_end:g} s, "
                     f"{time.process_time() - t0:.0f} CPU s")

    res = case.simulate(youngs, t_end=t_end, progress=tick)
    out = {"t": res["t"], "pos": res["pos"], "cpu_s": np.float64(time.process_time() - t0),
           "newton_iterations": np.int64(res["stats"]["newton_iterations"])}
    if path is not None:
        store.save_npz(path, out)
    return out


def convergence(base_case: str, resolutions: Sequence[int], youngs: float | None = None,
                t_end: float | None = None, cache: Path | None = None,
                progress: Callable[[str], None] | None = None) -> tuple[list[dict], list[dict]]:
    """Run the study; returns ``(summary rows, trajectory rows)`` (module docstring)."""
    from benchmarks.suite.registry import get_case

    rs = sorted(set(int(r) for r in resolutions))
    if not rs or rs[0] < 1:
        raise ValueError(f"resolutions must be positive integers, got {list(resolutions)}")
    case1 = get_case(base_case)
    youngs = float(case1.reference_youngs if youngs is None else youngs)
    t_end = float(case1.t_end if t_end is None else t_end)
    rest1 = np.asarray(case1.initial_state()[0], float)
    point = rest1[probe_node(case1)]
    scale = float(np.ptp(rest1, axis=0).max())
    free = not np.any(case1.system(youngs).fixed_nodes)
    summary, frames, disp = [], [], {}
    for r in rs:
        case = get_case(base_case if r == 1 else f"{base_case}@r{r}")
        system = case.system(youngs)
        rest = np.asarray(case.initial_state()[0], float)
        node = node_at(rest, point, scale)
        if progress is not None:
            progress(f"{case.id}: {len(rest)} nodes, Y = {youngs:g} Pa, t_end = {t_end:g} s")
        res = simulate_cached(case, youngs, t_end, cache, progress)
        u = _displacement(res["pos"], node, system.mass if free else None)
        disp[r] = (res["t"], u)
        steps = int(round(t_end / case.solver_settings.dt))
        amp = np.linalg.norm(u, axis=1)
        summary.append({
            "case": base_case, "r": r, "nodes": len(rest), "youngs_pa": youngs,
            "t_end_s": t_end, "probe_rest_x_m": point[0], "probe_rest_y_m": point[1],
            "probe_rest_z_m": point[2] if point.size > 2 else 0.0,
            "relative_to": "mass_centre" if free else "rest",
            "max_displacement_m": float(amp.max()), "final_displacement_m": float(amp[-1]),
            "next_r": None, "rel_diff": None, "final_rel_diff": None,
            "cpu_s": float(res["cpu_s"]), "cpu_s_per_step": float(res["cpu_s"]) / steps,
            "newton_iterations": int(res["newton_iterations"]), "steps": steps,
            "linear_solver": "band LU" if system.assembler.banded else
            f"sparse ({system.assembler.sparse.backend})"})
        for k, t in enumerate(res["t"]):
            frames.append({"case": base_case, "r": r, "nodes": len(rest), "t_s": float(t),
                           "ux_m": u[k, 0], "uy_m": u[k, 1], "uz_m": u[k, 2]})
    for row, nxt in zip(summary[:-1], summary[1:]):
        (t, u), (t2, u2) = disp[row["r"]], disp[nxt["r"]]
        if not np.allclose(t, t2, rtol=0, atol=1e-12):
            raise ValueError(f"{base_case}: r = {row['r']} and {nxt['r']} save different frames")
        d = np.linalg.norm(u - u2, axis=1)
        row["next_r"] = nxt["r"]
        row["rel_diff"] = float(d.max() / np.linalg.norm(u2, axis=1).max())
        row["final_rel_diff"] = float(d[-1] / np.linalg.norm(u2[-1]))
    return summary, frames


def update_summary(path: Path, rows: list[dict]) -> list[dict]:
    """Merge ``rows`` into the CSV at ``path`` (keyed by case and r), write it atomically and
    return every row."""
    import pandas as pd

    new = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    if Path(path).exists():
        old = pd.read_csv(path)
        keep = ~old.set_index(["case", "r"]).index.isin(new.set_index(["case", "r"]).index)
        new = pd.concat([old[keep], new], ignore_index=True)
    new = new.sort_values(["case", "r"]).reset_index(drop=True)
    text = new.to_csv(index=False, float_format="%.6g")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")
    return new.to_dict("records")


def write_frames(path: Path, frames: list[dict]) -> None:
    import pandas as pd

    text = pd.DataFrame(frames).to_csv(index=False, float_format="%.9g")
    store.atomic_write(Path(path), lambda f: f.write(text), mode="w")


def plot(path: Path, frames: list[dict], case: str) -> None:
    """Probe displacement magnitude vs time, one line per r (PNG)."""
    import pandas as pd

    from benchmarks.suite.figures import _plt, _save

    df = pd.DataFrame(frames)
    fig, ax = _plt().subplots(figsize=(7, 4))
    for r, g in df.groupby("r"):
        u = np.sqrt(g.ux_m**2 + g.uy_m**2 + g.uz_m**2)
        ax.plot(g.t_s, u, label=f"r = {r} ({int(g.nodes.iloc[0])} nodes)", lw=1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("probe displacement |u| (m)")
    ax.set_title(f"{case}: mesh convergence of the probe's trajectory")
    ax.legend()
    fig.tight_layout()
    _save(fig, Path(path))
