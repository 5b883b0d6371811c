"""Errors raised at the package boundary and small atomic-output helpers.

`InputError` means the user's input is wrong (a missing file, malformed JSON, a value out of
range). Its message is one line naming the file or value and the fix; the CLI prints it and exits
with status 2. Internal invariants use `assert`. A write that the system refuses (disk full, a
read-only or missing folder: `WRITE_ERRNOS`) is reported the same way (`write_failure`).

Outputs are all-or-nothing: a file is written through a temporary sibling and renamed into
place (`atomic_write`); a folder of outputs is written into a hidden staging folder and its
files moved in by `commit_files`, with SIGINT / SIGTERM held back while they move
(`uninterrupted`), so an interrupted or failed command leaves the old outputs or the new ones.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

# errors of a write the system refuses: the user can fix them (free space, another folder)
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                          errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENAMETOOLONG,
                          errno.EFBIG})


class InputError(ValueError):
    """Bad user input; the message names the file/value and how to fix it."""


class Interrupted(RuntimeError):
    """A run stopped before its end (Ctrl-C, SIGTERM, a rank of a distributed job lost): the
    message says what is intact and how to continue. The CLI prints it and exits with
    ``status`` (130 for a signal, 1 for a lost rank)."""

    def __init__(self, message: str, status: int = 1) -> None:
        super().__init__(message)
        self.status = status


def write_failure(exc: OSError, what: str = "") -> "InputError | None":
    """The one-line InputError for a refused write (`WRITE_ERRNOS`), else None."""
    if exc.errno not in WRITE_ERRNOS:
        return None
    where = exc.filename or what or "an output file"
    fix = ("free disk space" if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else
           "make the folder writable or choose another output folder")
    return InputError(f"{where}: cannot write ({exc.strerror or os.strerror(exc.errno)}); {fix} "
                      "and run the command again (what was there before is unchanged)")


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for the block (main thread): a signal that arrives during it
    is delivered, and raises, once the block is done. For short commit steps only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def commit_files(stage: Path, out: Path, last: str | None = None) -> None:
    """Move every file of the staging folder ``stage`` into ``out`` (created), ``last`` (a file
    name that marks a complete output) at the end, without being interrupted between them."""
    with uninterrupted():
        out.mkdir(parents=True, exist_ok=True)
        names = sorted(p.name for p in stage.iterdir())
        for n in [n for n in names if n != last] + [n for n in names if n == last]:
            os.replace(stage / n, out / n)


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Write a file through a temporary sibling and rename it into place.

    ``write(tmp_path)`` must create ``tmp_path``. A crash, a signal or a failed write (disk
    full) leaves either the old file or none, never a half-written one or the temporary.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        with uninterrupted():  # no signal between creating the temporary and knowing its name
            fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                       suffix=path.suffix)
            os.close(fd)
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename is None and exc.errno in WRITE_ERRNOS:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc  # name the file
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
