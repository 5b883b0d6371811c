"""Output shared by the benchmark scripts (each run as ``python -m bench.NAME`` from the
repository root): JSON results, the command line of appended tables, subcommands."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any, Callable

from shells.errors import InputError


def emit_json(data: Any, path: str | Path | None = None) -> None:
    """Print ``data`` as indented JSON and, when ``path`` is given, also write it there."""
    text = json.dumps(data, indent=1)
    print(text)
    if path:
        Path(path).write_text(text + "\n")


def command_line(name: str, argv: list[str] | None = None) -> str:
    """The command that ran ``bench.NAME`` with ``argv`` (default: this process's arguments)."""
    args = sys.argv[1:] if argv is None else argv
    return " ".join(["python", "-m", f"bench.{name}", *(shlex.quote(str(a)) for a in args)])


def subcommands(prog: str, description: str, commands: list[Callable[[argparse.Namespace], int]]
                ) -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    """A parser with one subcommand per function, named as it and described by its docstring
    (the part before the first colon is the one-line help), each taking a run directory RUN;
    returns it and the subparsers by name. `run_command` parses and runs."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    sub = p.add_subparsers(dest="command", required=True)
    for fn in commands:
        doc = " ".join((fn.__doc__ or "").split())
        sp = sub.add_parser(fn.__name__, help=doc.split(": ")[0], description=doc)
        sp.set_defaults(fn=fn)
        sp.add_argument("run", help="a shells-train run directory")
    return p, sub.choices


def run_command(p: argparse.ArgumentParser, argv: list[str] | None) -> int:
    """Parse ``argv`` and run the chosen subcommand of `subcommands`; an `InputError` becomes
    a one-line message and exit status 2."""
    a = p.parse_args(argv)
    try:
        return a.fn(a)
    except InputError as exc:
        p.exit(2, f"error: {exc}\n")
