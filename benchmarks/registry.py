"""Registries keyed by stable snake_case ids; the ids are exactly the strings in CSV columns."""

from __future__ import annotations

from groundtruth.cases import RodCase

CASES: dict = {
    "rod_falling": RodCase(),
}


class RegistryError(KeyError):
    """Unknown id in a registry; the message lists the valid ids."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def lookup(registry: dict, key: str, kind: str = "case"):
    """``registry[key]`` with an error that names the bad key and lists the valid ones."""
    try:
        return registry[key]
    except KeyError:
        valid = ", ".join(sorted(registry)) or "(none registered)"
        raise RegistryError(f"unknown {kind} id {key!r}; valid ids: {valid}") from None


def get_case(case_id: str):
    return lookup(CASES, case_id, "case")


def register_case(case, overwrite: bool = False):
    """Add a case object (with an ``id``) to ``CASES``; refuses to replace one silently."""
    if case.id in CASES and not overwrite:
        raise ValueError(f"case id {case.id!r} is already registered; pass overwrite=True")
    CASES[case.id] = case
    return case


# The torch side's registries, re-exported without importing torch until first used, so that
# data commands (generate, simulate, export) run where torch is not installed.
_TORCH_SIDE = {"MODELS": "meshodenet.registry", "INTEGRATORS": "meshodenet.integrators"}


def __getattr__(name: str):
    if name in _TORCH_SIDE:
        import importlib

        return getattr(importlib.import_module(_TORCH_SIDE[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
