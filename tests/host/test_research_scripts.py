"""research/ and benchmarks/ hold scripts, not the product: they are not tested here beyond this.
Each one imports (its module-level code runs, main is there) and research/ uses only the package's
public names (no ``from endowave_cl... import _private``)."""
from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted((ROOT / "research").glob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))


def test_the_folders_hold_their_scripts():
    names = {p.name for p in SCRIPTS}
    assert {"quality_run.py", "teacher_probe.py", "bench_render.py", "perf_table.py"} <= names
    assert not any((ROOT / "tools" / n).exists() for n in names)


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_script_imports(path, monkeypatch):
    monkeypatch.syspath_prepend(str(path.parent))        # siblings (quality_run, kernel_events)
    monkeypatch.setattr(sys, "argv", [str(path)])
    spec = importlib.util.spec_from_file_location(f"_script_{path.stem}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert callable(getattr(mod, "main", None)) or path.stem == "kernel_events"


@pytest.mark.parametrize("path", sorted((ROOT / "research").glob("*.py")), ids=lambda p: p.name)
def test_research_uses_public_names(path):
    private = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("endowave_cl"):
            private += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
            if any(part.startswith("_") for part in node.module.split(".")):
                private.append(node.module)
    assert not private, f"{path.name} imports private names: {private}"
