"""MeshODENet and its training engine (torch). Never imports ``groundtruth``: arrays in the
store's layout (docs/FORMAT.md) come in as plain dicts.

Public names: ``Mesh``, ``Trajectories`` (data), ``TrajectoryModel`` (the model interface),
``MeshODENet``, ``MeshODENetConfig``, ``INTEGRATORS``, ``GRADIENT_MODES``, ``odesolve``,
``MODELS``, ``TrainConfig``, ``fit``.
"""

from meshodenet.gnn.meshodenet import MeshODENet, MeshODENetConfig
from meshodenet.integrators.explicit import GRADIENT_MODES, INTEGRATORS, odesolve
from meshodenet.interface import TrajectoryModel
from meshodenet.mesh.data import DataError, Mesh, Trajectories
from meshodenet.registry import MODELS, get_model_spec, load_model, register_model
from meshodenet.training.train import TrainConfig, fit

__all__ = ["DataError", "Mesh", "Trajectories", "GRADIENT_MODES", "INTEGRATORS", "odesolve",
           "TrajectoryModel", "MeshODENet", "MeshODENetConfig", "MODELS", "get_model_spec",
           "load_model", "register_model", "TrainConfig", "fit"]
