"""Cases: frozen dataclasses that say what to simulate and how to sample the datasets.

A case builds a ``MechanicalSystem`` for a Young's modulus, knows its mesh, rest shape, save
times and solver settings, samples the moduli of its train/test splits from fixed seeds, and
has a stable hash of everything that determines its data. One module per case family
(``rod``, ``plate``), the shared base in ``base``. Cases are registered by id in
``benchmarks.suite.registry.CASES``; variants are made with ``dataclasses.replace``, finer
meshes of the same physics with ``refined(r)`` (id ``CASE@rN``, docs/SCALE.md).
"""

from groundtruth.cases.base import (
    RESOLUTION_MARK,
    SOLVER_VERSION,
    SPLITS,
    CaseBase,
    check_resolution,
    check_youngs,
    resolution_id,
    split_resolution_id,
)
from groundtruth.cases.plate import InPlanePlateCase, PlateCase
from groundtruth.cases.rod import RodCase

__all__ = ["RESOLUTION_MARK", "SOLVER_VERSION", "SPLITS", "CaseBase", "InPlanePlateCase",
           "PlateCase", "RodCase", "check_resolution", "check_youngs", "resolution_id",
           "split_resolution_id"]
