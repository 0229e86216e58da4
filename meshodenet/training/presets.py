"""What the model modules share: the preset names, the paper's optimiser and schedule, and the
checks of config fields (errors name ``Owner.field`` and the bad value).

Presets: ``paper`` (the paper's settings), ``quick`` (a reduction that trains each case on a
2-core CPU in minutes), ``smoke`` (seconds, tests). The paper's schedule depends on the mesh:
rods (line meshes) 400 epochs with the learning rate divided by 10 every 100 epochs, plates
(triangle meshes) 600 epochs divided at 200 and 400; it gives no batch size.
"""

from __future__ import annotations

import math
from dataclasses import asdict

from meshodenet.training.train import TrainConfig

PRESETS = ("paper", "quick", "smoke")
PAPER_SCHEDULES = {
    "line": {"epochs": 400, "lr_milestones": (100, 200, 300)},
    "triangle": {"epochs": 600, "lr_milestones": (200, 400)},
}
#: ``engine`` of a model config: how its network is evaluated, ``fast`` (``meshodenet.gnn.fast``,
#: hand-written forward and backward) or ``reference`` (the modules' own forward,
#: ``meshodenet.gnn.reference``); the same numbers up to float round-off, and ``reference``
#: reproduces results computed before the fast path bit for bit.
ENGINES = ("fast", "reference")
#: ``message_passing`` of a model config: the sum at the receivers in the layers' own forward
#: (the ``reference`` engine only): ``pyg`` (``torch_geometric.utils.scatter``) or
#: ``handwritten`` (``index_add_``, the code before PyG).
MESSAGE_PASSING = ("pyg", "handwritten")


def check_preset(preset: str) -> None:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")


def paper_train_config(kind: str) -> TrainConfig:
    """The paper's optimiser: Adam, lr 1e-4, weight decay 5e-4, its step schedule; one sample
    per optimizer step."""
    if kind not in PAPER_SCHEDULES:
        raise ValueError(f"no paper schedule for mesh kind {kind!r}; valid: "
                         f"{', '.join(PAPER_SCHEDULES)}")
    return TrainConfig(lr=1e-4, weight_decay=5e-4, lr_gamma=0.1, batch_size=1,
                       **PAPER_SCHEDULES[kind])


def preset_configs(preset: str, kind: str, quick: dict, config_cls, smoke: dict,
                   paper: dict | None = None) -> tuple:
    """``(TrainConfig, config)`` of the usual presets for a mesh of ``kind``: ``paper`` the
    paper's optimiser with ``config_cls(**paper.get(kind, {}))`` (``paper`` None: the config's
    defaults on every kind); ``quick`` ``quick[kind] = (TrainConfig fields,
    config fields)`` over the paper's optimiser; ``smoke`` 2 epochs of 3 steps of 4 samples at
    lr 1e-3 with ``config_cls(**smoke)``, validated on a seeded random trajectory (the smoke
    runs check plumbing: on ``rod_cantilever``'s four trajectories the stratified split trains
    on the softest rod, and a six-step MeshODENet then diverges on every rollout)."""
    check_preset(preset)
    base = asdict(paper_train_config(kind))
    if preset == "paper":
        return TrainConfig(**base), config_cls(**(paper or {}).get(kind, {}))
    if preset == "quick":
        t, m = quick[kind]
        return TrainConfig(**{**base, **t}), config_cls(**m)
    return (TrainConfig(**{**base, "epochs": 2, "lr": 1e-3, "lr_milestones": (),
                           "batch_size": 4, "max_batches": 3, "val_split": "random"}),
            config_cls(**smoke))


def check_int(obj, name: str, lo: int) -> None:
    """``obj.name`` an int ``>= lo`` (not a bool)."""
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{type(obj).__name__}.{name} must be an int >= {lo}, got {v!r}")


def check_choice(obj, name: str, valid) -> None:
    """``obj.name`` one of ``valid``."""
    v = getattr(obj, name)
    if v not in valid:
        raise ValueError(f"{type(obj).__name__}.{name} must be one of "
                         f"{', '.join(sorted(valid))}; got {v!r}")


def check_engine(obj) -> None:
    """``obj.engine`` in ``ENGINES`` and ``obj.message_passing`` in ``MESSAGE_PASSING``."""
    check_choice(obj, "engine", ENGINES)
    check_choice(obj, "message_passing", MESSAGE_PASSING)


def check_fraction(owner: str, name: str, value) -> None:
    """A number in ``[0, 1]`` (not a bool), else one line naming ``owner.name`` and the value."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or not 0 <= value <= 1:
        raise ValueError(f"{owner}.{name} must be a number in [0, 1], got {value!r}")


def check_nonnegative(owner: str, name: str, value) -> None:
    """A finite number ``>= 0`` (not a bool), else one line naming ``owner.name`` and the value."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"{owner}.{name} must be a finite number >= 0, got {value!r}")
