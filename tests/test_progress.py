"""Progress reports (volcal.base.progress): off unless enabled, nothing for short stages,
plain lines with the duration for long ones when the stream is not a terminal."""
from __future__ import annotations

import io
import time

import pytest

from volcal.base import progress


def test_progress_lines():
    buf = io.StringIO()
    progress.enable(False, buf)
    with progress.stage("off"):
        time.sleep(0.01)
    progress.enable(True, buf)
    with progress.stage("short"):
        time.sleep(0.05)
    assert buf.getvalue() == ""  # quick stages stay quiet
    with progress.stage("long", after=0.05):
        time.sleep(0.2)
        progress.update("iteration 3, cost 1.5")
    text = buf.getvalue()
    progress.enable(False)
    assert text.splitlines()[0] == "long ..."
    assert "long: iteration 3, cost 1.5" in text
    assert text.splitlines()[-1].startswith("long: done in ")


def test_a_stage_ended_by_a_signal_says_it_stopped():
    """A stage left by an exception (Ctrl-C, SIGTERM, an error) is not reported as done."""
    buf = io.StringIO()
    progress.enable(True, buf)
    try:
        with pytest.raises(KeyboardInterrupt):
            with progress.stage("planning", after=0.01):
                while "planning ..." not in buf.getvalue():
                    time.sleep(0.01)
                raise KeyboardInterrupt
    finally:
        progress.enable(False)
    last = buf.getvalue().splitlines()[-1]
    assert last.startswith("planning: stopped after ") and "done" not in last


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_counter_writes_plain_lines_with_total_and_time_left_off_a_terminal():
    buf = io.StringIO()
    progress.enable(True, buf)
    try:
        with progress.counter(4, "trials of x", "trial", interval=0.0) as c:
            for _ in range(4):
                c.update(1)
        with progress.counter(None, "order selection", "fit", interval=0.0) as c:
            c.update(1, note="last X3 Y2")
        with progress.counter(4, "quiet", "trial", on=False) as c:
            c.update(4)
    finally:
        progress.enable(False)
    text = buf.getvalue()
    lines = text.splitlines()
    assert "\r" not in text and "\x1b" not in text
    assert lines[0].startswith("trials of x: 1 of 4 trials (25 %), 0:00 elapsed, ETA 0:0")
    assert lines[3].startswith("trials of x: 4 of 4 trials (100 %)")
    assert lines[4].startswith("trials of x: 4 of 4 trials done in 0:0")
    assert lines[5].startswith("order selection: 1 fit, 0:00 elapsed (last X3 Y2)")
    assert not any(line.startswith("quiet") for line in lines)
    # on a terminal the same counter is a bar redrawn in place
    tty = _Terminal()
    progress.enable(True, tty)
    try:
        with progress.counter(3, "bar", "trial") as c:
            c.update(3)
    finally:
        progress.enable(False)
    assert "\r" in tty.getvalue() and "0/3" in tty.getvalue()


def test_steps_of_a_stage_still_report_after_an_inner_stage():
    buf = io.StringIO()
    progress.enable(True, buf)
    try:
        with progress.stage("outer", after=0.0):
            time.sleep(0.05)
            with progress.stage("inner", after=10.0):
                pass
            progress.update("GA round 1 of 2: generation 3 of 30")
    finally:
        progress.enable(False)
    assert "outer: GA round 1 of 2: generation 3 of 30" in buf.getvalue()
    assert progress.eta(1, 4, 10.0) == "0:30" and progress.clock(3725) == "1:02:05"
