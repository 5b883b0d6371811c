"""Outputs written whole or not at all, one writer at a time, and orderly ends on a signal.

A file is written through a temporary sibling and renamed into place (`atomic_write`); a
folder of outputs is written into a hidden staging folder and its files moved in by
`commit_files`, with SIGINT / SIGTERM held back while they move (`uninterrupted`), so an
interrupted or failed command leaves the old outputs or the new ones. A command whose commit
is its last step (`final_commit`) keeps a signal that arrives during the commit from turning a
finished command into an "interrupted" one: the outputs are complete by then, so the command
ends as done and says so (`late_signal`). A lock file (`lock`) lets one command at a time
write a run or an output folder.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from shells.errors import WRITE_ERRNOS, InputError, Interrupted

_SIGNALS = {signal.SIGINT, signal.SIGTERM}  # the ones a command turns into an orderly end


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


@contextlib.contextmanager
def staged_dir(out: Path, command: str) -> Iterator[Path]:
    """A hidden staging folder beside ``out`` for a command's files (the caller moves them in
    with `commit_files`); removed at the end, and a Ctrl-C leaves ``out`` as it was."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        yield tmp
    except KeyboardInterrupt:
        raise Interrupted(f"{command} interrupted; {out} is as it was before; run it again",
                          status=130) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


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


def output_lock(out: str | Path) -> Path:
    """The lock file of an output folder that is not a run (a render's OUT): beside it."""
    out = Path(os.path.abspath(out))
    return out.parent / f".{out.name}.lock"


# ---------------------------------------------------------------------------------------------
# Locks: one writer per run (or output folder) at a time
# ---------------------------------------------------------------------------------------------

def _start_time(pid: int) -> str | None:
    """The process's start time (Linux /proc, clock ticks since boot): tells a live owner from a
    new process that reuses its pid. None where /proc is missing or the pid is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]


def _alive(owner: dict[str, Any]) -> bool:
    """Whether the process that wrote a lock still runs (True when it cannot be told: another
    host)."""
    if owner.get("host") != socket.gethostname():
        return True
    pid = int(owner.get("pid", -1))
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass  # someone else's live process
    started = _start_time(pid)
    return owner.get("started") is None or started is None or started == owner["started"]


@contextlib.contextmanager
def lock(path: str | Path, command: str) -> Iterator[None]:
    """Hold the lock file ``path`` (e.g. `RunDir.lock`) for the block: a second command finds
    it held by a live process and gets a one-line InputError at once; a lock left by a process
    that is gone (killed) is stale and taken over. A folder the lock had to create is removed
    again when the block leaves nothing else in it (bad input writes nothing)."""
    path = Path(os.path.abspath(path))
    created = [d for d in path.parents if not d.exists()]  # innermost first
    me = {"pid": os.getpid(), "host": socket.gethostname(), "started": _start_time(os.getpid()),
          "command": command, "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    held = False
    try:  # taken and given up with signals held back: a signal then would strand the lock
        with uninterrupted():
            for attempt in range(2):
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_name(f"{path.name}.{os.getpid()}")
                tmp.write_text(json.dumps(me) + "\n")
                try:
                    os.link(tmp, path)  # atomic: the lock appears with its content or not
                    held = True
                    break
                except FileExistsError:
                    try:
                        owner = json.loads(path.read_text())
                    except (OSError, ValueError):
                        owner = {}  # removed meanwhile, or not ours: stale
                    if attempt == 0 and not _alive(owner):
                        path.unlink(missing_ok=True)
                        continue
                    raise InputError(
                        f"{path.parent}: in use by {owner.get('command', 'another command')} "
                        f"(pid {owner.get('pid', '?')} on {owner.get('host', '?')}, since "
                        f"{owner.get('since', '?')}); wait for it to end, or delete {path} if "
                        "that process is gone") from None
                finally:
                    tmp.unlink(missing_ok=True)
        yield
    finally:
        if held:
            with uninterrupted():
                try:
                    if json.loads(path.read_text()).get("pid") == os.getpid():
                        path.unlink()
                except (OSError, ValueError):
                    pass
                for d in created:
                    try:
                        d.rmdir()  # only if empty: nothing was written
                    except OSError:
                        break
