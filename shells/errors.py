"""Errors raised at the package boundary and small atomic-output helpers.

`InputError` means the user's input is wrong (a missing file, malformed JSON, a value out of
range). Its message is one line naming the file or value and the fix; the CLI prints it and exits
with status 2. Internal invariants use `assert`. A write that the system refuses (disk full, a
read-only or missing folder: `WRITE_ERRNOS`) is reported the same way (`write_failure`).

Outputs are all-or-nothing: a file is written through a temporary sibling and renamed into
place (`atomic_write`); a folder of outputs is written into a hidden staging folder and its
files moved in by `commit_files`, with SIGINT / SIGTERM held back while they move
(`uninterrupted`), so an interrupted or failed command leaves the old outputs or the new ones.
A command whose commit is its last step (`final_commit`) keeps a signal that arrives during the
commit from turning a finished command into an "interrupted" one: the outputs are complete by
then, so the command ends as done and says so (`late_signal`).
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

_SIGNALS = {signal.SIGINT, signal.SIGTERM}  # the ones a command turns into an orderly end


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


class _Held:
    """SIGINT / SIGTERM held back: while installed as their handler, a signal is only noted.
    Python runs signal handlers in the main thread, whichever thread the process received the
    signal in (torch's and Dr.Jit's worker threads included, which a thread's signal mask
    would not cover)."""

    def __init__(self) -> None:
        self.came: list[int] = []
        self.previous = {s: signal.getsignal(s) for s in _SIGNALS}
        for s in _SIGNALS:
            signal.signal(s, self)

    def __call__(self, signum: int, frame: object) -> None:
        self.came.append(signum)

    def restore(self) -> int | None:
        """Put the previous handlers back; the first signal that came (not yet delivered)."""
        for s, h in self.previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        return self.came[0] if self.came else None


def _main() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for the block (main thread): a signal that arrives during it
    is delivered, and raises, once the block is done. For short commit steps only."""
    if not _main():
        yield
        return
    held = _Held()
    try:
        yield
    finally:
        came = held.restore()
        if came is not None:
            signal.raise_signal(came)  # to the handler there was (KeyboardInterrupt, ...)


_final: dict[str, Any] = {"on": False, "held": None, "late": None}  # final_commit's state


@contextlib.contextmanager
def final_commit(then_ignore: bool = False) -> Iterator[None]:
    """For the block (a command whose `commit_files` is its last step: the CLI's single-output
    commands), the command is done once its outputs are in place: from the commit on, SIGINT /
    SIGTERM stay held back until the block ends, and one that came is then taken off instead of
    raised (`late_signal` tells which), so "interrupted" always means "outputs unchanged".
    ``then_ignore``: the process ignores both signals from then on (its interpreter shutting
    down). Without it (training, shells-demo, the library) a signal raises right after a
    commit, as anywhere else."""
    _final.update(on=True, held=None, late=None)
    try:
        yield
    finally:
        held, _final["on"], _final["held"] = _final["held"], False, None
        if held is not None:  # committed: signals are held back since
            _final["late"] = held.restore()
            if then_ignore:
                for s in _SIGNALS:
                    signal.signal(s, signal.SIG_IGN)


def late_signal() -> int | None:
    """The signal that `final_commit` took off after the outputs were committed, or None."""
    return _final["late"]


def commit_files(stage: Path, out: Path, last: str | None = None) -> None:
    """Move every file of the staging folder ``stage`` into ``out`` (created), ``last`` (a file
    name that marks a complete output) at the end, without being interrupted between them
    (nor, in a `final_commit` block, after them)."""
    def move() -> None:
        out.mkdir(parents=True, exist_ok=True)
        names = sorted(p.name for p in stage.iterdir())
        for n in [n for n in names if n != last] + [n for n in names if n == last]:
            os.replace(stage / n, out / n)

    if not (_final["on"] and _main()) or _final["held"] is not None:
        with uninterrupted():  # (in a final block after its first commit: held already)
            move()
        return
    held = _Held()
    try:
        move()
    except BaseException:
        came = held.restore()
        if came is not None:
            signal.raise_signal(came)
        raise
    _final["held"] = held  # held back until final_commit ends


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


def write_image(path: str | Path, img: Any, extension: str | None = None) -> None:
    """Write an image file (PNG, JPEG) with imageio, SIGINT / SIGTERM held back meanwhile (a
    few milliseconds): imageio's writer, interrupted while it opens, fails again in its
    destructor and prints a traceback after the one-line message."""
    import imageio.v3 as iio

    with uninterrupted():
        iio.imwrite(path, img, extension=extension)


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
