"""Errors raised at the package boundary and small atomic-output helpers.

`InputError` means the user's input is wrong (a missing file, malformed JSON, a value out of
range). Its message is one line naming the file or value and the fix; the CLI prints it and exits
with status 2. Internal invariants use `assert`.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable


class InputError(ValueError):
    """Bad user input; the message names the file/value and how to fix it."""


class Interrupted(RuntimeError):
    """A run stopped before its end (Ctrl-C, SIGTERM, a rank of a distributed job lost): the
    message says what is intact and how to continue. The CLI prints it and exits with
    ``status`` (130 for a signal, 1 for a lost rank)."""

    def __init__(self, message: str, status: int = 1) -> None:
        super().__init__(message)
        self.status = status


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Write a file through a temporary sibling and rename it into place.

    ``write(tmp_path)`` must create ``tmp_path``. A crash leaves either the old file or none,
    never a half-written one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: str | Path, data: Any) -> None:
    """Atomically write ``data`` as indented JSON."""
    atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=2) + "\n"))


def read_json(path: str | Path, what: str = "file", max_bytes: int | None = None) -> Any:
    """Read JSON, turning a missing file, one larger than ``max_bytes`` (checked by its size,
    before reading) or a syntax error into a one-line InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    size = path.stat().st_size
    if max_bytes is not None and size > max_bytes:
        raise InputError(f"{path}: {what} is {size / 2**20:.0f} MiB, more than the "
                         f"{max_bytes / 2**20:.0f} MiB this reader accepts; is it the right "
                         "file? Split or shrink it")
    try:
        return json.loads(path.read_text())
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text (UTF-8) file ({exc.reason} at byte {exc.start}); "
                         "fix or regenerate the file")
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: malformed JSON ({exc.msg} at line {exc.lineno}, "
                         f"column {exc.colno}); fix or regenerate the file")
