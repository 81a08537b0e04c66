"""Signals that a compiled solver swallowed.

IPOPT, called through CasADi, checks for Ctrl-C / SIGTERM between its iterations by running
Python's signal handlers; the KeyboardInterrupt the command line's handler raises there is
caught inside CasADi, which ends the solve with a status ("NonIpopt_Exception_Thrown" or
"User_Requested_Stop") and returns normally.  Without a check after the call the program
carried on: `volcal plan` sent SIGTERM during its placement search solved the remaining
starts, wrote its plan and exited 0.  The command line's handler notes every signal here;
code that calls a CasADi solver calls :func:`raise_if_signalled` after it.
"""

from __future__ import annotations

_SIGNALS: list[int] = []


def note_signal(signum: int) -> None:
    """Record that signal ``signum`` arrived (called by the command line's handler)."""
    _SIGNALS.append(int(signum))


def raise_if_signalled() -> None:
    """Raise KeyboardInterrupt if a signal arrived since the program started (or since
    :func:`clear`): a solver that returned may have swallowed it."""
    if _SIGNALS:
        raise KeyboardInterrupt(f"signal {_SIGNALS[-1]}")


def clear() -> None:
    """Forget the signals noted so far (the command line, once a command has ended)."""
    _SIGNALS.clear()
