"""Our store arrays in the layout the authors' training code reads (what their preprocessing
notebook writes to ``processed_dataset/``), restated from docs/SOURCES.md ("The authors'
data layout and training log"); none of their code is used here.

Per trajectory, a dict of tensors with a leading frame axis ``T`` (static ones repeated by
``expand``, no copy): ``world_pos, velocity (T, N, 3)``; ``youngs (T, N, 1)`` = Y / 1e6;
``node_type (T, N, 1)`` (1 clamped, float); ``one_hot_node_type (T, N, 2)``;
``edge_index (T, 2, 2E)`` (every mesh edge both ways: from the triangles for a triangle mesh,
from the segments for a line mesh); ``mesh_edge_attr (T, 2E, 4)`` = the rest relative position
``m_i - m_j`` and its norm. The velocity of frame k is ``(x_k - x_{k-1}) / 0.1`` (their ODE's
time unit is 0.1 per frame, whatever the physical interval), frame 0's previous frame being
itself (zero velocity). Statistics (``authors_stats``) are the mean and the unbiased standard
deviation, clamped at 1e-8, over every frame of every training trajectory: velocity, modulus,
the current relative position and its norm, the rest one and its norm.
"""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.ab.core import FRAME_TIME

YOUNGS_SCALE = 1e6
N_TYPES = 2
STD_MIN = 1e-8


def mesh_edges(arrays: dict) -> np.ndarray:
    """``(E, 2)`` undirected edges, ``i < j``, sorted: the triangles' sides for a triangle mesh,
    the store's ``edges`` (segments) for a line mesh."""
    cells = np.asarray(arrays["cells"], dtype=np.int64).reshape(-1, 3)
    if len(cells):
        e = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    else:
        e = np.asarray(arrays["edges"], dtype=np.int64).reshape(-1, 2)
    return np.unique(np.sort(e, axis=1), axis=0)


def both_ways(edges: np.ndarray) -> torch.Tensor:
    """``(2, 2E)`` long: every edge ``(i, j)`` then every ``(j, i)``."""
    e = torch.as_tensor(edges, dtype=torch.long).t()
    return torch.cat([e, e.flip(0)], 1)


def authors_velocity(pos: torch.Tensor) -> torch.Tensor:
    """``(T, N, 3)`` velocity of positions ``pos (T, N, 3)`` by the authors' rule."""
    prev = torch.cat([pos[:1], pos[:-1]])
    return (pos - prev) / FRAME_TIME


def relative(x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
    """``(..., 2E, 4)``: ``x_i - x_j`` over the edges ``(i, j)`` and its norm."""
    u = x[..., edge_index[0], :] - x[..., edge_index[1], :]
    return torch.cat([u, u.norm(dim=-1, keepdim=True)], -1)


def convert(arrays: dict) -> list[dict]:
    """One authors'-layout dict per trajectory of ``arrays`` (the store's layout, already cut
    to the frames to use); float32 like their files, ``edge_index`` long."""
    edge_index = both_ways(mesh_edges(arrays))
    node_type = torch.as_tensor(np.asarray(arrays["node_type"]), dtype=torch.long)
    N = len(node_type)
    missing = sorted(set(range(N)) - set(edge_index[1].tolist()))
    if missing:  # their scatter has no output size: every node must receive an edge
        raise ValueError(f"nodes {missing[:10]} are on no edge; the authors' code needs every "
                         "node to receive a message")
    rest = torch.as_tensor(np.asarray(arrays["rest_pos"]), dtype=torch.float32)
    static = {"edge_index": edge_index, "node_type": node_type[:, None].float(),
              "one_hot_node_type": torch.nn.functional.one_hot(node_type, N_TYPES).float(),
              "mesh_edge_attr": relative(rest, edge_index)}
    out = []
    for b in range(len(arrays["pos"])):
        pos = torch.as_tensor(np.asarray(arrays["pos"][b]), dtype=torch.float32)
        T = len(pos)
        youngs = torch.full((N, 1), float(arrays["youngs"][b]) / YOUNGS_SCALE)
        traj = {"world_pos": pos, "velocity": authors_velocity(pos)}
        for key, value in {**static, "youngs": youngs}.items():
            traj[key] = value.expand(T, *value.shape)
        out.append(traj)
    return out


class Moments:
    """Running count, sum and sum of squares per feature (float64), for the mean and the
    unbiased standard deviation of rows added in chunks."""

    def __init__(self):
        self.n, self.s, self.s2 = 0, 0.0, 0.0

    def add(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).double()
        self.n += len(x)
        self.s = self.s + x.sum(0)
        self.s2 = self.s2 + (x * x).sum(0)

    def mean_std(self) -> tuple[torch.Tensor, torch.Tensor]:
        mean = self.s / self.n
        var = ((self.s2 - self.n * mean * mean) / max(self.n - 1, 1)).clamp_min(0)
        return mean.float(), var.sqrt().clamp_min(STD_MIN).float()


def authors_stats(train: list[dict]) -> dict:
    """The statistics dict their model reads (``vel_mean``, ``vel_std``, ``youngs_*``,
    ``edge_*`` for the current edge features, ``mesh_edge_*`` for the rest ones, and the
    feature sizes ``node_size`` = 1 + 2, ``edge_size`` = 4 + 4) over the converted training
    trajectories ``train``."""
    m = {k: Moments() for k in ("vel", "youngs", "edge", "mesh_edge")}
    for traj in train:
        ei = traj["edge_index"][0]
        m["vel"].add(traj["velocity"])
        m["youngs"].add(traj["youngs"])
        m["edge"].add(relative(traj["world_pos"], ei))
        m["mesh_edge"].add(traj["mesh_edge_attr"])
    stats = {}
    for k, mo in m.items():
        stats[f"{k}_mean"], stats[f"{k}_std"] = mo.mean_std()
    first = train[0]
    stats["node_size"] = torch.tensor([first["youngs"].shape[-1] + first["one_hot_node_type"].shape[-1]])
    stats["edge_size"] = torch.tensor([4 + first["mesh_edge_attr"].shape[-1]])
    return stats
