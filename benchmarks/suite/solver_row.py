"""``solver_h``: the case's own solver stepped once per saved interval, a reference row.

From each trajectory's initial state and modulus, the case's ``MechanicalSystem``
(``case.system(youngs)``) is integrated by ``groundtruth.implicit.simulate`` with backward
Euler at ``h_k = t[k+1] - t[k]``: one implicit step per saved interval, solved by Newton with
the case's own tolerance (``newton_rtol``) and predictor. A step whose Newton fails is an
error (``ConvergenceError`` naming the trajectory, the time, ``h`` and the residual), never a
smaller step. The row is the accuracy a perfect vector field stepped implicitly at the
sampling interval can reach, and the classical method a learned simulator must beat in speed
at equal accuracy.

It is a ``TrajectoryModel`` like any other (torch tensors in and out, any ``t``), so metrics,
figures, animations and longer rollouts use it unchanged. It learns nothing
(``trainable = False``): ``save_untrained`` writes its run directory instead of
``meshodenet.training.train.fit``, so that ``meshbench run`` records, reuses and compares it. Its
columns: ``integrator = backward_euler``, ``grad_mode = none``.

Importing this module registers ``solver_h`` in ``meshodenet.registry.MODELS``; the
benchmarks side imports it wherever it looks a model up (``benchmarks.suite.runs
.get_model_spec``). ``meshodenet`` itself never imports ``groundtruth``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.suite.registry import get_case
from groundtruth.implicit import ConvergenceError, simulate
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import DataError, Mesh
from meshodenet.registry import MODELS, ModelSpec, register_model
from meshodenet.training.presets import check_int, check_preset
from meshodenet.training.train import FitResult, TrainConfig, model_info, save_checkpoint, write_history

MODEL_ID = "solver_h"


@dataclass(frozen=True)
class SolverRowConfig:
    """``solver_h`` has nothing to learn. ``max_iter``: Newton iterations per saved interval
    before the step counts as failed."""

    max_iter: int = 30

    def __post_init__(self):
        check_int(self, "max_iter", 1)


def solver_presets(preset: str, kind: str) -> tuple[TrainConfig, SolverRowConfig]:
    """The same configs for every preset and mesh kind. The ``TrainConfig`` (one epoch) is
    never used, nothing is trained; it keeps the run's configuration complete."""
    check_preset(preset)
    return TrainConfig(epochs=1), SolverRowConfig()


class SolverRow(TrajectoryModel):
    """The case of ``mesh.case`` (a registered case id) stepped by backward Euler once per
    saved interval. Shapes as ``TrajectoryModel.rollout``; computed in float64 with numpy
    on the CPU, returned in the dtype and on the device of ``x0``."""

    name = MODEL_ID
    trainable = False
    integrator_id = "backward_euler"
    grad_mode_id = "none"

    def __init__(self, mesh: Mesh, config: SolverRowConfig, train=None):
        super().__init__(mesh, config)
        self.case = case_of(mesh)

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")  # numpy computes; there are no parameters to place

    def n_training_samples(self, data) -> int:
        return 0

    def training_loss(self, data, samples, generator):
        raise ValueError(f"model {MODEL_ID!r} has nothing to train (trainable = False)")

    def settings(self, t: np.ndarray):
        """The case's Newton settings with one step per interval of ``t`` and no halving."""
        h = np.diff(t)
        if t.ndim != 1 or len(t) < 1 or not np.all(np.isfinite(t)) or np.any(h <= 0):
            raise ValueError(f"{MODEL_ID}: t must be finite and strictly increasing (T,), "
                             f"got shape {tuple(t.shape)}")
        # dt just above the longest interval: simulate() then takes exactly one step of
        # length t[k+1] - t[k] per interval (ceil(interval / dt) = 1)
        dt = float(h.max()) * (1 + 1e-9) if len(h) else self.case.save_dt
        return dataclasses.replace(self.case.solver_settings, dt=dt, max_halvings=0,
                                   max_iter=self.config.max_iter)

    @torch.no_grad()
    def rollout(self, x0, v0, youngs, t):
        tt = t.detach().cpu().double().numpy()
        settings = self.settings(tt)
        out = [self.rollout_one(b, x0[b], v0[b], float(youngs[b]), tt, settings)
               for b in range(x0.shape[0])]
        pos = torch.stack([torch.from_numpy(p) for p, _ in out]).to(x0)
        vel = torch.stack([torch.from_numpy(v) for _, v in out]).to(x0)
        return pos, vel

    def rollout_one(self, b: int, x0, v0, youngs: float, t: np.ndarray, settings):
        """``(pos, vel)`` ``(T, N, 3)`` float64 of trajectory ``b`` of a batch."""
        q0 = x0.detach().cpu().double().numpy().ravel()
        w0 = v0.detach().cpu().double().numpy().ravel()
        try:
            pos, vel, _ = simulate(self.case.system(youngs), q0, w0, t, settings)
        except ConvergenceError as e:
            raise ConvergenceError(
                f"{MODEL_ID} on {self.case.id}, trajectory {b} of the batch (Y = {youngs:.6g} "
                f"Pa): backward Euler at the sampling interval does not converge: {e}") from None
        n = x0.shape[0]
        return pos.reshape(-1, n, 3), vel.reshape(-1, n, 3)


def case_of(mesh: Mesh):
    """The registered case ``mesh`` comes from (``mesh.case``); ``DataError`` when the mesh
    names no registered case, or its case's parameters or nodes differ from the registered
    one's."""
    if not mesh.case:
        raise DataError(f"{MODEL_ID} needs the case a mesh comes from (Mesh.case) to step its "
                        "physics; this mesh names none")
    case = get_case(mesh.case)
    if mesh.case_hash and mesh.case_hash != case.hash():
        raise DataError(f"{MODEL_ID}: the mesh comes from case {mesh.case!r} with parameter "
                        f"hash {mesh.case_hash[:12]}, the registered case has "
                        f"{case.hash()[:12]}; regenerate the data (meshbench generate "
                        f"{mesh.case} --force)")
    if not np.array_equal(case.node_type(), mesh.node_type):
        nt = case.node_type()
        raise DataError(f"{MODEL_ID}: case {mesh.case!r} has {len(nt)} nodes, "
                        f"{int((nt == 1).sum())} clamped; the mesh {mesh.n_nodes}, "
                        f"{int((mesh.node_type == 1).sum())} clamped")
    return case


def save_untrained(model: TrajectoryModel, run_dir) -> FitResult:
    """For a model with nothing to learn (``trainable = False``), what ``fit`` leaves in
    ``run_dir``: ``best.pt`` and ``last.pt`` (its state dict, epoch 0, no optimizer state)
    and a ``history.csv`` without rows. Returns ``fit``'s result for 0 epochs."""
    run_dir = Path(run_dir)
    state = {"epoch": 0, "best_val_rmse": math.nan, "best_epoch": 0, "history": [],
             "wall_time_s": 0.0, "cpu_time_s": 0.0, "budgets": []}
    ck = {"model": model.state_dict(), "optimizer": {}, "scheduler": {},
          "generator": torch.Generator().get_state(), "torch_rng": torch.get_rng_state(),
          **state, "extra": {}, "model_info": model_info(model)}
    for name in ("best.pt", "last.pt"):
        save_checkpoint(run_dir / name, ck)
    write_history(run_dir / "history.csv", [])
    return FitResult(0, math.nan, 0, 0.0, [])


#: What a run of a model with nothing to learn records instead of its training preset's.
UNTRAINED_RECORD = {"epochs": 0, "best_epoch": 0, "train_wall_time_s": 0.0}

if MODEL_ID not in MODELS:
    register_model(MODEL_ID, ModelSpec(
        SolverRow, SolverRowConfig, solver_presets,
        "the case's own solver, backward Euler once per saved interval (Newton on the exact "
        "physics): a reference row, nothing learned (benchmarks/suite/solver_row.py)"))
