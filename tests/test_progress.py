"""Progress bars in a log: plain lines, no carriage returns, one per interval and the last state."""

from __future__ import annotations

import io

from shells import progress
from shells.progress import tqdm


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_gets_plain_lines_and_the_final_state(monkeypatch):
    log = io.StringIO()
    with tqdm(total=1000, desc="stage 1", unit="step", file=log) as bar:
        for _ in range(1000):
            bar.update(1)
            bar.set_postfix(loss="0.1")  # refreshes: must not add a line each time
        tqdm.write("warning: a line of its own", file=log)
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text
    lines = text.splitlines()
    # the first state, the message, the last state: the interval (15 s) has not passed
    assert len(lines) == 3, lines
    assert lines[0].startswith("stage 1:   0% 0/1000")
    assert lines[1] == "warning: a line of its own"
    assert lines[2].startswith("stage 1: 100% 1000/1000") and "loss=0.1" in lines[2]


def test_a_line_per_interval(monkeypatch):
    monkeypatch.setattr(progress, "LINE_INTERVAL_S", 0.0)
    log = io.StringIO()
    for _ in tqdm(range(3), desc="render", file=log, leave=False, mininterval=0):
        pass
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("render:   0% 0/3") and lines[-1].startswith("render: 100% 3/3")
    assert len(lines) == 4  # 0, 1, 2, 3 of 3


def test_a_terminal_keeps_the_redrawn_bar():
    term = _Terminal()
    for _ in tqdm(range(3), desc="x", file=term):
        pass
    assert "\r" in term.getvalue()
