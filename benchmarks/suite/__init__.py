"""The suite: case and suite registries, data generation, the runner, metrics and figures.

The plugin API is re-exported here: ``from benchmarks.suite import register_case, RunSpec,
Suite, register_suite``.
"""

from benchmarks.suite.registry import RegistryError, get_case, register_case
from benchmarks.suite.suites import RunSpec, Suite, register_suite

__all__ = ["RegistryError", "RunSpec", "Suite", "get_case", "register_case", "register_suite"]
