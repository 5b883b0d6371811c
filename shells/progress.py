"""Progress bars: tqdm on a terminal, periodic plain lines anywhere else (a log file, a pipe).

tqdm redraws its bar with carriage returns, which in a log file make one line of 100+ kB; when
its stream is not a terminal, `tqdm` here writes the bar's state as a line of its own at most
every LINE_INTERVAL_S seconds, and once more when the bar closes.
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm as _tqdm

LINE_INTERVAL_S = 15.0  # seconds between two progress lines in a log
LINE_FORMAT = "{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} [{elapsed}<{remaining}, " \
              "{rate_fmt}{postfix}]"


def _terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class tqdm(_tqdm):  # noqa: N801 (tqdm's own name: a drop-in replacement)
    """`tqdm.tqdm` that writes plain lines when its stream is not a terminal."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._lines = not _terminal(kwargs.get("file") or sys.stderr)
        if self._lines:
            kwargs.setdefault("mininterval", LINE_INTERVAL_S)
            kwargs.setdefault("ascii", True)
            total = kwargs.get("total")
            if total is None and args and hasattr(args[0], "__len__"):
                total = len(args[0])
            if total is not None:
                kwargs.setdefault("bar_format", LINE_FORMAT)
            self._stream = kwargs.get("file") or sys.stderr
            kwargs["file"] = _Quiet(self._stream)
            self._line_at, self._last_line = -float("inf"), ""
        super().__init__(*args, **kwargs)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool | None:
        if not self._lines:
            return super().display(msg, pos)
        # a line at most every LINE_INTERVAL_S (refresh() and set_postfix() call this too),
        # and the last state when the bar closes (msg "": tqdm clearing a bar that does not
        # stay, leave=False)
        now = self._time()
        if not getattr(self, "_closing", False) and now - self._line_at < LINE_INTERVAL_S:
            return True
        line = (self.__str__() if not msg else msg).strip()
        if line and line != self._last_line:
            self._stream.write(line + "\n")
            self._stream.flush()
            self._line_at, self._last_line = now, line
        return True

    def close(self) -> None:
        self._closing = True
        super().close()

    def clear(self, nolock: bool = False) -> None:  # nothing to erase in a log
        if not self._lines:
            super().clear(nolock)

    def moveto(self, n: int) -> None:  # nested bars are lines one after another in a log
        if not self._lines:
            super().moveto(n)


class _Quiet:
    """The stream of a line-mode bar as tqdm sees it: its carriage returns and the newline it
    ends a bar with are dropped (`tqdm.display` writes the lines)."""

    def __init__(self, stream: Any) -> None:
        self.stream = stream

    def write(self, s: str) -> None:
        if s.strip("\r\n"):
            self.stream.write(s.replace("\r", ""))

    def flush(self) -> None:
        self.stream.flush()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)
