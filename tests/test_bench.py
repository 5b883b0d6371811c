"""Every benchmark script (bench/, run as ``python -m bench.NAME``) and docs/figures.py still
imports against the library and answers --help, each subcommand too: API drift breaks here
rather than in the next benchmark run. One process; no data needed."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import runpy
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures.py"
SCRIPTS = sorted(p.stem for p in (ROOT / "bench").glob("*.py")
                 if p.stem not in ("__init__", "report"))
SUBCOMMANDS = {"diagnostics": ["error", "ball", "weight", "slope", "density", "drift"],
               "step_speed": ["stage1", "stage2", "allocator"],
               "figures": ["demo", "animation", "curve", "baked"]}


def help_text(run, argv: list[str], capsys) -> str:
    """The --help output of ``run()`` (runpy of a script as __main__) with ``argv``."""
    old = sys.argv
    sys.argv = argv
    try:
        with pytest.raises(SystemExit) as exit_:
            run()
    finally:
        sys.argv = old
    assert exit_.value.code in (0, None), f"{argv}: exit {exit_.value.code}"
    out = capsys.readouterr().out
    assert "usage:" in out and len(out.splitlines()) > 2, f"{argv}: no help text\n{out}"
    return out


def calls(name: str) -> list[list[str]]:
    return [["--help"]] + [[sub, "--help"] for sub in SUBCOMMANDS.get(name, [])]


@pytest.mark.filterwarnings("ignore:.*found in sys.modules:RuntimeWarning")
@pytest.mark.parametrize("name", SCRIPTS)
def test_bench_script_help(name, capsys):
    for args in calls(name):
        help_text(lambda: runpy.run_module(f"bench.{name}", run_name="__main__"),
                  [f"bench/{name}.py", *args], capsys)


def test_figures_help_and_imports(capsys):
    for args in calls("figures"):
        help_text(lambda: runpy.run_path(str(FIGURES), run_name="__main__"),
                  [str(FIGURES), *args], capsys)
    tree = ast.parse(FIGURES.read_text())
    mods = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    mods |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not {m for m in mods if m.split(".")[0] == "bench"}, "docs/figures.py imports bench"


def test_every_import_resolves():
    """The imports inside functions too (the ones --help does not run): each project module
    exists and has the names taken from it."""
    project = ("shells", "scenes", "bench")
    bad = []
    for path in [ROOT / "bench" / f"{n}.py" for n in SCRIPTS + ["report"]] + [FIGURES]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in project:
                        importlib.import_module(a.name)
            elif (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
                  and node.module.split(".")[0] in project):
                mod = importlib.import_module(node.module)
                bad += [f"{path.name}:{node.lineno} {node.module}.{a.name}" for a in node.names
                        if not hasattr(mod, a.name) and not (
                            hasattr(mod, "__path__")  # a package: the name may be a submodule
                            and importlib.util.find_spec(f"{node.module}.{a.name}"))]
    assert not bad, "names missing:\n" + "\n".join(bad)


def test_bench_scripts_are_modules():
    """No script reaches for sys.path: each imports the project as a package."""
    for name in SCRIPTS + ["report"]:
        text = (ROOT / "bench" / f"{name}.py").read_text()
        assert "sys.path" not in text and "E402" not in text, f"bench/{name}.py"
    assert "sys.path" not in FIGURES.read_text()
