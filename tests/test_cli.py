"""The commands come from one table (`shells.cli.COMMANDS`): every console script of
pyproject.toml is a row of it and every row a console script, each with a --help description."""

from __future__ import annotations

import re
from pathlib import Path

from shells import cli

ROOT = Path(__file__).resolve().parents[1]


def console_scripts() -> dict[str, str]:
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    return dict(re.findall(r'^(shells-[\w-]+) = "([\w.:]+)"', section, re.M))


def test_console_scripts_are_the_rows_of_the_table():
    scripts = console_scripts()
    assert set(scripts) == set(cli.COMMANDS) and len(scripts) == 13
    for prog, target in scripts.items():
        module, name = target.split(":")
        assert module == "shells.cli"
        main = getattr(cli, name)
        assert main.__name__ == name and prog in main.__doc__


def test_every_command_has_a_description_and_its_arguments(capsys):
    for prog in cli.COMMANDS:
        p = cli.parser(prog)
        assert p.prog == prog and len(p.description) > 20, prog
        assert "usage: " + prog in p.format_help()
    train = cli.parser("shells-train").parse_args(["--out", "R", "--iters", "5"])
    assert (train.out, train.iters, train.preset, train.scene) == ("R", 5, "auto", "auto")
    render = cli.parser("shells-render").parse_args(["R", "--stage", "stage1", "--shells", "lod"])
    assert (render.stage, render.shells, render.config) == ("stage1", "lod", None)
