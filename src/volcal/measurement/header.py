"""The header of a table: its columns matched to a schema, with the standard library only.

:mod:`volcal.measurement.tables` validates whole tables with pandas; the matching of the
header row to the expected columns (missing, unknown, misnamed, doubled columns) needs
only the names, and lives here so that the command line can check a measurement table's
header before numpy's and pandas' import (a third of a second): :func:`check_header`
reads the first line of the file and raises the same :class:`InputError` that
:func:`volcal.measurement.tables.load_measurements` raises for that header.  Cells are
checked by the loader: a bad cell further down still needs the parser.

This module imports no numerical package (tests/test_startup_csv.py checks it).
"""

from __future__ import annotations

import csv
import difflib
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from volcal.base.exceptions import InputError

__all__ = ["check_header", "measurement_schema"]

_MAX_LISTED = 12  # problems listed in one message
_MAX_HEADER_BYTES = 1 << 20  # a first line longer than this is left to the loader


@dataclass
class _Problem:
    row: int | None
    column: str | None
    message: str


class _Problems:
    """The problems found in one pass over a table, raised together as one
    :class:`InputError` (the first in file order named by its row and column)."""

    def __init__(self, source: str):
        self.source = source
        self.items: list[_Problem] = []

    def add(self, row: int | None, column: str | None, message: str) -> None:
        self.items.append(_Problem(row, column, message))

    def raise_if_any(self) -> None:
        if not self.items:
            return
        # in file order (stable: problems of one row keep their order); row-less last
        self.items.sort(key=lambda p: (p.row is None, p.row or 0))
        first = self.items[0]
        msg = first.message
        rest = self.items[1:]
        if rest:
            lines = []
            for p in rest[: _MAX_LISTED - 1]:
                where = ", ".join(
                    ([f"row {p.row}"] if p.row is not None else [])
                    + ([f"column '{p.column}'"] if p.column is not None else [])
                )
                lines.append(f"  - {where}: {p.message}" if where else f"  - {p.message}")
            if len(rest) > _MAX_LISTED - 1:
                lines.append(f"  - ... and {len(rest) - (_MAX_LISTED - 1)} more")
            msg += f"\n{len(rest)} further problem(s) in {self.source}:\n" + "\n".join(lines)
        raise InputError(msg, source=self.source, row=first.row, column=first.column)


@dataclass(frozen=True)
class _Col:
    canonical: str
    synonyms: tuple[str, ...]
    required: bool
    kind: str  # "id", "float", "optfloat", "bool"
    unit: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return (self.canonical, *self.synonyms)


def measurement_schema(spec: Any) -> list[_Col]:
    """The columns of a measurement table for a machine (a
    :class:`volcal.model.spec.MachineSpec`: its axes name the axis columns)."""
    cols = [_Col("station", (), True, "id"), _Col("point", (), True, "id")]
    for a in spec.axes:
        unit = "deg" if a.is_rotary else "mm"
        cols.append(_Col(a.name, (f"{a.name}_{unit}",), True, "float", unit))
    cols += [_Col(f"tool_{c}", (f"tool_{c}_mm",), False, "float", "mm") for c in "xyz"]
    cols += [
        _Col("length", ("length_mm",), True, "float", "mm"),
        _Col("time", ("time_s",), False, "optfloat", "s"),
        _Col("sigma", ("sigma_mm",), False, "optfloat", "mm"),
    ]
    return cols


def _closest(name: str, candidates: Iterable[str]) -> str | None:
    low: dict[str, str] = {}
    for c in candidates:
        low.setdefault(c.lower(), c)
    m = difflib.get_close_matches(name.lower(), list(low), n=1, cutoff=0.6)
    return low[m[0]] if m else None


def resolve_columns(
    header: Sequence[str],
    schema: list[_Col],
    problems: _Problems,
    *,
    axis_names: list[str] | None = None,
    model_name: str | None = None,
) -> dict[str, int]:
    """Map canonical names to positions in the header (its cells stripped, "" for a blank
    one); report naming problems (row 1) and raise them."""
    by_name = {n: c for c in schema for n in c.names}
    allowed = [n for c in schema for n in c.names]
    found: dict[str, tuple[str, int]] = {}
    seen: dict[str, int] = {}
    unknown: list[tuple[str, int]] = []
    for k, h in enumerate(header):
        if h == "":
            problems.add(1, f"#{k + 1}", f"column {k + 1} has no name in the header row")
            continue
        if h in seen:
            problems.add(1, h, f"column '{h}' appears twice (columns {seen[h] + 1} and {k + 1})")
            continue
        seen[h] = k
        col = by_name.get(h)
        if col is None:
            unknown.append((h, k))
            continue
        if col.canonical in found:
            other = found[col.canonical][0]
            problems.add(
                1,
                h,
                f"columns '{other}' and '{h}' are the same quantity "
                f"({col.canonical}{', ' + col.unit if col.unit else ''}); keep one",
            )
            continue
        found[col.canonical] = (h, k)
    unknown_names = [u for u, _ in unknown]
    missing = [c for c in schema if c.required and c.canonical not in found]
    missing_axes = [c.canonical for c in missing if axis_names and c.canonical in axis_names]
    guessed: set[str] = set()
    for c in missing:
        if c.canonical in missing_axes:
            continue
        msg = f"missing required column '{c.canonical}'"
        if c.synonyms:
            msg += f" (or {', '.join(repr(s) for s in c.synonyms)})"
        if c.unit:
            msg += f", {c.unit}"
        guess = _closest(c.canonical, unknown_names) or (
            _closest(c.synonyms[0], unknown_names) if c.synonyms else None
        )
        if guess is not None:
            guessed.add(guess)
            msg += f"; is column '{guess}' meant to be '{c.canonical}'?"
        problems.add(1, c.canonical, msg)
    if missing_axes:
        msg = (
            f"the axis columns do not match the model '{model_name}': its axes are "
            f"{', '.join(axis_names or [])}; missing column(s) for "
            f"{', '.join(missing_axes)}"
        )
        extra = [u for u in unknown_names if re.fullmatch(r"[A-Z][A-Z0-9]{0,3}(_mm|_deg)?", u)]
        if extra:
            guessed.update(extra)
            msg += f"; the table has column(s) {', '.join(extra)} that the model has no axis for"
        problems.add(1, missing_axes[0], msg)
    for u, _ in unknown:
        if u in guessed:
            continue
        hint = _closest(u, allowed)
        msg = f"unknown column '{u}'"
        if hint is not None and hint != u:
            msg += f" (did you mean '{hint}'?)"
        problems.add(1, u, msg)
    if unknown:
        groups = []
        for c in schema:
            groups.append(c.canonical + (f" ({'/'.join(c.synonyms)})" if c.synonyms else ""))
        problems.add(1, None, "allowed columns: " + ", ".join(groups))
    problems.raise_if_any()
    return {canon: pos for canon, (_, pos) in found.items()}


def _header_cells(path: Path) -> list[str] | None:
    """The stripped cells of the first line of a CSV file as the loader's parser reads
    them, or None when this cheap reading could differ from it (the loader then decides):
    no such file, not UTF-8, an empty or a very long first line, quotes, a blank cell (an unnamed
    column the loader drops when it is empty throughout), a single cell (perhaps another
    separator, which the loader explains)."""
    try:
        with open(path, "rb") as fh:
            line = fh.readline(_MAX_HEADER_BYTES)
    except OSError:
        return None
    if len(line) >= _MAX_HEADER_BYTES:  # perhaps cut: not a header to judge by its start
        return None
    try:
        # a lone \r ends a line too (the parser's rule; old Mac files)
        text = line.decode("utf-8-sig").rstrip("\r\n").partition("\r")[0]
    except UnicodeDecodeError:
        return None
    if not text.strip() or '"' in text or "'" in text:
        return None
    cells = [c.strip() for c in next(csv.reader([text], skipinitialspace=True))]
    if len(cells) < 2 or "" in cells:
        return None
    return cells


def check_header(path: str | Path, spec: Any, *, name: str | None = None) -> None:
    """Raise the :class:`InputError` that :func:`volcal.measurement.tables.load_measurements`
    raises for the header of the measurement table at ``path`` (missing, unknown,
    misnamed or doubled columns; axis columns that do not match the model ``spec``, a
    :class:`volcal.model.spec.MachineSpec`), reading only its first line.  Returns
    quietly when the header is right and whenever the first line alone cannot decide
    (the loader then reads the whole file and reports whatever is wrong).  name: the
    source in messages (default: the path)."""
    path = Path(path)
    cells = _header_cells(path)
    if cells is None:
        return
    problems = _Problems(name if name is not None else str(path))
    resolve_columns(
        cells,
        measurement_schema(spec),
        problems,
        axis_names=list(spec.axis_names),
        model_name=spec.name,
    )
