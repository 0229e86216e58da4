"""Load user plugins that register cases or models without editing the package.

Three sources, loaded in this order (each at most once per process):

1. installed packages exposing the entry-point group ``meshbench.plugins`` (the entry point
   may name a module, whose import registers things, or a callable, which is called);
2. files listed in ``$MESHBENCH_PLUGINS`` (separated by ``os.pathsep``);
3. files given with ``meshbench --plugin FILE`` (repeatable).

A plugin file is ordinary Python, e.g.::

    from benchmarks.suite.registry import register_case
    from groundtruth.cases import RodCase
    register_case(RodCase(id="rod_long", n_nodes=31, length=0.2))
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path

ENTRY_POINT_GROUP = "meshbench.plugins"
_loaded: set[str] = set()


class PluginError(ValueError):
    """A plugin file is missing or raised while being imported."""


def load_file(path: str | os.PathLike) -> None:
    """Import a plugin file once; it is kept in ``sys.modules`` so worker processes see it."""
    path = Path(path).expanduser().resolve()
    key = str(path)
    if key in _loaded:
        return
    if not path.is_file() or path.suffix != ".py":
        raise PluginError(f"plugin file {str(path)!r} does not exist or is not a .py file")
    name = f"meshbench_plugin_{path.stem}_{hashlib.sha1(key.encode()).hexdigest()[:8]}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as e:
        del sys.modules[name]
        raise PluginError(f"plugin {str(path)!r} failed to load: {type(e).__name__}: {e}") from e
    _loaded.add(key)


def load_entry_points() -> None:
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        key = f"ep:{ep.name}={ep.value}"
        if key in _loaded:
            continue
        try:
            obj = ep.load()
            if callable(obj):
                obj()
        except Exception as e:
            raise PluginError(f"plugin entry point {ep.name!r} ({ep.value}) failed: "
                              f"{type(e).__name__}: {e}") from e
        _loaded.add(key)


def loaded_files() -> list[str]:
    """The plugin files loaded so far in this process (to load again in worker processes)."""
    return sorted(k for k in _loaded if not k.startswith("ep:"))


def load_all(files=()) -> None:
    """Entry points, then ``$MESHBENCH_PLUGINS``, then ``files``."""
    load_entry_points()
    env = os.environ.get("MESHBENCH_PLUGINS", "")
    for f in [p for p in env.split(os.pathsep) if p.strip()] + list(files or ()):
        load_file(f)
