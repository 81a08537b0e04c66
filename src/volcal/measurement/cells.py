"""A measurement table's cells read and checked with the standard library, before pandas.

:func:`volcal.measurement.tables.load_measurements` reads a CSV file with pandas; the
command line, to report a bad table before numpy's and pandas' import (a third of a
second), and the loader itself, for a small file, first call :func:`scan_measurements`,
which reads the file with the standard library (a split on commas, or the ``csv`` module
when the file has quotes) and either

* raises the :class:`InputError` that the pandas reading raises for the file's header and
  cells, word for word: columns (:mod:`volcal.measurement.header`), a row with more cells
  than the header, a cell that is not a number, empty or infinite, a length, axis position
  or sigma out of range (with the loader's warning about rotary axes in radians first), or
* returns the table as read (:class:`ScannedTable`: ids as text, numbers as floats), which
  the loader takes instead of reading the file again (the numbers parsed once: this
  reading costs what pandas' reading of the text and its ``to_numeric`` cost together at
  10^4 readings), or
* returns None when it cannot be sure to read the file as pandas does (not UTF-8, a NUL
  byte, a header the first line cannot decide, odd quoting the ``csv`` module rejects, a
  file above :data:`MAX_SCAN_BYTES`, 2 MiB): the loader then reads it with pandas, and a
  bad cell of a larger table is reported once pandas has read it.

A cell is a number when, stripped of blanks, it is a plain decimal (``[-+]``, digits with
an optional ``.``, an optional exponent) or an infinity (``inf``, ``infinity``, any case,
signed): exactly what pandas accepts.  Python's ``float`` accepts more (``1_000``, Arabic
digits, ``nan``): a column is read with ``float`` only after those are ruled out, and
cell by cell with the rule above otherwise.  tests/test_csv_cells.py draws spoilt tables
with hypothesis and checks that both readings give the same message.

The later checks of the loader (duplicate readings, readings per station, the stations
table, geometry) need the whole table and stay with it.  This module imports no numerical
package.
"""

from __future__ import annotations

import csv
import io
import math
import operator
import re
import warnings
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from itertools import repeat
from pathlib import Path
from typing import Any

from volcal.base.exceptions import InputError
from volcal.measurement.header import (
    _header_cells,
    _Problems,
    measurement_schema,
    resolve_columns,
)

__all__ = [
    "DataWarning",
    "MAX_LENGTH_MM",
    "MAX_SCAN_BYTES",
    "NA_STRINGS",
    "ScannedTable",
    "TRAVEL_TOLERANCE",
    "scan_measurements",
    "separator_hint",
]

#: Lengths above this (mm, i.e. 100 m) are rejected as absurd (probably not in mm).
MAX_LENGTH_MM = 100_000.0
#: Relative tolerance on axis travel: a position may exceed the travel by this fraction
#: of the travel range (max - min).
TRAVEL_TOLERANCE = 1e-6
#: Cells read as missing values (any case, surrounding blanks ignored).
NA_STRINGS = frozenset({"nan", "na", "n/a", "null", "none"})
#: Files larger than this (bytes, about 2 x 10^4 readings) are left to pandas: at 10^4
#: readings this reading and pandas' take the same time (the numbers are parsed once,
#: here), at 10^5 this one took 15 % more time and 50 MiB more memory.
MAX_SCAN_BYTES = 2 << 20

_NUMBER = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?")
_INTEGER = re.compile(r"\s*[-+]?[0-9]+\s*")
_INFINITY = re.compile(r"([-+]?)inf(?:inity)?", re.IGNORECASE)
_DECIMAL_COMMA = re.compile(r"\s*[-+]?\d+,\d+\s*")
CONVERT_HINT = (
    "(convert it, e.g. pandas.read_csv(path, sep=';', decimal=',').to_csv(new_path, index=False))"
)


class DataWarning(UserWarning):
    """Suspicious but usable input data (weak station geometry, few readings, ...)."""


def separator_hint(path: Path) -> str:
    """A hint when the first line shows ';', tab or '|' separators (a spreadsheet's export
    in a locale with decimal commas)."""
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as fh:
            first = fh.readline()
    except OSError:
        return ""
    for sep, name in ((";", "semicolons"), ("\t", "tabs"), ("|", "'|'")):
        if first.count(sep) >= 1 and first.count(sep) >= first.count(","):
            return (
                f"; the header is separated by {name}, and decimal commas would then split "
                "numbers: volcal reads comma-separated files with '.' as the decimal mark "
                + CONVERT_HINT
            )
    return ""


# --------------------------------------------------------------------------------------
# the loader's messages (volcal.measurement.tables uses the same functions)


def describe(v: Any) -> str:
    """A cell as quoted in messages (stripped text)."""
    return repr(v.strip()) if isinstance(v, str) else repr(v)


def not_a_number(unit: str, v: Any) -> str:
    return f"expected a number ({unit}), got {describe(v)}" + (
        " (a decimal comma? volcal reads '.' as the decimal mark)"
        if isinstance(v, str) and _DECIMAL_COMMA.fullmatch(v)
        else ""
    )


def missing_number(unit: str) -> str:
    return f"missing value (empty cell or NaN); expected a number ({unit})"


def not_finite(unit: str, v: Any) -> str:
    return f"expected a finite number ({unit}), got {describe(v)}"


MISSING_ID = "missing id (empty cell or NaN); expected a text id"


def length_too_long_relative(v: float) -> str:
    return (
        f"|length| {v:g} mm exceeds the plausibility bound of "
        f"{MAX_LENGTH_MM:g} mm (100 m); lengths are in mm"
    )


def length_not_positive(v: float) -> str:
    return (
        f"expected a positive length in mm, got {v:g} (pass "
        "relative_lengths=True for readings relative to a dead length)"
    )


def length_too_long(v: float) -> str:
    return (
        f"length {v:g} mm exceeds the plausibility bound of "
        f"{MAX_LENGTH_MM:g} mm (100 m); lengths are in mm"
    )


def outside_travel(axis: Any, v: float) -> str:
    lo, hi = axis.travel
    tol = TRAVEL_TOLERANCE * (hi - lo)
    unit = "deg" if axis.is_rotary else "mm"
    return (
        f"{axis.name} = {v:g} {unit} is outside the travel [{lo:g}, {hi:g}] {unit} of "
        f"axis {axis.name} (tolerance {tol:g} {unit})"
    )


def sigma_not_positive(v: float) -> str:
    return f"expected a positive standard uncertainty in mm, got {v:g}"


def looks_like_radians(name: str, column: str, axis: Any, lo_v: float, hi_v: float) -> str:
    lo, hi = axis.travel
    return (
        f"{name}: column '{column}' (rotary axis {axis.name}) looks like "
        f"radians: every value lies within +-2 pi ({lo_v:.4g} to "
        f"{hi_v:.4g}) while the travel spans {lo:g} to {hi:g} deg; rotary "
        "axis positions are read in degrees"
    )


def radians_suspected(axis: Any, finite: Sequence[float]) -> bool:
    """The loader's rule: a rotary axis whose travel spans 180 deg or more, with every
    (finite) value within +-2 pi, spread over more than one unit and not all whole."""
    lo, hi = axis.travel
    return bool(
        len(finite)
        and hi - lo >= 180.0
        and all(abs(v) <= 2 * math.pi + 1e-9 for v in finite)
        and max(finite) - min(finite) > 1.0
        and not all(v.is_integer() for v in finite)
    )


# --------------------------------------------------------------------------------------
# reading


@dataclass(frozen=True)
class ScannedTable:
    """A measurement table read by :func:`scan_measurements`, its cells checked: a source
    :func:`volcal.measurement.tables.load_measurements` accepts.  ``columns`` by file
    column: ids as text (as in the file), numbers as ``array('d')`` (NaN: an empty
    optional cell); ``rows``: the spreadsheet row of each reading (header = row 1)."""

    name: str
    header: tuple[str, ...]
    columns: tuple[list[str] | array, ...]
    rows: array


class _Defer(Exception):
    """The file cannot be read here as pandas reads it: left to the loader."""


def _records(text: str, ncols: int) -> tuple[list[list[str]], list[int]]:
    """The data records (header dropped; short ones padded with empty cells, blank ones
    dropped) and their spreadsheet rows; raises the parser's error for a record with more
    cells than the header (first such record), or _Defer."""
    if '"' in text:
        try:
            recs = list(csv.reader(io.StringIO(text, newline=""), skipinitialspace=True))
        except csv.Error:
            raise _Defer from None
    else:
        if "\r" in text:  # pandas ends a line at \r\n, \n and a lone \r alike
            text = text.replace("\r\n", "\n").replace("\r", "\n")
        if text.endswith("\n"):
            text = text[:-1]
        recs = [line.split(",") for line in text.split("\n")]
    out: list[list[str]] = []
    rows: list[int] = []
    for r, rec in enumerate(recs[1:], start=2):
        n = len(rec)
        if n > ncols:
            raise _TooLong(r, n)
        if n < ncols:
            rec = rec + [""] * (ncols - n)
        if all(not c or c.isspace() for c in rec):
            continue  # a blank line: skipped, counted in the row numbers
        out.append(rec)
        rows.append(r)
    return out, rows


class _TooLong(Exception):
    def __init__(self, row: int, n: int):
        self.row, self.n = row, n


def _fast_columns(text: str, ncols: int) -> tuple[list[list[str]], int] | None:
    """The columns of a file without quotes, blank lines or short/long rows, by one
    split of the whole text on commas (None otherwise)."""
    if '"' in text:
        return None
    if "\r" in text:
        text = text.replace("\r\n", "\n")  # Windows' line ends
        if "\r" in text:
            return None
    start = text.find("\n") + 1
    end = len(text) - 1 if text.endswith("\n") else len(text)
    if start <= 0 or end <= start:
        return None
    n = text.count("\n", start, end) + 1
    pieces = text[start:end].split(",")
    m = ncols - 1
    if len(pieces) != n * m + 1:
        return None
    # with n * (ncols - 1) commas and n - 1 line ends, every line has ncols - 1 commas
    # exactly when each of the n - 1 pieces that should hold a line end holds one
    # (last cell, line end, first cell of the next line)
    ends = pieces[m:-1:m]
    if not all(map(operator.contains, ends, repeat("\n"))):
        return None
    split = "\n".join(ends).split("\n")  # last, first, last, first, ...
    first = [pieces[0], *split[1::2]]
    last = [*split[0::2], pieces[-1]]
    return [first, *(pieces[j::m] for j in range(1, m)), last], n


def _floats(cells: list[str], plain: bool) -> tuple[list[float], list[int], list[int], list[int]]:
    """(values, bad, blank, infinite): values NaN where a cell is blank, not a number or
    infinite, with the indices of each.  ``plain``: the column's text has no underscore
    and is ASCII (Python's ``float`` then accepts exactly pandas' numbers, nan and inf
    aside, which the sum shows)."""
    if plain:
        try:
            vals = list(map(float, cells))  # a list: min, max and sum unbox nothing
        except ValueError:
            pass
        else:
            total = sum(vals)
            if not (math.isnan(total) or math.isinf(total)):
                if 0.0 in vals and all(map(_INTEGER.fullmatch, cells)):
                    # pandas reads a column of whole numbers as integers: no -0
                    vals = [v + 0.0 for v in vals]
                return vals, [], [], []
    vals = [0.0] * len(cells)
    bad: list[int] = []
    blank: list[int] = []
    inf: list[int] = []
    nan = math.nan
    for k, c in enumerate(cells):
        s = c.strip()
        if not s or s.lower() in NA_STRINGS:
            blank.append(k)
            vals[k] = nan
        elif _NUMBER.fullmatch(s):
            v = float(s)
            if math.isinf(v):  # 1e999
                inf.append(k)
                v = nan
            vals[k] = v
        else:
            m = _INFINITY.fullmatch(s)
            if m is not None:
                inf.append(k)
            else:
                bad.append(k)
            vals[k] = nan
    return vals, bad, blank, inf


def _report(
    problems: _Problems,
    rows: Sequence[int],
    idx: Sequence[int],
    column: str,
    message: str | Callable[[int], str],
) -> None:
    """One problem at the first index in ``idx``, with a count (the loader's _report)."""
    if not idx:
        return
    k = idx[0]
    msg = message(k) if callable(message) else message
    if len(idx) > 1:
        msg += f" (and {len(idx) - 1} more row(s) in this column)"
    problems.add(int(rows[k]), column, msg)


def scan_measurements(
    path: str | Path,
    spec: Any,
    *,
    name: str | None = None,
    relative_lengths: bool = False,
) -> ScannedTable | None:
    """Read the measurement table at ``path`` for the machine ``spec`` (a
    :class:`volcal.model.spec.MachineSpec`) with the standard library: raise the
    :class:`InputError` that :func:`volcal.measurement.tables.load_measurements` raises
    for its header, its rows and its cells (units: lengths and linear axes in mm, rotary
    axes in degrees, time in s), return the table read (:class:`ScannedTable`), or None
    when the loader must read the file with pandas (see the module docstring).  name: the
    source in messages (default: the path); relative_lengths: as the loader's."""
    path = Path(path)
    label = name if name is not None else str(path)
    try:
        if not path.is_file() or path.stat().st_size > MAX_SCAN_BYTES:
            return None
        with open(path, "rb") as fh:
            data = fh.read()
        text = data.decode("utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    del data
    header = _header_cells(path)  # None: a first line for pandas to read
    if header is None or "\x00" in text:
        return None
    ncols = len(header)
    # Python's float reads a plain column (ASCII, no underscore) as pandas does
    plain_text = text.isascii() and text.find("_", text.find("\n") + 1) < 0  # not the header's
    # the rows first: pandas reports a row longer than the header before the header
    rows: Sequence[int]
    fast = _fast_columns(text, ncols)
    if fast is not None and not all(map(str.strip, fast[0][0])):
        fast = None  # perhaps a blank row (blank in every column): read record by record
    if fast is not None:
        columns, n = fast
        rows = range(2, n + 2)
    else:
        try:
            records, rows = _records(text, ncols)
        except _Defer:
            return None
        except _TooLong as exc:
            raise InputError(
                f"cannot parse as CSV: Error tokenizing data. C error: Expected {ncols} "
                f"fields in line {exc.row}, saw {exc.n}\n{separator_hint(path)}",
                source=label,
                row=exc.row,
            ) from None
        if not records:
            raise InputError(
                "the measurement table has a header but no data rows", source=label, row=2
            )
        columns = [list(c) for c in zip(*records)]
        del records
    del text
    problems = _Problems(label)
    pos = resolve_columns(
        header,
        measurement_schema(spec),
        problems,
        axis_names=list(spec.axis_names),
        model_name=spec.name,
    )  # raises the header's problems
    label_of = {c: header[p] for c, p in pos.items()}
    for c in ("station", "point"):
        ids = columns[pos[c]]
        if fast is None or not all(map(str.strip, ids)):
            missing = [k for k, v in enumerate(ids) if not v or v.isspace()]
            _report(problems, rows, missing, label_of[c], MISSING_ID)
    values: dict[str, tuple[list[float], bool]] = {}
    numbers: dict[int, array] = {}
    units = {a.name: ("deg" if a.is_rotary else "mm") for a in spec.axes}
    order = [(a.name, units[a.name], False) for a in spec.axes]
    order += [(f"tool_{x}", "mm", False) for x in "xyz" if f"tool_{x}" in pos]
    order += [("length", "mm", False)]
    order += [(c, u, True) for c, u in (("time", "s"), ("sigma", "mm")) if c in pos]
    for c, unit, optional in order:
        cells = columns[pos[c]]
        plain = plain_text
        if not plain:
            joined = "".join(cells)
            plain = joined.isascii() and "_" not in joined
        vals, bad, blank, inf = _floats(cells, plain)
        col = label_of[c]
        _report(problems, rows, bad, col, partial(_cell, not_a_number, unit, cells))
        if not optional:
            _report(problems, rows, blank, col, missing_number(unit))
        _report(problems, rows, inf, col, partial(_cell, not_finite, unit, cells))
        values[c] = (vals, not (bad or blank or inf))
        numbers[pos[c]] = array("d", vals)
    L = label_of["length"]
    if relative_lengths:
        _where(problems, rows, values["length"], lambda v: abs(v) > MAX_LENGTH_MM, L,
               length_too_long_relative)  # fmt: skip
    else:
        _where(problems, rows, values["length"], lambda v: v <= 0, L, length_not_positive)
        _where(problems, rows, values["length"], lambda v: v > MAX_LENGTH_MM, L,
               length_too_long)  # fmt: skip
    for a in spec.axes:
        lo, hi = a.travel
        tol = TRAVEL_TOLERANCE * (hi - lo)
        _where(problems, rows, values[a.name], partial(_outside, lo - tol, hi + tol),
               label_of[a.name], partial(outside_travel, a))  # fmt: skip
    if "sigma" in pos:
        _where(problems, rows, values["sigma"], lambda v: v <= 0, label_of["sigma"],
               sigma_not_positive)  # fmt: skip
    if problems.items:
        # the loader warns of radians before it raises
        for a in spec.axes:
            if a.is_rotary:
                finite = [v for v in values[a.name][0] if math.isfinite(v)]
                if radians_suspected(a, finite):
                    warnings.warn(
                        looks_like_radians(label, label_of[a.name], a, min(finite), max(finite)),
                        DataWarning,
                        stacklevel=2,
                    )
        problems.raise_if_any()
    out = tuple(numbers.get(k, columns[k]) for k in range(ncols))
    return ScannedTable(label, tuple(header), out, array("q", rows))


def _cell(message: Callable[[str, Any], str], unit: str, cells: list[str], k: int) -> str:
    return message(unit, cells[k])


def _outside(lo: float, hi: float, v: float) -> bool:
    return v < lo or v > hi


def _where(
    problems: _Problems,
    rows: Sequence[int],
    column_values: tuple[list[float], bool],
    test: Callable[[float], bool],
    column: str,
    message: Callable[[float], str],
) -> None:
    """A range problem at the rows where ``test`` holds (never at NaN): for a column
    without NaN the smallest and largest value decide whether to look cell by cell (the
    tests are bounds)."""
    vals, clean = column_values
    if clean and not (test(min(vals)) or test(max(vals))):
        return
    idx = [k for k, v in enumerate(vals) if test(v)]
    _report(problems, rows, idx, column, lambda k: message(vals[k]))
