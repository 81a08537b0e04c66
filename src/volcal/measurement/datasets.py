"""One instrument's table as an input of an identification (:class:`DataSet`), and the
command line's ``--data [INSTRUMENT=]FILE`` text parsed into one.

Kept apart from :mod:`volcal.analysis.fusion`, which joins several tables into one
problem: the command line parses ``--data`` before it reads the table, and a bad table
must be reported before the numerics (SciPy, the solver) are imported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pandas as pd

    from volcal.measurement.budget import Budget
    from volcal.measurement.instruments import Instrument

__all__ = ["DataSet", "parse_data_argument"]


@dataclass(frozen=True)
class DataSet:
    """One instrument's table: the instrument (name or object), the table (CSV path or
    DataFrame), its budget (None: the identification's budget, for a tracker or a
    multi-laser head; other instruments' tables need sigma or a budget) and a name."""

    instrument: str | Instrument
    source: str | Path | pd.DataFrame
    budget: str | Path | Budget | None = None
    name: str | None = None

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        return str(self.source) if isinstance(self.source, (str, Path)) else "<DataFrame>"


def parse_data_argument(text: str, default: str = "tracker") -> DataSet:
    """``"ballbar=circles.csv"`` -> DataSet("ballbar", Path("circles.csv")); a path
    without a registered instrument name before ``=`` is read by ``default``."""
    head, sep, tail = str(text).partition("=")
    if not sep:  # a plain path: the registry (which imports the numerics) is not needed
        return DataSet(default, Path(text))
    from volcal.measurement.instruments import instruments

    if head.strip() in instruments():
        return DataSet(head.strip(), Path(tail))
    return DataSet(default, Path(text))
