"""The layout of the packages: no import circle (the static import graph of every ``import``
and ``from ... import`` statement, those inside functions included, has no cycle), no module
over 650 lines, the plugin API where the docs say it is."""

import ast
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
    import subprocess
    import sys

    code = ("import sys, benchmarks.suite.procs; assert 'numpy' not in sys.modules; "
            "from benchmarks.suite import RegistryError, RunSpec, Suite, get_case, "
            "register_case, register_suite; import benchmarks.suite.suites as s; "
            "assert RunSpec is s.RunSpec")
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


def test_no_module_over_650_lines():
    long = {str(p.relative_to(ROOT)): n for p in _modules().values()
            if (n := len(p.read_text().splitlines())) > 650}
    assert long == {}
