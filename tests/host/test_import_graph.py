"""The package's imports point down (issue 59): no import cycle between endowave_cl's modules, with
the imports inside functions counted, and the ground floors import nothing above them; imports sit
at the top of each module, but for the optional dependencies and the listed exceptions."""
from __future__ import annotations

import ast
import configparser
import re
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / "endowave_cl"


def _modules():
    mods = {}
    for f in PKG.rglob("*.py"):
        parts = f.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = f
    return mods


def _graph():
    """{module: {module it imports, at the top or inside a function}} within endowave_cl."""
    mods = _modules()
    graph = {}
    for name, f in mods.items():
        is_pkg = f.name == "__init__.py"
        out = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = name.split(".")
                if node.level:
                    base = base[:len(base) - node.level + (1 if is_pkg else 0)]
                mod = ".".join(base + ([node.module] if node.module else [])) if node.level else node.module
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in mods else mod for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != name and t != "endowave_cl":
                    out.add(t)
        graph[name] = out
    return graph


def _cycles(graph):
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
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
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle():
    assert _cycles(_graph()) == []


def test_the_ground_floors_import_nothing_above_them():
    g = _graph()
    # the warps, the flow estimators and the settings sit below the baselines and the in-between
    # targets; the probe's parent side below the rasterizer ops; evaluation below the run folders
    assert not {m for m in g["endowave_cl.warp"] if m.startswith("endowave_cl.")} - {"endowave_cl.errors"}
    assert "endowave_cl.baselines" not in g["endowave_cl.data.flow"]
    assert not {"endowave_cl.baselines", "endowave_cl.train.between"} & g["endowave_cl.train.config"]
    assert "endowave_cl.ops.rasterize" not in g["endowave_cl.probe"]
    assert "endowave_cl.run_io" not in g["endowave_cl.evaluation"]
    # the references are the kernels' test oracles: the product reads them only where the torch
    # backend of the wavelet loss is one (wavelet/loss.py) and in the probe's child
    readers = {m for m, deps in g.items() if any(d.startswith("endowave_cl.reference") for d in deps)
               and not m.startswith("endowave_cl.reference")}
    assert readers <= {"endowave_cl.wavelet.loss", "endowave_cl.probe_child"}


# ------------------------------------------------------------------------------ imports at the top
# A module imports the package's own modules, the standard library and the required dependencies
# (setup.cfg install_requires) at its top.  Inside a function: the optional dependencies, the
# required ones of LAZY_DEPENDENCIES and the imports of LAZY_IMPORTS, each for the reason given.

DIST_MODULES = {   # install_requires: distribution -> the module it is imported as (None: not imported)
    "numpy": "numpy", "pyopencl": "pyopencl", "pocl-binary-distribution": None, "torch": "torch",
    "opencv-contrib-python-headless": "cv2", "scikit-image": "skimage", "matplotlib": "matplotlib",
    "tqdm": "tqdm", "pywavelets": "pywt", "imageio-ffmpeg": "imageio_ffmpeg", "tomli": "tomli",
}
LAZY_DEPENDENCIES = {   # required, yet imported where they are used
    "torch": "about 3 s to import; the device path, export, eval and the viewer do not use it",
    "matplotlib": "about 1 s to import, for the figures alone (the Agg backend chosen before pyplot)",
    "skimage": "imports scipy (about 0.3 s), for the SSIM alone",
    "imageio_ffmpeg": "optional at run time: render writes mp4v without it (video.py)",
}
LAZY_IMPORTS = {   # (module, what it imports inside a function; a package covers its modules): why
    ("endowave_cl.cli", "endowave_cl.runtime"):
        "CLI start-up: numpy; cli.py imports nothing slow before main() has installed its signal "
        "handlers (a Ctrl-C then is one line, tests/cli/test_hostile.py), and --help needs none of it",
    ("endowave_cl.cli", "endowave_cl.host_memory"):
        "CLI start-up: ctypes.util imports subprocess and tempfile; as above",
    ("endowave_cl.device", "pyopencl"):
        "OpenCL is loaded on first device use: cli.py imports runtime.py and device.py for their "
        "error types before every command, and a missing pyopencl is a one-line OpenCLUnavailable",
    ("endowave_cl.runtime", "pyopencl"): "as in device.py",
    ("endowave_cl.run_io", "endowave_cl.train"):
        "export, eval and the viewer import run_io and stay free of train/ (test_gaussians.py)",
    ("endowave_cl.baselines", "endowave_cl.train"):
        "evaluation imports baselines and stays free of train/ (test_gaussians.py)",
    ("endowave_cl.wavelet", "endowave_cl.wavelet.loss"):
        "the torch names on first use: importing endowave_cl.wavelet does not import torch",
}


def _required_modules():
    cfg = configparser.ConfigParser()
    cfg.read(PKG.parent / "setup.cfg")
    dists = {re.match(r"[A-Za-z0-9_.-]+", line.strip()).group(0).lower()
             for line in cfg["options"]["install_requires"].splitlines()
             if line.strip() and not line.strip().startswith("#")}
    assert dists == set(DIST_MODULES), "install_requires changed: update DIST_MODULES (and LAZY_DEPENDENCIES)"
    return {m for m in DIST_MODULES.values() if m}


def _function_imports(name, path):
    """[(line, imported module)] of the imports inside the functions of module ``name``, the
    package's own modules by their full name."""
    mods = _modules()
    is_pkg = path.name == "__init__.py"
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            if in_function and isinstance(child, ast.Import):
                found.extend((child.lineno, a.name) for a in child.names)
            elif in_function and isinstance(child, ast.ImportFrom):
                mod = child.module
                if child.level:
                    base = name.split(".")
                    base = base[:len(base) - child.level + (1 if is_pkg else 0)]
                    mod = ".".join(base + ([child.module] if child.module else []))
                found.extend((child.lineno, f"{mod}.{a.name}" if f"{mod}.{a.name}" in mods else mod)
                             for a in child.names)
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))
    visit(ast.parse(path.read_text()), False)
    return found


def _allowed(name, target):
    return any(name == m and (target == a or target.startswith(a + ".")) for m, a in LAZY_IMPORTS)


def test_imports_are_at_the_top():
    """The package's own modules, the standard library and the required dependencies are imported
    at the top of a module, not inside a function, but for the reasons in LAZY_IMPORTS and
    LAZY_DEPENDENCIES."""
    if not hasattr(sys, "stdlib_module_names"):
        pytest.skip("Python >= 3.10 lists the standard library's modules")
    required = _required_modules()
    bad = []
    for name, path in sorted(_modules().items()):
        for line, target in _function_imports(name, path):
            top = target.split(".")[0]
            checked = top == "endowave_cl" or top in sys.stdlib_module_names or (
                top in required and top not in LAZY_DEPENDENCIES)
            if checked and not _allowed(name, target):
                bad.append(f"{path.relative_to(PKG.parent)}:{line}: import of {target}")
    assert not bad, ("imports inside functions: move them to the top of the module, or add them to "
                     "LAZY_IMPORTS with the reason\n  " + "\n  ".join(bad))


def test_every_lazy_import_is_still_there():
    """An entry of LAZY_IMPORTS goes when its import does."""
    mods = _modules()
    unused = {(m, a) for m, a in LAZY_IMPORTS
              if not any(t == a or t.startswith(a + ".") for _, t in _function_imports(m, mods[m]))}
    assert not unused, unused
