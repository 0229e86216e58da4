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
    "line": (dict(epochs=12, lr=1e-3, lr_milestones=(8,), batch_size=32),
             dict(hidden=64, shooting=10)),
    "triangle": (dict(epochs=8, lr=1e-3, lr_milestones=(6,), batch_size=16),
                 dict(hidden=64, shooting=10)),
}


def meshodenet_presets(preset: str, kind: str) -> tuple[TrainConfig, MeshODENetConfig]:
    """``(TrainConfig, MeshODENetConfig)`` of ``preset`` for a mesh of ``kind``.

    - ``paper``: hidden 128, 1 message-passing layer, MLPs of 2 hidden layers, rk4 with the step
      equal to the sampling interval, whole-trajectory rollouts from the initial state, the
      paper's optimiser and schedule, one trajectory per step. Gradient mode ``checkpoint``
      (same gradient as direct backpropagation, bounded memory).
    - ``quick``: the same model family and loss, reduced where it costs least accuracy:
      hidden 64 (4x fewer multiply-adds per evaluation), multiple shooting with segments of
      10 frames restarted from ground truth (many more optimizer steps per unit of compute;
      the test rollout is still the whole trajectory from the initial state), several
      segments per step, lr 1e-3 divided by 10 for the last epochs, few epochs.
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
