"""Errors raised at the package boundary.

`InputError` means the user's input is wrong (a missing file, malformed JSON, a value out of
range). Its message is one line naming the file or value and the fix; the CLI prints it and exits
with status 2. Internal invariants use `assert`. A write that the system refuses (disk full, a
read-only or missing folder: `WRITE_ERRNOS`) is reported the same way (`write_failure`).
"""

from __future__ import annotations

import errno
import os

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
