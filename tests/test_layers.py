"""The import graph of shells/, scenes/ and bench/: layers point down, no cycle, no module reaches
into a CLI module or another module's private names.

Every import statement counts, the ones inside functions too (a lazy import is still a
dependency). Layers, bottom to top (a module may import only lower layers, or its own
subpackage at the same layer):

    0 errors
    1 files         atomic writes, locks, signals; progress; allocator (malloc settings)
    2 config, device, metrics, distributed
    3 data/         cameras, data sets, camera paths, COLMAP
    4 fields/       hash grid, networks, NeuS, contraction
    5 levelset/, deform/
    6 render/
  6.5 bake/         baked layers: format, renderer, layers, fit (bake/run: run level, as 9)
    7 run           the run directory (builds fields, shells); presets (data + preset -> Config)
    8 train/        the shared loop, stage 1, stage 2, health
    9 pipeline      run-level extraction and rendering, the demo; viewer
   10 cli
   11 bench/
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RANKS = {
    "shells": 0,  # the package's __init__ (a docstring and the version)
    "shells.errors": 0,
    "shells.browser": 1,
    "shells.files": 1, "shells.progress": 1, "shells.allocator": 1,
    "shells.config": 2, "shells.device": 2, "shells.metrics": 2, "shells.distributed": 2,
    "shells.data": 3, "scenes": 3,
    "shells.fields": 4,
    "shells.levelset": 5, "shells.deform": 5,
    "shells.render": 6,
    "shells.bake": 6.5,  # format, render, layers, fit: the field and the shells come as values
    "shells.run": 7, "shells.presets": 7,
    "shells.train": 8,
    "shells.pipeline": 9, "shells.viewer": 9, "shells.bake.run": 9,
    "shells.cli": 10,
    "bench": 11,
}
PACKAGES = ("shells.data", "shells.fields", "shells.levelset", "shells.deform", "shells.render",
            "shells.bake", "shells.train", "scenes", "bench")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    files = [p for d in ("shells", "scenes", "bench") for p in (ROOT / d).rglob("*.py")]
    return {module_name(p): p for p in files}


def group(name: str) -> str:
    """The RANKS key a module belongs to (longest prefix)."""
    keys = [k for k in RANKS if name == k or (k != "shells" and name.startswith(k + "."))]
    assert keys, f"{name}: not in the layer table of tests/test_layers.py"
    return max(keys, key=len)


def imports(path: Path, known: set[str]) -> list[tuple[str, list[str], int]]:
    """(imported project module, names imported from it, line) for every import statement."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [a.name for a in node.names]
            # `from pkg import mod` imports the submodule pkg.mod
            subs = [f"{node.module}.{n}" for n in names if f"{node.module}.{n}" in known]
            out += [(s, [], node.lineno) for s in subs]
            rest = [n for n in names if f"{node.module}.{n}" not in known]
            if rest or not subs:
                out.append((node.module, rest, node.lineno))
    return [(m, n, ln) for m, n, ln in out if m.split(".")[0] in ("shells", "scenes", "bench")]


def graph() -> dict[str, list[tuple[str, list[str], int]]]:
    mods = modules()
    known = set(mods)
    return {name: [(m, n, ln) for m, n, ln in imports(path, known) if m in known]
            for name, path in mods.items()}


def test_every_project_import_resolves():
    mods = modules()
    known = set(mods)
    for name, path in mods.items():
        for m, _, ln in imports(path, known):
            assert m in known, f"{path}:{ln} imports {m}, which is no module of the project"


def layer_violations(g: dict[str, list[tuple[str, list[str], int]]]) -> list[str]:
    bad = []
    for name, deps in g.items():
        a = group(name)
        for m, _, ln in deps:
            b = group(m)
            if m == name or (a == b and a in PACKAGES):
                continue
            if RANKS[b] >= RANKS[a]:
                bad.append(f"{name}:{ln} ({a}, layer {RANKS[a]}) imports {m} (layer {RANKS[b]})")
    return bad


def find_cycles(g: dict[str, list[str]]) -> list[str]:
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    cycles = []

    def visit(n: str, stack: list[str]) -> None:
        state[n] = 1
        for m in g.get(n, []):
            if state.get(m) == 1:
                cycles.append(" -> ".join(stack[stack.index(m):] + [m]))
            elif m not in state:
                visit(m, stack + [m])
        state[n] = 2

    for n in sorted(g):
        if n not in state:
            visit(n, [n])
    return cycles


def test_layers_point_down():
    bad = layer_violations(graph())
    assert not bad, "upward or sideways imports:\n" + "\n".join(bad)


def test_no_import_cycle():
    g = {name: sorted({m for m, _, _ in deps if m != name}) for name, deps in graph().items()}
    cycles = find_cycles(g)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_no_cli_imports_and_no_private_names():
    bad = []
    for name, deps in graph().items():
        for m, names, ln in deps:
            if m == "shells.cli" and name != "shells.cli":
                bad.append(f"{name}:{ln} imports the CLI module")
            priv = [n for n in names if n.startswith("_")]
            if priv and m != name:
                bad.append(f"{name}:{ln} imports private {priv} from {m}")
    assert not bad, "\n".join(bad)


def test_the_checks_catch_what_they_are_for():
    """On made-up graphs: an upward import, a sideways one and a cycle are reported; the real
    graph is read (so the tests above do not pass on an empty graph)."""
    g = graph()
    assert len(g) > 30 and "shells.render.raycast" in {m for m, _, _ in g["shells.render.frame"]}
    assert layer_violations({"shells.render.frame": [("shells.run", [], 7)]}) == [
        "shells.render.frame:7 (shells.render, layer 6) imports shells.run (layer 7)"]
    assert layer_violations({"shells.pipeline": [("shells.viewer", [], 1)]})  # sideways
    assert layer_violations({"shells.fields.network": [("shells.levelset.grid", [], 1)]})
    assert not layer_violations({"shells.render.frame": [("shells.render.occupancy", [], 1)]})
    assert find_cycles({"a": ["b"], "b": ["c"], "c": ["a"]}) == ["a -> b -> c -> a"]
    assert not find_cycles({"a": ["b"], "b": ["c"], "c": []})
