"""Long-horizon stability of a trained model: the ``horizon_*`` rows of ``metrics.csv``.

Every test trajectory is rolled out by the model's own ``rollout(x0, v0, youngs, t)`` from its
initial state for ``FACTOR`` times the trajectory's length at the same interval h (frames
``0 .. FACTOR (T - 1)``), and its end is compared with what the case's solver says the motion
settles to at the same modulus:

- a case with clamped nodes (the plates, ``rod_cantilever``) settles to its static
  equilibrium (``case.solve_static``, ``meshbench simulate --static``):
  ``horizon_equilibrium_rmse`` (m) = sqrt(mean over nodes of |x_i - x*_i|^2) of the final
  frame against the equilibrium x*; ``horizon_tip_rel_error`` (1) = |d - d*| / |d*|, d the
  final displacement of the tip node (``tip_node``) along the load (the direction of the summed
  applied force), d* the equilibrium's;
- a plate that deforms in its own plane (``plate_cantilever``: a planar mesh loaded in its
  plane) also counts inverted triangles over frames 1 .. FACTOR (T - 1): a triangle is
  inverted in a frame when its signed area (its area vector projected on its rest normal) is
  <= 0. ``horizon_inverted_triangles``: distinct triangles inverted in at least one frame;
  ``horizon_inverted_triangle_frames``: (triangle, frame) pairs inverted;
- a free case with ``terminal_velocity()`` (``rod_falling``) settles to a steady fall:
  ``horizon_shape_rmse`` (m) = the RMSE over nodes of the final shape in the frame that moves
  with the centroid (the mean of the nodes) against the steady shape of the solver run until
  it is steady (``steady_fall``); ``horizon_terminal_speed_rel_error`` (1) = |v - v_T| / v_T,
  v the centroid's speed over the final interval, v_T = ``case.terminal_velocity()`` (exact).

A rollout that diverges (non-finite positions) gets NaN in every metric. Each metric is one row
per test trajectory with the columns of the RMSE rows: ``step`` = FACTOR (T - 1), ``time`` its
time, and the metric's value in the ``rmse`` column. The solver's references are computed once
per (case hash, modulus) and cached under ``DATA/CASE/horizon/``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd

from groundtruth import store

#: How many trajectory lengths the long rollout covers.
FACTOR = 5
#: The metrics, their units and one-line definitions (docs/SUITE.md, the results README).
METRICS = {
    "horizon_equilibrium_rmse": ("m", "RMSE over nodes of the final frame against the "
                                      "solver's static equilibrium"),
    "horizon_tip_rel_error": ("1", "|d - d*| / |d*| of the tip's final displacement along the "
                                   "load"),
    "horizon_inverted_triangles": ("count", "distinct triangles with signed area <= 0 in at "
                                            "least one frame"),
    "horizon_inverted_triangle_frames": ("count", "(triangle, frame) pairs with signed area "
                                                  "<= 0"),
    "horizon_shape_rmse": ("m", "RMSE over nodes of the final shape about the centroid "
                                "against the solver's steady shape"),
    "horizon_terminal_speed_rel_error": ("1", "|v - v_T| / v_T of the centroid's final speed"),
}
CSV_NOTE = (f"metric=horizon_*: long-horizon stability, one row per test trajectory rolled out "
            f"for {FACTOR}x its length (step = {FACTOR} (T-1)); the `rmse` column holds the "
            "metric's value: " + "; ".join(f"{k} ({u}): {d}" for k, (u, d) in METRICS.items())
            + ". NaN: the rollout diverged. See docs/SUITE.md, \"Long-horizon stability\".")
#: A steady fall: the comoving shape moved by at most this fraction of its deflection from
#: the straight rest shape over the last ``FACTOR t_end`` of solver time (one chunk); at most
#: ``STEADY_MAX_CHUNKS`` chunks.
STEADY_RTOL = 1e-6
STEADY_MAX_CHUNKS = 40
#: Bumped when a reference's computation changes: old cache files are then recomputed.
CACHE_VERSION = 2


class HorizonError(RuntimeError):
    """The solver's reference could not be computed (not steady, solver failure)."""


# --- which metrics a case has ---------------------------------------------------------------
def has_clamp(arrays: dict) -> bool:
    return bool((np.asarray(arrays["node_type"]) == 1).any())


def falls_freely(case, arrays: dict) -> bool:
    return not has_clamp(arrays) and callable(getattr(case, "terminal_velocity", None))


def load_direction(arrays: dict) -> np.ndarray:
    """Unit vector ``(3,)`` of the summed applied force (gravity)."""
    f = np.asarray(arrays["force"], float).sum(axis=0)
    return f / np.linalg.norm(f)


def rest_normals(rest: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Unit normals ``(M, 3)`` of the triangles ``cells (M, 3)`` at ``rest (N, 3)``."""
    a = np.cross(rest[cells[:, 1]] - rest[cells[:, 0]], rest[cells[:, 2]] - rest[cells[:, 0]])
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def deforms_in_plane(arrays: dict) -> bool:
    """A triangle mesh that is planar at rest and loaded in its plane (its triangles stay in
    it, so the orientation against the rest normal tests inversion)."""
    cells = np.asarray(arrays["cells"])
    if len(cells) == 0:
        return False
    n = rest_normals(np.asarray(arrays["rest_pos"], float), cells)
    return bool(np.allclose(n, n[0], atol=1e-9) and abs(n[0] @ load_direction(arrays)) < 1e-9)


def metric_names(case, arrays: dict) -> list[str]:
    """The ``horizon_*`` metrics of ``case`` (empty: the case has none)."""
    out = []
    if has_clamp(arrays):
        out += ["horizon_equilibrium_rmse", "horizon_tip_rel_error"]
        if deforms_in_plane(arrays):
            out += ["horizon_inverted_triangles", "horizon_inverted_triangle_frames"]
    elif falls_freely(case, arrays):
        out += ["horizon_shape_rmse", "horizon_terminal_speed_rel_error"]
    return out


def tip_node(case, rest: np.ndarray) -> int:
    """``case.tip_node`` when the case defines it, else the node of the free end (largest x)
    nearest the centre line (the mean y of the rest nodes)."""
    if getattr(case, "tip_node", None) is not None:
        return int(case.tip_node)
    far = np.flatnonzero(np.isclose(rest[:, 0], rest[:, 0].max(), rtol=0, atol=1e-12))
    return int(far[np.argmin(np.abs(rest[far, 1] - rest[:, 1].mean()))])


# --- the metrics on arrays ------------------------------------------------------------------
def node_rmse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(..., N, 3)`` twice -> ``(...)``: sqrt of the mean over nodes of |a - b|^2."""
    return np.sqrt(((np.asarray(a) - np.asarray(b)) ** 2).sum(-1).mean(-1))


def comoving(pos: np.ndarray) -> np.ndarray:
    """Positions ``(..., N, 3)`` relative to their centroid (the mean over nodes)."""
    return pos - pos.mean(axis=-2, keepdims=True)


def centroid_speed(pos: np.ndarray, h: float) -> np.ndarray:
    """``(..., T, N, 3)`` -> ``(...)``: |c_T - c_{T-1}| / h, c the mean of the nodes."""
    c = pos[..., -2:, :, :].mean(axis=-2)
    return np.linalg.norm(c[..., 1, :] - c[..., 0, :], axis=-1) / h


def signed_areas(pos: np.ndarray, cells: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``pos (..., N, 3)`` -> ``(..., M)``: each triangle's area vector projected on its
    rest normal ``normals (M, 3)`` (positive at rest, <= 0 once inverted), m^2."""
    p = [pos[..., cells[:, k], :] for k in range(3)]
    return 0.5 * (np.cross(p[1] - p[0], p[2] - p[0]) * normals).sum(-1)


def inverted_counts(pos: np.ndarray, cells: np.ndarray, normals: np.ndarray):
    """``pos (T, N, 3)`` -> (distinct triangles inverted in some frame, inverted
    (triangle, frame) pairs)."""
    bad = signed_areas(pos, cells, normals) <= 0
    return int(bad.any(axis=0).sum()), int(bad.sum())


def tip_displacement(pos: np.ndarray, rest: np.ndarray, tip: int, direction) -> np.ndarray:
    """``pos (..., N, 3)`` -> ``(...)``: the tip's displacement from rest along ``direction``."""
    return (pos[..., tip, :] - rest[tip]) @ np.asarray(direction)


def clamped_values(case, pred: np.ndarray, arrays: dict, refs: list) -> dict:
    """The metrics of a clamped case: ``pred (B, T, N, 3)``, ``refs`` the B equilibria."""
    rest = np.asarray(arrays["rest_pos"], float)
    eq = np.stack(refs)
    tip, g = tip_node(case, rest), load_direction(arrays)
    d, d_eq = tip_displacement(pred[:, -1], rest, tip, g), tip_displacement(eq, rest, tip, g)
    out = {"horizon_equilibrium_rmse": node_rmse(pred[:, -1], eq),
           "horizon_tip_rel_error": np.abs(d - d_eq) / np.abs(d_eq)}
    if deforms_in_plane(arrays):
        cells = np.asarray(arrays["cells"])
        counts = np.array([inverted_counts(p[1:], cells, rest_normals(rest, cells))
                           for p in pred], float).reshape(-1, 2)
        out["horizon_inverted_triangles"] = counts[:, 0]
        out["horizon_inverted_triangle_frames"] = counts[:, 1]
    return out


def falling_values(case, pred: np.ndarray, h: float, refs: list) -> dict:
    """The metrics of a free fall: ``pred (B, T, N, 3)``, ``refs`` the B steady falls."""
    steady = np.stack([r["shape"] for r in refs])
    v_t = float(case.terminal_velocity())
    return {"horizon_shape_rmse": node_rmse(comoving(pred[:, -1]), steady),
            "horizon_terminal_speed_rel_error": np.abs(centroid_speed(pred, h) - v_t) / v_t}


def horizon_values(case, pred: np.ndarray, arrays: dict, data_dir=None, log=None) -> dict:
    """``{metric: (B,)}`` for the long rollouts ``pred (B, T5, N, 3)`` of the test split
    ``arrays``; NaN for a rollout that diverged; ``{}`` for a case without these metrics."""
    names = metric_names(case, arrays)
    if not names:
        return {}
    pred = np.asarray(pred, float)
    refs = references(case, arrays, data_dir, log)
    if has_clamp(arrays):
        out = clamped_values(case, pred, arrays, refs)
    else:
        out = falling_values(case, pred, float(arrays["t"][1] - arrays["t"][0]), refs)
    bad = ~np.isfinite(pred).all(axis=(1, 2, 3))
    return {k: np.where(bad, np.nan, np.asarray(out[k], float)) for k in names}


# --- the solver's references (cached) -------------------------------------------------------
def cache_dir(case, data_dir=None) -> Path:
    """``DATA/CASE/horizon``: the solver's references of a case."""
    return store.data_dir(data_dir) / case.id / "horizon"


def cache_path(case, kind: str, youngs: float, data_dir=None) -> Path:
    """``DATA/CASE/horizon/KIND-HASH16-Y.npz``: one file per (case hash, modulus)."""
    return cache_dir(case, data_dir) / f"{kind}-{case.hash()[:16]}-{float(youngs)!r}.npz"


def _read_cache(path: Path, case_hash: str, youngs: float) -> dict | None:
    """The cached arrays when the file is readable and names this case, modulus and version."""
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError):
        return None
    ok = (str(d.get("case_hash")) == case_hash and float(d.get("youngs", np.nan)) == youngs
          and int(d.get("cache_version", -1)) == CACHE_VERSION)
    return d if ok else None


def cached(case, kind: str, youngs: float, compute, data_dir=None) -> dict:
    """``compute(case, youngs) -> dict of arrays``, stored once in ``cache_path`` (atomically)
    and read back from there afterwards; a missing, unreadable or stale file is recomputed."""
    youngs = float(youngs)
    path = cache_path(case, kind, youngs, data_dir)
    hit = _read_cache(path, case.hash(), youngs) if path.exists() else None
    if hit is not None:
        return hit
    out = {**compute(case, youngs), "case_hash": np.array(case.hash()),
           "youngs": np.array(youngs), "cache_version": np.array(CACHE_VERSION)}
    store.save_npz(path, out)
    return out


def references(case, arrays: dict, data_dir=None, log=None) -> list:
    """The solver's reference for every trajectory of ``arrays``: its static equilibrium
    ``(N, 3)`` (a clamped case) or steady fall (``steady_fall``); ``log(message)`` before each
    one that is not cached yet."""
    clamped = has_clamp(arrays)
    kind, get = ("static", static_equilibrium) if clamped else ("steady", steady_fall)
    youngs = [float(y) for y in np.asarray(arrays["youngs"], float)]
    todo = [y for y in youngs if not cache_path(case, kind, y, data_dir).exists()]
    if not todo:
        return [get(case, y, data_dir) for y in youngs]
    from benchmarks.suite.procs import DirLock

    # one process computes a case's references; another run of it (--jobs) waits, then reads
    say = log or (lambda msg: None)
    with DirLock(cache_dir(case, data_dir), ".lock").acquire(
            wait=True, on_wait=lambda pid: say(f"process {pid or '?'} is computing the "
                                               "solver references; waiting for it")):
        out = []
        for y in youngs:
            if y in todo and not cache_path(case, kind, y, data_dir).exists():
                say(f"solver reference {todo.index(y) + 1}/{len(todo)} ({kind}, Y = {y:.4g} Pa)")
            out.append(get(case, y, data_dir))
    return out


def _static(case, youngs: float) -> dict:
    return {"pos": np.asarray(case.solve_static(youngs), float)}


def static_equilibrium(case, youngs: float, data_dir=None) -> np.ndarray:
    """The solver's static equilibrium ``(N, 3)`` at ``youngs`` (cached), m."""
    return cached(case, "static", youngs, _static, data_dir)["pos"]


def _steady(case, youngs: float) -> dict:
    """Run the solver from rest, one backward-Euler step per saved interval (a uniformly
    translating state is a fixed point of backward Euler at any step, so the steady fall does
    not depend on it), in chunks of ``FACTOR t_end`` until the comoving shape moves by at most
    ``STEADY_RTOL`` of its deflection over one chunk."""
    import dataclasses

    from groundtruth import implicit

    system, (q, v) = case.system(youngs), case.initial_state()
    settings = dataclasses.replace(case.solver_settings, dt=case.save_dt)
    q, v, t = q.ravel(), v.ravel(), case.t_save(FACTOR * case.t_end)
    straight, prev, change = comoving(case.rest_positions()), None, np.inf
    for chunk in range(1, STEADY_MAX_CHUNKS + 1):
        pos, vel, _ = implicit.simulate(system, q, v, t, settings)
        q, v = pos[-1], vel[-1]
        frames = pos[-2:].reshape(2, -1, 3)
        shape = comoving(frames[-1])
        if prev is not None:
            change = float(node_rmse(shape, prev))
            if change <= STEADY_RTOL * float(node_rmse(shape, straight)):
                speed = float(centroid_speed(frames, case.save_dt))
                return {"shape": shape, "speed": np.array(speed), "change_m": np.array(change),
                        "t_end": np.array(chunk * float(t[-1]))}
        prev = shape
    raise HorizonError(f"{case.id} at Y = {youngs:g} Pa: the solver's fall is not steady after "
                       f"{STEADY_MAX_CHUNKS * float(t[-1]):g} s (its comoving shape still moves "
                       f"by {change:.3g} m per {float(t[-1]):g} s)")


def steady_fall(case, youngs: float, data_dir=None) -> dict:
    """The solver's steady fall at ``youngs`` (cached): ``shape (N, 3)`` about the centroid
    (m), ``speed`` (m/s, the centroid's), ``change_m`` (the shape's RMS change over the last
    chunk, the steadiness check) and ``t_end`` (s simulated)."""
    return cached(case, "steady", youngs, _steady, data_dir)


# --- rollouts and rows ----------------------------------------------------------------------
def long_times(t: np.ndarray, factor: int = FACTOR) -> np.ndarray:
    """``FACTOR (T - 1) + 1`` times from ``t[0]`` at the interval of ``t``."""
    t = np.asarray(t, float)
    return t[0] + (t[1] - t[0]) * np.arange(factor * (len(t) - 1) + 1)


def long_rollout(model, arrays: dict, factor: int = FACTOR, batch_size: int = 4,
                 log=None) -> np.ndarray:
    """Positions ``(B, FACTOR (T - 1) + 1, N, 3)`` of the model's rollouts of every trajectory
    of ``arrays`` from its initial state; ``log(message)`` after every batch."""
    import torch

    from meshodenet.mesh.data import Trajectories

    data = Trajectories.from_arrays(arrays, device=model.device)
    t = torch.as_tensor(long_times(arrays["t"], factor), dtype=data.t.dtype, device=data.t.device)
    out, t0 = [], time.perf_counter()
    with torch.no_grad():
        for s in range(0, len(data), batch_size):
            sl = slice(s, s + batch_size)
            pos, _ = model.rollout(data.pos[sl, 0], data.vel[sl, 0], data.youngs[sl], t)
            out.append(pos.detach().double().cpu().numpy())
            if log is not None:
                log(f"{min(s + batch_size, len(data))}/{len(data)} trajectories rolled out to "
                    f"{len(t) - 1} steps ({time.perf_counter() - t0:.0f} s)")
    return np.concatenate(out)


def horizon_frame(values: dict, arrays: dict, ids: dict, factor: int = FACTOR) -> pd.DataFrame:
    """Tidy rows (the columns of the RMSE rows) of ``values`` (``{metric: (B,)}``)."""
    t = long_times(arrays["t"], factor)
    frames = [pd.DataFrame({**ids, "metric": name, "trajectory": np.arange(len(v)),
                            "step": len(t) - 1, "time": float(t[-1]), "rmse": v})
              for name, v in values.items()]
    cols = list(ids) + ["metric", "trajectory", "step", "time", "rmse"]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=cols)


def has_rows(metrics: pd.DataFrame) -> bool:
    return bool(metrics["metric"].astype(str).str.startswith("horizon_").any())


def add_to_run(run_dir, metrics_file: Path, data_dir=None, device: str = "auto", arrays=None,
               log=None, model=None) -> int:
    """Append the ``horizon_*`` rows of a finished run to its ``metrics_file`` (a run's
    ``test_metrics.csv``) unless they are there or its case has none: the rows already in
    the file are kept byte for byte, the file is rewritten atomically. ``model``: the run's
    model (default: its ``best.pt``). Returns the number of rows appended."""
    from benchmarks.suite.registry import get_case

    metrics_file = Path(metrics_file)
    old = pd.read_csv(metrics_file)
    case = get_case(str(old["case"].iloc[0]))
    arrays = store.load_split(case, "test", data_dir) if arrays is None else arrays
    if has_rows(old) or not metric_names(case, arrays):
        return 0
    if model is None:
        from benchmarks.suite.runs import _load_run

        model = _load_run(Path(run_dir), "best", device)[1]
    t0 = time.perf_counter()
    pred = long_rollout(model, arrays, log=log)
    rows = horizon_frame(horizon_values(case, pred, arrays, data_dir, log), arrays,
                         _ids(old), FACTOR)[list(old.columns)]
    text = metrics_file.read_text() + rows.to_csv(index=False, header=False,
                                                  float_format="%.9g", lineterminator="\n")
    store.atomic_write(metrics_file, lambda f: f.write(text), mode="w")
    if log is not None:
        log(f"{len(rows)} long-horizon rows in {time.perf_counter() - t0:.0f} s")
    return len(rows)


def _ids(metrics: pd.DataFrame) -> dict:
    """The id columns (those before ``metric``) of a run's metrics, from its first row."""
    cols = list(metrics.columns)
    return {c: metrics[c].iloc[0] for c in cols[:cols.index("metric")]}


# --- the markdown table ---------------------------------------------------------------------
def _cell(name: str, v: pd.Series) -> str:
    unit = METRICS[name][0]
    if v.isna().all():
        return "diverged" if len(v) else ""
    nan = f" ({int(v.isna().sum())} diverged)" if v.isna().any() else ""
    if unit == "count":
        return f"{int(v.sum())}{nan}"
    scale, suffix = (1e3, "") if unit == "m" else (1e2, " %")
    return f"{scale * v.mean():.3g} ± {scale * v.std(ddof=0):.2g}{suffix}{nan}"


HEADINGS = {"horizon_equilibrium_rmse": "to equilibrium (mm)",
            "horizon_tip_rel_error": "tip deflection error",
            "horizon_inverted_triangles": "inverted triangles",
            "horizon_inverted_triangle_frames": "inverted triangle-frames",
            "horizon_shape_rmse": "shape vs steady (mm)",
            "horizon_terminal_speed_rel_error": "terminal speed error"}


def markdown_lines(metrics: pd.DataFrame, keys: list) -> list[str]:
    """The long-horizon table of ``rmse_at_step.md``: per case, one row per ``keys`` value,
    mean ± std over test trajectories (counts: the sum over them)."""
    hz = metrics[metrics["metric"].astype(str).str.startswith("horizon_")]
    if hz.empty:
        return []
    lines = [f"## Long horizon ({FACTOR}x the trajectory's length)", "",
             "Each test trajectory rolled out from its initial state for "
             f"{FACTOR}x its length; its end against the solver's static equilibrium (clamped "
             "cases) or steady fall (free rod); mean ± std over test trajectories, counts "
             "summed over them. Definitions: docs/SUITE.md, \"Long-horizon stability\".", ""]
    for case, dfc in hz.groupby("case", sort=True):
        names = [m for m in METRICS if m in set(dfc["metric"])]
        step = int(dfc["step"].max())
        lines += [f"### {case} (step {step})", "",
                  "| " + " | ".join(keys + [HEADINGS[m] for m in names]) + " |",
                  "|" + "---|" * (len(keys) + len(names))]
        for kv, dfm in dfc.groupby(keys, sort=True):
            kv = kv if isinstance(kv, tuple) else (kv,)
            cells = [_cell(m, dfm.loc[dfm["metric"] == m, "rmse"]) for m in names]
            lines.append("| " + " | ".join([str(v) for v in kv] + cells) + " |")
        lines.append("")
    return lines
