"""What the parts of ``meshbench bench scale`` share (``benchmarks.cost.scalebench``, its
processes ``scaleprocs`` and outputs ``scalereport``): the cases, methods, columns and the small
helpers."""

from __future__ import annotations

import time

import numpy as np

CASES = ("rod_falling", "plate_cantilever", "plate_hanging")
DEFAULT_CASES = ("rod_falling", "plate_cantilever")
#: resolutions per case (nodes: rod 20 r + 1; plate_cantilever 182 ... ~1e5 at r = 27)
DEFAULT_R = {"rod_falling": (1, 4, 16, 64, 500),
             "plate_cantilever": (1, 2, 4, 8, 16, 27),
             "plate_hanging": (1, 2, 4, 8, 16)}
LEARNERS = ("meshodenet", "mgn", "meshodenet_imex", "implicit_energy",
            "implicit_energy_dissipation")
METHODS = ("groundtruth", "solver_h") + LEARNERS
GRAD_MODES = ("direct", "adjoint", "checkpoint")
#: a timing longer than this (s) is not repeated in later rounds
REPEAT_BELOW_S = 20.0
#: the cost ratio ground truth / learner per simulated second looked for
CROSSOVER_RATIO = 10.0
COLUMNS = ["case", "r", "nodes", "edges", "stage", "method", "variant", "quantity", "value",
           "unit", "note"]
PROVENANCE = ["git_sha", "timestamp", "machine", "cpu_model", "cpu_count", "threads", "device",
              "linear_backend", "preset", "steps", "window", "version_python", "version_numpy",
              "version_scipy", "version_torch"]


# --- small helpers ---------------------------------------------------------------------------
def write_rows(path, fields, rows: list, digits: int, extra: str = "raise") -> None:
    """``rows`` (dicts) as a CSV of the columns ``fields``, floats to ``digits`` significant
    digits, written atomically (``groundtruth.store.atomic_write``); ``extra``: what a key
    outside ``fields`` does, ``raise`` or ``ignore`` (``csv.DictWriter``'s ``extrasaction``)."""
    import csv
    import io
    from pathlib import Path

    from groundtruth import store

    buf = io.StringIO()
    w = csv.DictWriter(buf, fields, extrasaction=extra, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: f"{v:.{digits}g}" if isinstance(v, float) else v for k, v in r.items()})
    store.atomic_write(Path(path), lambda f: f.write(buf.getvalue()), mode="w")


def refined_id(case: str, r: int) -> str:
    return case if r == 1 else f"{case}@r{r}"


def mem_available_gb() -> float:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 1024**2
    except OSError:
        pass
    return float("inf")


def fit_power(nodes, values) -> tuple[float, float]:
    """``(exponent, prefactor)`` of the least-squares line of log(value) on log(nodes)."""
    x, y = np.log(np.asarray(nodes, float)), np.log(np.asarray(values, float))
    p, a = np.polyfit(x, y, 1)
    return float(p), float(np.exp(a))


def _timer(device):
    """``(now, sync)``: CPU seconds of this process on the CPU, wall seconds (after the GPU's
    queue has run) on CUDA."""
    from benchmarks.cost import device as dv

    if device.type == "cuda":
        return time.perf_counter, lambda: dv.sync(device)
    return time.process_time, lambda: None


def _row(case, r, nodes, edges, stage, method, variant, quantity, value, unit, note=""):
    v = float(value) if value is not None else float("nan")
    return {"case": case, "r": int(r), "nodes": int(nodes), "edges": int(edges), "stage": stage,
            "method": method, "variant": variant, "quantity": quantity, "value": v, "unit": unit,
            "note": note}


def mesh_arrays(case, system, t, pos, vel, youngs, split="single") -> dict:
    """The store layout of ``store.trajectory_arrays`` with the loads of an already built
    ``system`` (``case.loads()`` would build it again)."""
    from groundtruth import store

    edges, cells, node_type = case.mesh()
    return {"t": np.asarray(t, float), "pos": np.asarray(pos, float),
            "vel": np.asarray(vel, float), "youngs": np.asarray(youngs, float),
            "edges": np.asarray(edges, np.int64), "cells": np.asarray(cells, np.int64),
            "node_type": np.asarray(node_type, np.int64), "rest_pos": case.rest_positions(),
            "mass": system.mass.copy(), "force": system.force.copy(),
            "damping": system.damping.copy(), "case": np.array(case.id),
            "split": np.array(split), "case_hash": np.array(case.hash()),
            "format_version": np.array(store.FORMAT_VERSION)}


def synthetic_training(arrays: dict, n_traj: int, frames: int, save_dt: float) -> dict:
    """``arrays`` with ``n_traj`` synthetic trajectories of ``frames`` frames (rest positions
    plus a small seeded random walk of the free nodes; the cost of a training step does not
    depend on the values)."""
    rest = np.asarray(arrays["rest_pos"], float)
    rng = np.random.default_rng(0)
    shape = (n_traj, frames) + rest.shape
    vel = 1e-3 * rng.standard_normal(shape).cumsum(1) / np.sqrt(frames)
    vel *= (np.asarray(arrays["node_type"]) == 0)[None, None, :, None]
    vel[:, 0] = 0.0
    pos = rest + np.cumsum(vel, 1) * save_dt
    youngs = np.full(n_traj, float(np.asarray(arrays["youngs"]).ravel()[0]))
    return dict(arrays, t=np.arange(frames) * save_dt, pos=pos, vel=vel, youngs=youngs,
                split=np.array("train"))


def base_model(method: str, case_id: str, preset: str, device, log=None):
    """An untrained ``method`` (seeded weights) on the base case's mesh, its statistics from the
    base case's training data (the generated data when present, else synthetic), and where the
    data came from."""
    import torch

    from benchmarks.cost.enginebench import bench_arrays
    from benchmarks.suite.registry import get_case
    from benchmarks.suite.runs import get_model_spec
    from meshodenet.mesh.data import Mesh, Trajectories

    base = get_case(case_id.split("@")[0])
    n = min(base.n_train, 8)
    arrays, source = bench_arrays(base, n, base.n_frames, None)
    mesh = Mesh.from_arrays(arrays)
    spec = get_model_spec(method)
    _, cfg = spec.presets(preset, mesh.kind)
    torch.manual_seed(0)
    model = spec.build(mesh, cfg, Trajectories.from_arrays(arrays))
    return model.to(device), source
