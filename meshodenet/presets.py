"""Presets: ``paper`` (the paper's settings), ``quick`` (a documented reduction that trains
both cases on a 2-core CPU in about 20 minutes and still learns), ``smoke`` (seconds, tests).

The paper's schedule depends on the case: rods (line meshes) 400 epochs with the learning rate
divided by 10 every 100 epochs, plates (triangle meshes) 600 epochs divided at 200 and 400.
The paper does not give a batch size; ``paper`` uses one trajectory per optimizer step, which
also matches the authors' cost per epoch.
"""

from __future__ import annotations

from meshodenet.model import MeshODENetConfig
from meshodenet.train import TrainConfig

PRESETS = ("paper", "quick", "smoke")
PAPER_SCHEDULES = {
    "line": {"epochs": 400, "lr_milestones": (100, 200, 300)},
    "triangle": {"epochs": 600, "lr_milestones": (200, 400)},
}


def check_preset(preset: str) -> None:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")


def paper_train_config(kind: str) -> TrainConfig:
    """The paper's optimiser: Adam, lr 1e-4, weight decay 5e-4, its step schedule."""
    if kind not in PAPER_SCHEDULES:
        raise ValueError(f"no paper schedule for mesh kind {kind!r}; valid: "
                         f"{', '.join(PAPER_SCHEDULES)}")
    return TrainConfig(lr=1e-4, weight_decay=5e-4, lr_gamma=0.1, batch_size=1,
                       **PAPER_SCHEDULES[kind])


# ``quick``: see meshodenet_presets' docstring for the reasoning behind each number.
QUICK = {
    "line": (dict(epochs=10, lr=1e-3, lr_milestones=(9,), batch_size=8, grad_clip=1.0),
             dict(hidden=64, shooting=10, shooting_epochs=1)),
    "triangle": (dict(epochs=6, lr=1e-3, lr_milestones=(5,), batch_size=8, grad_clip=1.0,
                      max_batches=8),
                 dict(hidden=32, shooting=32, shooting_epochs=1)),
}


def meshodenet_presets(preset: str, kind: str) -> tuple[TrainConfig, MeshODENetConfig]:
    """``(TrainConfig, MeshODENetConfig)`` of ``preset`` for a mesh of ``kind``.

    - ``paper``: hidden 128, 1 message-passing layer, MLPs of 2 hidden layers, rk4 with the step
      equal to the sampling interval, whole-trajectory rollouts from the initial state, the
      paper's optimiser and schedule, one trajectory per step. Gradient mode ``checkpoint``
      (same gradient as direct backpropagation, bounded memory).
    - ``quick``: the same model family, loss and integrator, reduced where it costs least:
      a narrower GNN (hidden 64 for rods, 32 for plates), lr 1e-3 with gradient clipping
      (norm 1) and a last epoch at 1e-4, few epochs, and a multiple-shooting curriculum:
      windows of 10 (rod) / 32 (plate) intervals restarted from the ground truth, 8 windows
      per step, the horizon doubling every epoch until whole trajectories are rolled out from
      the initial state (rod: 10, 20, 40, 80, 160 intervals, then 5 epochs of whole 200-frame
      rollouts; plate: 32 ... 256, then 2 epochs of whole 500-frame rollouts). Plates cap each
      epoch at 8 steps (a random subset of the windows) to fit the time budget. Measured on
      a 2-core CPU: the rod learns (test RMSE 4.2 mm, no motion 62.9 mm, 6 min); the plate
      does not: the in-plane plate_cantilever stays at the no-motion error (test RMSE 0.156-0.175 m
      over 3 seeds, no motion 0.136 m, 13-16 min loaded) -- see README and docs/TRAINING.md.
    - ``smoke``: a tiny model, 2 epochs, for tests.
    """
    check_preset(preset)
    base = paper_train_config(kind)
    if preset == "paper":
        return base, MeshODENetConfig()
    if preset == "quick":
        t, m = QUICK[kind]
        return TrainConfig(**{**_fields(base), **t}), MeshODENetConfig(**m)
    return (TrainConfig(**{**_fields(base), "epochs": 2, "lr": 1e-3, "lr_milestones": (),
                           "batch_size": 4, "max_batches": 3}),
            MeshODENetConfig(hidden=16, mlp_hidden_layers=1, shooting=5))


def _fields(cfg) -> dict:
    from dataclasses import asdict

    return asdict(cfg)
