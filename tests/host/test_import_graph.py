"""The package's imports point down (issue 59): no import cycle between endowave_cl's modules, with
the imports inside functions counted, and the ground floors import nothing above them."""
from __future__ import annotations

import ast
from pathlib import Path

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
