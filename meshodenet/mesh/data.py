"""Plain arrays in, torch tensors out: the mesh and the trajectories a model sees.

``meshodenet`` never reads the store itself (that is ``benchmarks``' job); it is handed the
store's arrays as a dict (layout in ``docs/FORMAT.md``) and checks them here, with errors that
name the array, its shape and the expected one.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

N_NODE_TYPES = 2  # 0 free, 1 clamped (docs/FORMAT.md)
#: what each ``Mesh.kind`` is, for messages
KIND_NAMES = {"line": "a rod", "triangle": "a plate or shell"}
MESH_KEYS = ("edges", "cells", "node_type", "rest_pos", "mass", "force", "damping")
TRAJECTORY_KEYS = ("t", "pos", "vel", "youngs")


class DataError(ValueError):
    """Arrays that do not have the documented shapes, or that belong to another mesh."""


def check_arrays(arrays: dict, name: str = "arrays") -> None:
    """Raise ``DataError`` unless ``arrays`` holds the store's keys with consistent shapes."""
    missing = [k for k in MESH_KEYS + TRAJECTORY_KEYS if k not in arrays]
    if missing:
        raise DataError(f"{name}: missing arrays {missing}; expected the store's layout "
                        "(docs/FORMAT.md)")
    pos = np.asarray(arrays["pos"])
    if pos.ndim != 4 or pos.shape[-1] != 3:
        raise DataError(f"{name}: pos has shape {pos.shape}, expected (B, T, N, 3)")
    B, T, N, _ = pos.shape
    want = {"vel": (B, T, N, 3), "t": (T,), "youngs": (B,), "node_type": (N,),
            "rest_pos": (N, 3), "mass": (N,), "force": (N, 3), "damping": (N,)}
    bad = [f"{k} has shape {np.shape(arrays[k])}, expected {s}" for k, s in want.items()
           if np.shape(arrays[k]) != s]
    for k, width in (("edges", 2), ("cells", 3)):
        a = np.asarray(arrays[k])
        if a.ndim != 2 or a.shape[1] != width:
            bad.append(f"{k} has shape {a.shape}, expected (*, {width})")
        elif a.size and (a.min() < 0 or a.max() >= N):
            bad.append(f"{k} refers to nodes outside [0, {N})")
    if bad:
        raise DataError(f"{name}: inconsistent arrays: " + "; ".join(bad))
    if T < 2:
        raise DataError(f"{name}: needs at least 2 frames, got t of shape {(T,)}")
    if not np.all(np.diff(arrays["t"]) > 0):
        raise DataError(f"{name}: times t must increase strictly")
    nt = np.asarray(arrays["node_type"])
    if nt.size and (nt.min() < 0 or nt.max() >= N_NODE_TYPES):
        raise DataError(f"{name}: node_type values must be in [0, {N_NODE_TYPES}), "
                        f"got {sorted(set(nt.tolist()))}")
    if len(arrays["edges"]) == 0:
        raise DataError(f"{name}: the mesh has no edges")


@dataclass(frozen=True)
class Mesh:
    """The static part of a case: topology, rest shape and loads (numpy, SI units).

    ``edges (E, 2)`` undirected, ``cells (M, 3)`` triangles (``M = 0`` for a rod),
    ``node_type (N,)`` (1 = clamped), ``rest_pos (N, 3)``, ``mass (N,)``, ``force (N, 3)`` and
    ``damping (N,)`` so that the external force on node i is ``force[i] - damping[i] * v[i]``.
    ``case`` and ``case_hash`` say where it came from.
    """

    edges: np.ndarray
    cells: np.ndarray
    node_type: np.ndarray
    rest_pos: np.ndarray
    mass: np.ndarray
    force: np.ndarray
    damping: np.ndarray
    case: str = ""
    case_hash: str = ""

    @classmethod
    def from_arrays(cls, arrays: dict, name: str = "arrays") -> Mesh:
        check_arrays(arrays, name)
        return cls(**{k: np.array(arrays[k]) for k in MESH_KEYS},
                   case=str(arrays.get("case", "")), case_hash=str(arrays.get("case_hash", "")))

    @property
    def n_nodes(self) -> int:
        return len(self.node_type)

    @property
    def kind(self) -> str:
        """``"line"`` (a rod: no cells) or ``"triangle"`` (a shell); selects the node features."""
        return "triangle" if len(self.cells) else "line"

    @property
    def dims(self) -> int:
        """2 for a mesh that stays in its plane (rest ``z`` constant, no load along ``z``: it
        moves in ``x-y`` only), else 3."""
        planar = np.ptp(self.rest_pos[:, 2]) == 0 and not np.any(self.force[:, 2])
        return 2 if planar else 3

    @property
    def length_scale(self) -> float:
        """The mesh's element size (m): the mean rest edge length of a line mesh, the square
        root of the mean rest triangle area of a triangle mesh (a mesh r times finer: 1/r)."""
        x = np.asarray(self.rest_pos, np.float64)
        if self.kind == "line":
            e = np.asarray(self.edges, np.int64)
            return float(np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1).mean())
        p = x[np.asarray(self.cells, np.int64)]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        return float(np.sqrt(area.mean()))

    def describe(self) -> str:
        """``"case 'rod_falling' (a line mesh: a rod, 21 nodes, 20 edges)"``, for messages."""
        return (f"case {self.case or '?'!r} (a {self.kind} mesh: {KIND_NAMES[self.kind]}, "
                f"{self.n_nodes} nodes, {len(self.edges)} edges)")

    def same_as(self, other: Mesh) -> bool:
        """Whether ``other`` holds this mesh's arrays (topology, rest shape, node types,
        masses, loads, damping), whatever the case it names."""
        return all(np.shape(getattr(self, k)) == np.shape(getattr(other, k))
                   and np.array_equal(getattr(self, k), getattr(other, k)) for k in MESH_KEYS)

    def signature(self) -> str:
        """sha256 of the topology and rest shape; a model only runs on meshes with its own."""
        h = hashlib.sha256()
        for a in (self.edges.astype(np.int64), self.cells.astype(np.int64),
                  self.node_type.astype(np.int64), np.round(self.rest_pos, 12)):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def to_dict(self) -> dict:
        """JSON-able form, stored in checkpoints so a run can be reloaded without the data."""
        d = {k: getattr(self, k).tolist() for k in MESH_KEYS}
        d.update(case=self.case, case_hash=self.case_hash)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Mesh:
        ints = {"edges", "cells", "node_type"}
        arrays = {k: np.asarray(d[k], np.int64 if k in ints else np.float64) for k in MESH_KEYS}
        arrays["cells"] = arrays["cells"].reshape(-1, 3)
        return cls(**arrays, case=d.get("case", ""), case_hash=d.get("case_hash", ""))

    def check_same(self, other: Mesh, what: str = "data") -> None:
        """Raise ``DataError`` if ``other`` is not this mesh or comes from another case (where
        only the training mesh will do; a rollout on another mesh of the same kind goes
        through ``TrajectoryModel.on_mesh``)."""
        other_case = bool(self.case and other.case and self.case != other.case)
        if other_case or other.signature() != self.signature():
            raise DataError(
                f"{what} is {other.describe()} but the model was trained on case "
                f"{self.case or '?'!r} ({self.n_nodes} nodes, {len(self.edges)} edges) and "
                "this needs its training mesh")


@dataclass(frozen=True)
class Trajectories:
    """Ground-truth trajectories as tensors: ``t (T,)`` s, ``pos, vel (B, T, N, 3)``,
    ``youngs (B,)`` Pa. Index with a tensor or slice to take a subset of trajectories."""

    t: torch.Tensor
    pos: torch.Tensor
    vel: torch.Tensor
    youngs: torch.Tensor

    @classmethod
    def from_arrays(cls, arrays: dict, dtype=torch.float32, device="cpu",
                    name: str = "arrays") -> Trajectories:
        check_arrays(arrays, name)
        conv = lambda k: torch.as_tensor(np.asarray(arrays[k], np.float64), dtype=dtype,
                                         device=device)
        return cls(conv("t"), conv("pos"), conv("vel"), conv("youngs"))

    def __len__(self) -> int:
        return self.pos.shape[0]

    @property
    def n_frames(self) -> int:
        return self.pos.shape[1]

    def subset(self, index) -> Trajectories:
        return Trajectories(self.t, self.pos[index], self.vel[index], self.youngs[index])

    def to(self, device=None, dtype=None) -> Trajectories:
        return Trajectories(*(a.to(device=device, dtype=dtype)
                              for a in (self.t, self.pos, self.vel, self.youngs)))


#: How ``TrainConfig.val_split`` carves the validation trajectories from the training file:
#: ``stratified`` (default) evenly over the sorted Young's moduli, ``random`` a seeded draw
#: (every run stored before ``val_split`` existed used it).
VAL_SPLITS = ("stratified", "random")


def _n_val(n: int, val_fraction: float) -> int:
    if not 0 <= val_fraction < 1:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction!r}")
    n_val = int(round(val_fraction * n))
    if val_fraction > 0 and n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    return n_val


def split_indices(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Carve a validation set from ``n`` training trajectories: ``(train_idx, val_idx)``, sorted.

    ``round(val_fraction * n)`` trajectories (at least one when ``val_fraction > 0`` and
    ``n >= 2``) drawn without replacement by ``numpy.random.default_rng(seed)``.
    """
    n_val = _n_val(n, val_fraction)
    perm = np.random.default_rng(seed).permutation(n)
    return np.sort(perm[n_val:]), np.sort(perm[:n_val])


def stratified_split(youngs, val_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Carve a validation set that spans the moduli: ``(train_idx, val_idx)``, sorted.

    The trajectories are sorted by Young's modulus (ties by index) and cut into ``n_val``
    strata of equal count (``n_val`` as in ``split_indices``); validation takes the middle
    trajectory of each stratum. Deterministic: no seed. The validation moduli then leave no
    gap wider than about one stratum between each other, half of one to the ends of the
    range, and the softest and stiffest trajectories stay in training.
    """
    y = np.asarray(youngs, dtype=np.float64)
    if y.ndim != 1 or not np.all(np.isfinite(y)):
        raise ValueError(f"youngs must be a 1-D array of finite moduli, got shape {y.shape}")
    n = len(y)
    n_val = _n_val(n, val_fraction)
    order = np.argsort(y, kind="stable")
    picks = np.floor((np.arange(n_val) + 0.5) * n / n_val).astype(int) if n_val else []
    val = np.sort(order[picks]) if n_val else np.zeros(0, dtype=np.int64)
    return np.setdiff1d(np.arange(n), val), val


def validation_split(youngs, val_fraction: float, method: str = "stratified",
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(train_idx, val_idx)`` of the training file's trajectories (moduli ``youngs``) by
    ``method`` (``VAL_SPLITS``): ``stratified_split``, or ``split_indices`` with ``seed``."""
    if method == "stratified":
        return stratified_split(youngs, val_fraction)
    if method == "random":
        return split_indices(len(np.atleast_1d(youngs)), val_fraction, seed)
    raise ValueError(f"val_split must be one of {', '.join(VAL_SPLITS)}, got {method!r}")
