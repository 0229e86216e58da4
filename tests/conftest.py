"""Shared fixtures: tiny meshes (a 5-node rod, a 10-node clamped strip) with synthetic
trajectories in the store's layout, small enough for float64 gradchecks."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


def rod_arrays(n_nodes=5, B=3, T=6, seed=0, dt=0.1):
    """A planar rod along x falling and bending a little, in the store's layout."""
    rng = np.random.default_rng(seed)
    L = 0.1
    rest = np.zeros((n_nodes, 3))
    rest[:, 0] = np.linspace(0, L, n_nodes)
    t = np.arange(T) * dt
    s = rest[:, 0] / L
    pos = np.empty((B, T, n_nodes, 3))
    vel = np.empty_like(pos)
    for b in range(B):
        amp, speed = 0.01 * rng.uniform(0.5, 1.5), 0.005 * rng.uniform(0.5, 1.5)
        shape = amp * np.sin(np.pi * s)  # sag in the middle
        for k, tk in enumerate(t):
            g = 1 - np.exp(-tk / 0.2)
            pos[b, k] = rest
            pos[b, k, :, 1] = -speed * tk - shape * g
            vel[b, k] = 0
            vel[b, k, :, 1] = -speed - shape * np.exp(-tk / 0.2) / 0.2
    edges = np.stack([np.arange(n_nodes - 1), np.arange(1, n_nodes)], 1)
    mass = np.full(n_nodes, 1e-3)
    force = np.zeros((n_nodes, 3))
    force[:, 1] = -9.81 * mass
    return {"t": t, "pos": pos, "vel": vel, "youngs": rng.uniform(1e8, 1.5e9, B),
            "edges": edges, "cells": np.zeros((0, 3), np.int64),
            "node_type": np.zeros(n_nodes, np.int64), "rest_pos": rest, "mass": mass,
            "force": force, "damping": np.full(n_nodes, 0.5), "case": np.array("tiny_rod"),
            "case_hash": np.array("0" * 64)}


def strip_arrays(nx=5, ny=2, B=2, T=5, seed=1, dt=0.01):
    """A triangulated strip clamped at x = 0, sagging out of plane (z), store layout."""
    rng = np.random.default_rng(seed)
    xs, ys = np.linspace(0, 0.2, nx), np.linspace(0, 0.05, ny)
    rest = np.array([[x, y, 0.0] for x in xs for y in ys])
    idx = np.arange(nx * ny).reshape(nx, ny)
    cells = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            cells += [(a, b, c), (a, c, d)]
    cells = np.array(cells)
    e = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    edges = np.unique(np.sort(e, axis=1), axis=0)
    node_type = (rest[:, 0] == 0).astype(np.int64)
    t = np.arange(T) * dt
    pos = np.repeat(np.repeat(rest[None, None], T, 1), B, 0).copy()
    vel = np.zeros_like(pos)
    for b in range(B):
        w = rng.uniform(0.5, 2.0)
        pos[b, :, :, 2] = -w * (rest[:, 0] ** 2)[None] * t[:, None] ** 2
        vel[b, :, :, 2] = -2 * w * (rest[:, 0] ** 2)[None] * t[:, None]
    mass = np.full(len(rest), 1e-3)
    force = np.zeros((len(rest), 3))
    force[:, 2] = -9.81 * mass
    return {"t": t, "pos": pos, "vel": vel, "youngs": rng.uniform(2.5e6, 7.5e6, B),
            "edges": edges, "cells": cells, "node_type": node_type, "rest_pos": rest,
            "mass": mass, "force": force, "damping": 0.1 * mass,
            "case": np.array("tiny_strip"), "case_hash": np.array("1" * 64)}


MESHES = {"rod": rod_arrays, "strip": strip_arrays}


@pytest.fixture(params=sorted(MESHES))
def arrays(request):
    return MESHES[request.param]()


def permuted_arrays(arrays, perm):
    """The same arrays with node i renamed inv[i] (new node k is old node perm[k]);
    returns ``(arrays, inv)``."""
    inv = np.argsort(perm)
    out = dict(arrays)
    for k in ("pos", "vel"):
        out[k] = arrays[k][:, :, perm]
    for k in ("node_type", "rest_pos", "mass", "force", "damping"):
        out[k] = arrays[k][perm]
    out["edges"], out["cells"] = inv[arrays["edges"]], inv[arrays["cells"]]
    return out, inv
