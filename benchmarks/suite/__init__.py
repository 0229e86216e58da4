"""The suite: case and suite registries, data generation, the runner, metrics and figures.

The plugin API is importable from here: ``from benchmarks.suite import register_case, RunSpec,
Suite, register_suite`` (also ``get_case``, ``RegistryError``).
"""

import importlib

# Resolved on first use: importing a submodule (``procs`` before the kernel settings are
# pinned) must not load the registry and numpy with it.
_API = {"RegistryError": "registry", "get_case": "registry", "register_case": "registry",
        "RunSpec": "suites", "Suite": "suites", "register_suite": "suites"}
__all__ = sorted(_API)


def __getattr__(name):
    if name not in _API:
        raise AttributeError(f"module 'benchmarks.suite' has no attribute {name!r}")
    return getattr(importlib.import_module(f"benchmarks.suite.{_API[name]}"), name)
