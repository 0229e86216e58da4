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
    "triangle": (dict(epochs=24, lr=1e-3, lr_milestones=(18,), batch_size=4, grad_clip=1.0,
                      max_batches=24, weight_decay=0.0),
                 dict(hidden=32, shooting=16, shooting_epochs=0, rest_position=True)),
}


def meshodenet_presets(preset: str, kind: str) -> tuple[TrainConfig, MeshODENetConfig]:
    """``(TrainConfig, MeshODENetConfig)`` of ``preset`` for a mesh of ``kind``.

    - ``paper``: hidden 128, 1 message-passing layer, MLPs of 2 hidden layers, rk4 with the step
      equal to the sampling interval, whole-trajectory rollouts from the initial state, the
      paper's optimiser and schedule, one trajectory per step. Gradient mode ``checkpoint``
      (same gradient as direct backpropagation, bounded memory).
    - ``quick``: the same model family, loss and integrator, reduced where it costs least:
      a narrower GNN (hidden 64 for rods, 32 for plates), lr 1e-3 with gradient clipping
      (norm 1) and a last stretch at 1e-4, few epochs, and multiple shooting: windows
      restarted from the ground truth. Rods: windows of 10 intervals, 8 per step, the
      horizon doubling every epoch until whole trajectories are rolled out from the initial
      state (10, 20, 40, 80, 160 intervals, then 5 epochs of whole 200-frame rollouts); the
      rod learns (test RMSE 4.2 mm, no motion 62.9 mm, 6 min on a 2-core CPU). Plates:
      windows of 16 intervals throughout, 4 per step, 24 steps (a random subset of the
      windows) per epoch, 24 epochs (1e-4 from epoch 19), no weight decay. On the
      validation split of the in-plane ``plate_cantilever`` this reached 0.115 m (seed 0;
      0.111 m at seed 1; no motion 0.1705 m) in 301-323 s on one thread, where the former
      plate preset (32-interval windows doubling every epoch to whole rollouts, 8 steps of 8
      per epoch, 6 epochs, weight decay 5e-4) stayed above standing still (0.206 m): the
      paper's coupled weight decay held the model at almost no acceleration, and growing the
      windows at lr 1e-3 made its rollouts diverge. Reasoning and every experiment:
      docs/TRAINING.md, "The in-plane plate". Plates also feed the nodes' rest coordinates
      (``rest_position``; seed 0, validation: 116 -> 70 mm; docs/TRAINING.md, "Rest
      coordinates for every model").
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
