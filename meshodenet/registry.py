"""Registries of the torch side, keyed by the stable ids used in CSV columns.

``MODELS`` maps a model id to its ``ModelSpec``, built from the model modules of
``meshodenet.gnn`` and ``meshodenet.energy`` (one per model: config, presets, model); a user adds
a model from their own file with ``register_model``. ``INTEGRATORS`` is re-exported from
``meshodenet.integrators.explicit``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path

from meshbench_registry import lookup
from meshodenet.energy.model import EnergyConfig, ImplicitEnergy, energy_presets
from meshodenet.energy.model_dissipation import (
    DissipationConfig,
    ImplicitEnergyDissipation,
    dissipation_presets,
)
from meshodenet.gnn.imex import ImexConfig, MeshODENetIMEX, imex_presets
from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig, meshodenet_presets
from meshodenet.gnn.mgn import MeshGraphNet, MeshGraphNetConfig, mgn_presets
from meshodenet.gnn.unrolled import UnrolledMGN, UnrolledMGNConfig, unrolled_mgn_presets
from meshodenet.integrators.explicit import INTEGRATORS
from meshodenet.mesh.data import Mesh


@dataclass(frozen=True)
class ModelSpec:
    """A registered model: its ``TrajectoryModel`` class, its config dataclass, and
    ``presets(preset, mesh_kind) -> (TrainConfig, config)``."""

    model_cls: type
    config_cls: type
    presets: Callable
    description: str = ""

    def build(self, mesh: Mesh, config, train=None):
        return self.model_cls(mesh, config, train)

    def config_from_dict(self, d: dict):
        """The config dataclass from its JSON form (lists back to tuples where declared)."""
        names = {f.name for f in fields(self.config_cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"{self.config_cls.__name__} has no fields {unknown}; valid: "
                             f"{', '.join(sorted(names))}")
        return self.config_cls(**{k: tuple(v) if isinstance(v, list) else v
                                  for k, v in d.items()})


MODELS: dict = {
    "meshodenet": ModelSpec(MeshODENet, MeshODENetConfig, meshodenet_presets,
                            "graph neural ODE: GNN acceleration field integrated over the "
                            "whole rollout (paper section 2.2)"),
    "mgn": ModelSpec(MeshGraphNet, MeshGraphNetConfig, mgn_presets,
                     "MeshGraphNet: autoregressive one-step GNN (Pfaff et al. 2021; the paper's "
                     "baseline, section 3)"),
    "meshodenet_imex": ModelSpec(MeshODENetIMEX, ImexConfig, imex_presets,
                                 "MeshODENet's GNN with the case's linear drag implicit: "
                                 "semi-implicit Euler, one evaluation per interval "
                                 "(docs/TRAINING.md)"),
    "mgn_unrolled": ModelSpec(UnrolledMGN, UnrolledMGNConfig, unrolled_mgn_presets,
                              "MeshGraphNet trained through short rollouts of its own "
                              "(docs/MGN.md)"),
    "implicit_energy": ModelSpec(ImplicitEnergy, EnergyConfig, energy_presets,
                                 "a learned elastic energy over edges and rod hinges with the "
                                 "case's masses, loads and drag, one backward-Euler step per "
                                 "interval (docs/ENERGY.md)"),
    "implicit_energy_dissipation": ModelSpec(
        ImplicitEnergyDissipation, DissipationConfig, dissipation_presets,
        "implicit_energy told less: its learned energy with a learned non-negative "
        "dissipation of invariant features in place of the case's drag; only masses and "
        "loads given (docs/ENERGY.md)"),
}

__all__ = ["MODELS", "INTEGRATORS", "ModelSpec", "get_model_spec", "register_model",
           "load_model"]


def get_model_spec(name: str) -> ModelSpec:
    """``MODELS[name]``; an unknown id raises ``RegistryError`` listing the valid ones."""
    return lookup(MODELS, name, "model")


def register_model(name: str, spec: ModelSpec, overwrite: bool = False) -> ModelSpec:
    if name in MODELS and not overwrite:
        raise ValueError(f"model id {name!r} is already registered; pass overwrite=True")
    MODELS[name] = spec
    return spec


def load_model(checkpoint: str | Path, device="cpu"):
    """Rebuild the model saved in a checkpoint written by ``meshodenet.training.train.fit``."""
    from meshodenet.training.train import load_checkpoint

    ck = load_checkpoint(Path(checkpoint), device)
    info = ck["model_info"]
    spec = get_model_spec(info["name"])
    model = spec.build(Mesh.from_dict(info["mesh"]), spec.config_from_dict(info["config"]))
    model.load_state_dict(ck["model"])
    return model.to(device), ck
