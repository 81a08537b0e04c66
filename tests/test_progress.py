"""Progress reports (volcal.base.progress): off unless enabled, nothing for short stages,
plain lines with the duration for long ones when the stream is not a terminal."""
from __future__ import annotations

import io
import time

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
