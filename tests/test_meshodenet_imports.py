"""The import arrows: groundtruth never imports torch, meshodenet never imports groundtruth,
and the data commands of the CLI run without torch."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules_after(code: str) -> set:
    code += "\nimport sys\nprint(' '.join(sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         check=True, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    return set(out.stdout.split())


def test_meshodenet_does_not_import_groundtruth():
    mods = _modules_after("import meshodenet, meshodenet.registry, meshodenet.training.train")
    assert "torch" in mods
    assert not any(m == "groundtruth" or m.startswith("groundtruth.") for m in mods)


def _groundtruth_modules() -> list:
    paths = (p.relative_to(ROOT).with_suffix("").parts for p in (ROOT / "groundtruth").rglob("*.py"))
    return sorted(".".join(p[:-1] if p[-1] == "__init__" else p) for p in paths)


@pytest.mark.parametrize("module", [m for m in _groundtruth_modules() if m != "groundtruth"])
def test_groundtruth_does_not_import_torch(module):
    assert "torch" not in _modules_after(f"import {module}")


def test_cli_and_registry_load_without_torch():
    mods = _modules_after("import benchmarks.cli as c; c.build_parser(); "
                          "import benchmarks.suite.registry")
    assert "torch" not in mods
