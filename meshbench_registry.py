"""The one error of every registry lookup (cases, suites, models, integrators), and the lookup.

A module of its own, with no dependencies: ``meshodenet`` (torch, never the glue) and
``benchmarks`` (the glue, torch-free until a model is needed) both raise it.
"""

from __future__ import annotations


class RegistryError(KeyError):
    """Unknown id in a registry; the message lists the valid ids."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def lookup(registry: dict, key: str, kind: str):
    """``registry[key]`` with an error that names the bad key and lists the valid ones."""
    try:
        return registry[key]
    except KeyError:
        valid = ", ".join(sorted(registry)) or "(none registered)"
        raise RegistryError(f"unknown {kind} id {key!r}; valid ids: {valid}") from None
