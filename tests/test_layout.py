"""The layout of the packages: no import circle (the static import graph of every ``import``
and ``from ... import`` statement, those inside functions included, has no cycle), no module
over 650 lines, the plugin API where the docs say it is.

The import arrows, pinned. Between the top-level packages: ``groundtruth`` (numpy, scipy)
imports neither torch nor ``meshodenet`` nor ``benchmarks``; ``meshodenet`` (torch) imports
neither ``groundtruth`` nor ``benchmarks``; only ``benchmarks`` joins them.

Inside ``meshodenet``, each sub-package may import only the pieces listed in ``ALLOWED``:
``mesh`` (arrays and topology) and ``integrators`` import no other part of ``meshodenet``;
``training`` builds on ``mesh``, ``integrators`` and the shared top-level modules; the two
learners, ``gnn`` and ``energy``, build on those and never on each other. The one arrow from a
learner to the top-level registry is ``gnn.pyg.register_pyg_model``, which registers a user's
PyG model there when it is called. ``subdomain`` (patches of a mesh) evaluates the learners, so
it imports ``gnn``, ``energy``, ``mesh`` and ``interface`` (its ``PatchTraining`` is a
``TrajectoryModel``), and no part of ``meshodenet`` imports it
(``test_nothing_imports_subdomain``): only ``benchmarks`` may.

Two checks per sub-package: a fresh interpreter imports every module of the sub-package with
``meshodenet/__init__.py`` left out (it re-exports from every sub-package, which would hide the
arrows) and the sub-packages found in ``sys.modules`` are compared with ``ALLOWED``; and every
import statement of its files, the ones inside functions included (imported only when called),
is read and compared with ``ALLOWED`` too.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("benchmarks", "groundtruth", "meshodenet")


def _modules() -> dict:
    """``{dotted name: path}`` of every module of the project's packages."""
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _imports(name: str, path: Path, known: dict) -> set:
    """The project modules that ``name`` imports by name (a parent package's ``__init__``
    is not counted: Python runs it first, so it cannot close a circle by itself)."""
    is_pkg = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")[: len(name.split(".")) - node.level + is_pkg]
                base = ".".join(anchor + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                out.add(sub if sub in known else base)
    return {m for m in out if m in known and m != name and not name.startswith(m + ".")}


def _cycles(graph: dict) -> list:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, comps = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comps


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circle(package):
    known = _modules()
    graph = {n: _imports(n, p, known) for n, p in known.items()}
    assert [c for c in _cycles(graph) if c[0].split(".")[0] == package] == []


def test_the_check_sees_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_plugin_api_from_the_suite_package_without_loading_numpy_early():
    code = ("import sys, benchmarks.suite.procs; assert 'numpy' not in sys.modules; "
            "from benchmarks.suite import RegistryError, RunSpec, Suite, get_case, "
            "register_case, register_suite; import benchmarks.suite.suites as s; "
            "assert RunSpec is s.RunSpec")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


def test_no_module_over_650_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules().values()
            if (n := len(p.read_text().splitlines())) > 650}
    assert long == {}


# --- the import arrows ----------------------------------------------------------------------

#: What each top-level package must never import (by itself or through its modules).
FORBIDDEN = {"groundtruth": ("torch", "meshodenet", "benchmarks"),
             "meshodenet": ("groundtruth", "benchmarks")}
#: ``meshodenet``'s sub-packages and the parts of ``meshodenet`` each may import (besides
#: itself): other sub-packages, and the shared top-level modules ``interface``, ``metrics``,
#: ``registry``.
ALLOWED = {
    "mesh": set(),
    "integrators": set(),
    "training": {"mesh", "integrators", "interface", "metrics"},
    "gnn": {"mesh", "integrators", "training", "interface", "registry"},
    "energy": {"mesh", "integrators", "training", "interface"},
    "subdomain": {"mesh", "integrators", "gnn", "energy", "interface"},
}
#: What the shared top-level modules import at load time (``registry`` is left out: it imports
#: every model, and ``gnn`` reaches it only when ``register_pyg_model`` is called).
SHARED = {"interface": {"mesh"}, "metrics": set()}
#: Old module paths kept for a while: each warns and re-exports the new module's names.
DEPRECATED = {"meshodenet.pyg": ("meshodenet.gnn.pyg", "register_pyg_model"),
              "meshodenet.train": ("meshodenet.training.train", "fit"),
              "meshodenet.models.meshodenet": ("meshodenet.gnn.meshodenet", "PAPER")}


def _package_modules(package: str) -> list[str]:
    """Every module of ``package`` (a dotted name under ROOT), packages included."""
    base = ROOT.joinpath(*package.split("."))
    out = []
    for p in sorted(base.rglob("*.py")):
        parts = p.relative_to(ROOT).with_suffix("").parts
        out.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return out


def _modules_after(code: str) -> set:
    """The names in ``sys.modules`` after ``code`` runs in a fresh interpreter."""
    code += "\nimport sys\nprint(' '.join(sys.modules))"
    r = subprocess.run([sys.executable, "-W", "ignore", "-c", code], capture_output=True,
                       text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert r.returncode == 0, r.stderr[-2000:]
    return set(r.stdout.split())


def _under(mods, prefix: str) -> set:
    return {m for m in mods if m == prefix or m.startswith(prefix + ".")}


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_top_level_package_imports_nothing_forbidden(package):
    mods = _modules_after("import importlib\n" + "".join(
        f"importlib.import_module({m!r})\n" for m in _package_modules(package)
        if not m.startswith("meshodenet.models") and m not in DEPRECATED))
    for other in FORBIDDEN[package]:
        assert not _under(mods, other), f"{package} imports {sorted(_under(mods, other))[:5]}"


def _reachable(sub: str) -> set:
    """The parts of ``meshodenet`` that importing ``sub`` may load: ``ALLOWED`` and ``SHARED``
    followed through (not ``registry``'s own imports: see ``SHARED``)."""
    seen, todo = set(), [sub]
    while todo:
        part = todo.pop()
        new = (ALLOWED.get(part, set()) | SHARED.get(part, set())) - seen
        seen |= new
        todo += sorted(new)
    return seen - {sub}


def _meshodenet_part(module: str) -> str | None:
    """The part of ``meshodenet`` a module belongs to: its sub-package, or the top-level
    module's name (``interface``...); None outside ``meshodenet`` or for the package itself."""
    parts = module.split(".")
    return parts[1] if parts[0] == "meshodenet" and len(parts) > 1 else None


@pytest.mark.parametrize("sub", sorted(ALLOWED))
def test_subpackage_imports_at_import_time(sub):
    # a stand-in for the package ``meshodenet``: its sub-packages and modules load from the
    # directory, and its __init__ (which imports every sub-package) does not run
    stub = ("import importlib, sys, types\n"
            f"m = types.ModuleType('meshodenet'); m.__path__ = [{str(ROOT / 'meshodenet')!r}]\n"
            "sys.modules['meshodenet'] = m\n")
    mods = _modules_after(stub + "".join(f"importlib.import_module({m!r})\n"
                                         for m in _package_modules(f"meshodenet.{sub}")))
    used = {_meshodenet_part(m) for m in mods} - {None, sub}
    assert used <= _reachable(sub), f"meshodenet.{sub} loads {sorted(used - _reachable(sub))}"
    for other in FORBIDDEN["meshodenet"]:
        assert not _under(mods, other), f"meshodenet.{sub} imports {sorted(_under(mods, other))}"


def _imported_names(path: Path) -> set:
    """Every absolute import of a file (module-level or inside functions), as dotted names:
    ``import a.b`` gives ``a.b``, ``from a.b import c`` gives ``a.b`` and ``a.b.c``."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path}: relative import"
            names |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return names


@pytest.mark.parametrize("sub", sorted(ALLOWED))
def test_subpackage_import_statements(sub):
    bad = []
    for path in sorted((ROOT / "meshodenet" / sub).rglob("*.py")):
        for name in _imported_names(path):
            part = _meshodenet_part(name)
            if name.split(".")[0] in FORBIDDEN["meshodenet"] or (
                    part is not None and part != sub and part not in ALLOWED[sub]):
                bad.append(f"{path.relative_to(ROOT)}: {name}")
    assert not bad, bad


def test_nothing_imports_subdomain():
    bad = [f"{p.relative_to(ROOT)}: {n}" for p in sorted((ROOT / "meshodenet").rglob("*.py"))
           if "subdomain" not in p.relative_to(ROOT).parts for n in _imported_names(p)
           if _meshodenet_part(n) == "subdomain"]
    assert not bad, bad


def test_groundtruth_and_meshodenet_never_name_benchmarks():
    bad = [f"{p.relative_to(ROOT)}: {n}" for pkg in ("groundtruth", "meshodenet")
           for p in sorted((ROOT / pkg).rglob("*.py")) for n in _imported_names(p)
           if n.split(".")[0] == "benchmarks"]
    assert not bad, bad


def test_every_source_directory_is_a_package():
    missing = sorted({str(p.parent.relative_to(ROOT)) for pkg in PACKAGES
                      for p in (ROOT / pkg).rglob("*.py") if "__pycache__" not in p.parts
                      and not (p.parent / "__init__.py").exists()})
    assert not missing, f"directories with modules but no __init__.py: {missing}"


@pytest.mark.parametrize("old", sorted(DEPRECATED))
def test_deprecated_path_warns_and_reexports(old):
    new, name = DEPRECATED[old]
    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old_module = __import__(old, fromlist=[name])
    assert any(issubclass(w.category, DeprecationWarning) and new in str(w.message) for w in caught)
    assert getattr(old_module, name) is getattr(__import__(new, fromlist=[name]), name)
