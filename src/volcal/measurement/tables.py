"""Loading and validation of the measurement table and the stations table.

Both tables come from a CSV file (comma separated, UTF-8, optional byte-order mark) or a
pandas DataFrame.  Loading never writes anything and never modifies the caller's object:
the validated tables are new DataFrames.

Measurement table (one row per length reading; DESIGN.md)
=========================================================

=====================================  ===========  ========  ======================================
column (accepted synonym)              required     unit      meaning
=====================================  ===========  ========  ======================================
``station``                            yes          -         station (tracker position) or laser id
``point``                              yes          -         id of the commanded pose
one per model axis, named as the axis  yes          mm / deg  commanded axis position; linear axes
(``X`` or ``X_mm``, ``B`` or ``B_deg``)                       in mm, rotary axes in degrees
``tool_x`` ``tool_y`` ``tool_z``       no (0)       mm        reflector offset in the tool frame
(``tool_x_mm`` ...)
``length`` (``length_mm``)             yes          mm        measured length
``time`` (``time_s``)                  no (NaN)     s         time stamp; empty cells allowed
``sigma`` (``sigma_mm``)               no (NaN)     mm        standard uncertainty overriding the
                                                              budget; empty cells allowed
=====================================  ===========  ========  ======================================

Column names are matched exactly (surrounding blanks ignored).  Any other column is an
error (a misspelled axis must never be ignored silently) and so is giving both forms of
one column (``length`` and ``length_mm``).  The validated :attr:`Measurements.table` has
the DESIGN.md names in this order: ``station, point, <axes in model order>, tool_x,
tool_y, tool_z, length, time, sigma`` (file units: mm, deg, s), with ``station`` and
``point`` as strings (ids are always read as text, so ``"01"`` stays ``"01"``), absent
tool columns filled with 0.0 and absent ``time``/``sigma`` with NaN.

Stations table
==============

==================================  ========  =====  =========================================
column (accepted synonym)           required  unit   meaning
==================================  ========  =====  =========================================
``station``                         yes       -      station id (text)
``x_mm`` ``y_mm`` ``z_mm``          yes       mm     station position (approximate or known)
(``x`` ``y`` ``z``)
``dead_length_mm`` (``dead_length``) no        mm     dead length; empty cell = not given
``fixed``                           no        -      true when the position is known and must
                                                     not be estimated (default false)
==================================  ========  =====  =========================================

The unit-suffixed names are preferred; DESIGN.md's ``x, y, z, dead_length`` are accepted
as synonyms (also in mm).  :func:`load_stations` returns the internal form, columns
``station, x_mm, y_mm, z_mm, dead_length_mm, dead_length_given, fixed``:
``dead_length_mm`` is 0.0 where no dead length was given and ``dead_length_given`` says
which rows had one.  That output is itself a valid input (``dead_length_given`` is accepted).
``fixed`` accepts ``true/false, yes/no, 1/0`` (any case) and booleans.

Errors and warnings
===================

Every defect raises :class:`volcal.base.exceptions.InputError` naming the file (or the
DataFrame's ``name``, default ``"<DataFrame>"``), the row as a spreadsheet shows it
(header = row 1, first data row = row 2; for a DataFrame the position + 2, i.e. the row it
would have once saved with ``to_csv(index=False)``), the column and what was expected.
Problems found in one pass are collected into one message; the exception's ``row`` and
``column`` are those of the first.  Suspicious but usable data produce a
:class:`DataWarning` (see :func:`load_measurements`).
"""

from __future__ import annotations

import re
import warnings
from array import array
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError
from volcal.measurement import cells as _cells
from volcal.measurement.cells import (
    MAX_LENGTH_MM,
    TRAVEL_TOLERANCE,
    DataWarning,
    ScannedTable,
    scan_measurements,
)
from volcal.measurement.cells import NA_STRINGS as _NA_STRINGS
from volcal.measurement.cells import separator_hint as _separator_hint
from volcal.measurement.header import (
    _closest,
    _Col,
    _header_cells,
    _Problems,
)
from volcal.measurement.header import measurement_schema as _measurement_schema
from volcal.measurement.header import resolve_columns as _resolve_header
from volcal.model.spec import MachineSpec, resolve_model

__all__ = [
    "DataWarning",
    "Measurements",
    "load_measurements",
    "load_stations",
    "load_instrument_stations",
    "parse_column_map",
    "MAX_LENGTH_MM",
    "TRAVEL_TOLERANCE",
    "MIN_READINGS_PER_STATION",
    "FEW_READINGS_PER_STATION",
    "COPLANAR_RTOL",
    "DATAFRAME_NAME",
]

#: A station with fewer readings cannot be located (3 coordinates and a dead length).
MIN_READINGS_PER_STATION = 4
#: A station with fewer readings than this draws a :class:`DataWarning`.
FEW_READINGS_PER_STATION = 10
#: The points seen by a station are coplanar when the smallest singular value of their
#: centred nominal coordinates is below this fraction of the largest.
COPLANAR_RTOL = 1e-6
#: Name used in messages for a DataFrame given without ``name``.
DATAFRAME_NAME = "<DataFrame>"

_TRUE = {"true", "t", "yes", "y", "1"}
_FALSE = {"false", "f", "no", "n", "0"}


# --------------------------------------------------------------------------------------
# result object


@dataclass(frozen=True, eq=False)
class Measurements:
    """A validated measurement table and the arrays the solver needs (N readings).

    table: validated DataFrame (see the module docstring for its columns; file units).
    source: file path or DataFrame name used in messages.
    axis_names: model axes in chain order, the columns of ``q_internal``.
    station_ids: distinct station ids in order of first appearance.
    station_index: (N,) int, index of each reading's station into ``station_ids``.
    point_ids: distinct point ids in order of first appearance.
    point_index: (N,) int, index of each reading's point into ``point_ids``.
    q_internal: (N, n_axes) float, axis positions in mm (linear) and rad (rotary).
    tool: (N, 3) float, tool (reflector) offset in the tool frame, mm.
    length: (N,) float, measured lengths, mm.
    sigma: (N,) float, standard uncertainty per reading, mm, NaN where not given.
    time: (N,) float, time stamps, s, NaN where not given.
    rows: (N,) int, spreadsheet row of each reading in the source (header = row 1).
    given_columns: the canonical names of the columns the source had.
    stations: the validated stations table (:func:`load_stations` form) or None.

    The arrays are read-only.
    """

    table: pd.DataFrame
    source: str
    axis_names: tuple[str, ...]
    station_ids: list[str]
    station_index: np.ndarray
    point_ids: list[str]
    point_index: np.ndarray
    q_internal: np.ndarray
    tool: np.ndarray
    length: np.ndarray
    sigma: np.ndarray
    time: np.ndarray
    rows: np.ndarray
    given_columns: tuple[str, ...]
    stations: pd.DataFrame | None = None

    def __len__(self) -> int:
        return int(self.length.shape[0])

    @property
    def n(self) -> int:
        """Number of readings."""
        return len(self)

    @property
    def has_time(self) -> bool:
        """True when at least one reading has a time stamp."""
        return bool(np.isfinite(self.time).any())

    @property
    def has_sigma(self) -> bool:
        """True when at least one reading has its own standard uncertainty."""
        return bool(np.isfinite(self.sigma).any())


# --------------------------------------------------------------------------------------
# reading


@dataclass
class _Raw:
    name: str
    header: list[str]
    body: pd.DataFrame  # positional integer columns, object values
    rows: np.ndarray  # spreadsheet row of each body row


def _stripped(col: pd.Series) -> pd.Series:
    """``col.str.strip()`` of a column of text, without pandas' Python call per cell when
    no cell holds a blank (ids like ``LT1``, ``p0001``): one search of the joined text
    (``\\s`` is what str.strip removes).  A column with a missing cell is stripped."""
    try:
        joined = "\x00".join(col.tolist())
    except TypeError:  # NaN or None among the cells
        return col.str.strip()
    return col.str.strip() if _BLANK.search(joined) else col


_BLANK = re.compile(r"\s")


def _blank_cells(col: pd.Series) -> np.ndarray:
    """:func:`_is_blank` of every cell of a column read as text (strings; NaN or None where
    a short row has no cell), vectorised."""
    if col.dtype != object and not pd.api.types.is_string_dtype(col):
        return np.asarray(col.isna(), bool)
    text = _stripped(col)  # NaN for cells that are not strings
    return np.asarray(col.isna(), bool) | np.asarray(text.eq("").fillna(False), bool)


def _is_blank(v: Any) -> bool:
    if v is None:
        return True
    if isinstance(v, str):
        return v.strip() == ""
    try:
        return bool(pd.isna(v))
    except (TypeError, ValueError):
        return False


_CONVERT_HINT = _cells.CONVERT_HINT


#: How pandas reads a measurement file: every cell as written (no missing-value words, blank
#: lines kept so that row numbers are the file's), blanks after a separator skipped, a
#: UTF-8 byte-order mark allowed
_CSV_OPTIONS: dict[str, Any] = {
    "keep_default_na": False,
    "na_filter": False,
    "skip_blank_lines": False,
    "skipinitialspace": True,
    "encoding": "utf-8-sig",
}


def _read_raw(
    source: str | Path | pd.DataFrame | ScannedTable, name: str | None, what: str
) -> _Raw:
    if isinstance(source, ScannedTable):
        # read and checked cell by cell by volcal.measurement.cells: ids as text, numbers
        # as floats (NaN: an empty optional cell), blank lines dropped
        body = pd.DataFrame(
            {
                k: np.frombuffer(c, dtype=float) if isinstance(c, array) else np.array(c, object)
                for k, c in enumerate(source.columns)
            }
        )
        rows = np.frombuffer(source.rows, dtype=np.int64).astype(int)
        return _Raw(name if name is not None else source.name, list(source.header), body, rows)
    if isinstance(source, pd.DataFrame):
        label = name if name is not None else DATAFRAME_NAME
        header = [str(c).strip() for c in source.columns]
        body = pd.DataFrame(
            {k: source.iloc[:, k].to_numpy(dtype=object, copy=True) for k in range(source.shape[1])}
        )
        rows = np.arange(source.shape[0], dtype=int) + 2
        if source.shape[0] == 0:
            raise InputError(f"the {what} has no data rows", source=label)
        return _Raw(label, header, body, rows)
    if not isinstance(source, (str, Path)):
        raise InputError(
            f"expected a CSV path or a pandas DataFrame for the {what}, got "
            f"{type(source).__name__}",
            source=name,
        )
    path = Path(source)
    label = name if name is not None else str(path)
    if not path.is_file():
        raise InputError(f"no such {what} file", source=label)
    try:
        raw = pd.read_csv(
            path,
            header=None,
            dtype=str,
            **_CSV_OPTIONS,
        )
    except pd.errors.EmptyDataError:
        raise InputError(
            f"the {what} file is empty; expected a header row", source=label, row=1
        ) from None
    except pd.errors.ParserError as exc:
        m = re.search(r"line (\d+)", str(exc))
        raise InputError(
            f"cannot parse as CSV: {exc}{_separator_hint(path)}",
            source=label,
            row=int(m.group(1)) if m else None,
        ) from None
    except UnicodeDecodeError as exc:
        raise InputError(f"not UTF-8 text: {exc}", source=label) from None
    except OSError as exc:
        raise InputError(f"cannot read {what} file: {exc.strerror or exc}", source=label) from None
    header_cells = ["" if _is_blank(v) else str(v).strip() for v in raw.iloc[0].tolist()]
    body = raw.iloc[1:].reset_index(drop=True)
    body.columns = range(body.shape[1])
    rows = np.arange(body.shape[0], dtype=int) + 2
    # fully blank lines (often trailing) are skipped; the row numbers stay those of the file.
    # A row is blank when every cell is: each further column is checked only on the rows
    # still blank (one pass over one column for a table without blank lines)
    all_blank = np.ones(body.shape[0], bool)
    for c in body.columns:
        idx = np.flatnonzero(all_blank)
        if idx.size == 0:
            break
        all_blank[idx] = (
            _blank_cells(body[c].iloc[idx]) if idx.size < len(body) else (_blank_cells(body[c]))
        )
    keep = ~all_blank
    body = body.loc[keep].reset_index(drop=True)
    rows = rows[keep]
    # unnamed columns that are empty throughout (trailing separators) are dropped
    drop = [k for k, h in enumerate(header_cells) if h == "" and _blank_cells(body[k]).all()]
    if drop:
        body = body.drop(columns=drop)
        header_cells = [h for k, h in enumerate(header_cells) if k not in drop]
        body.columns = range(body.shape[1])
    if len(header_cells) == 1 and re.search(r"[;\t|]", header_cells[0]):
        raise InputError(
            f"the header {header_cells[0]!r} looks separated by ';', tab or '|'; "
            "volcal reads comma-separated files with '.' as the decimal mark "
            f"{_CONVERT_HINT}",
            source=label,
            row=1,
        )
    if body.shape[0] == 0:
        raise InputError(f"the {what} has a header but no data rows", source=label, row=2)
    return _Raw(label, header_cells, body, rows)


#: Whether :func:`load_measurements` first tries :func:`_read_typed` on a file the
#: standard-library reading leaves to pandas (tests turn it off to compare the readings).
TYPED_READING = True


def _read_typed(path: Path, spec: MachineSpec, name: str | None) -> _Raw | None:
    """A clean measurement table read by pandas with its number columns parsed as floats
    by the C parser, or None when the file is not clean (the text reading then reads it
    and reports what is wrong, word for word).

    The text reading (:func:`_read_raw`, every cell a Python string, then
    ``pandas.to_numeric``) costs about six times this at 3 x 10^5 readings.  The number
    columns are those the header names (axes, tool offsets, length, time, sigma; decided
    from the first line by the loader's own rules); every other column is read as text,
    as before.  Clean: a plain header (:func:`volcal.measurement.header._header_cells`),
    every row as long as the header, no blank line, every number cell a finite number
    and every text cell present.  pandas' float parser rounds correctly, as
    ``to_numeric`` does (tests/test_csv_cells.py compares both readings on spoilt files),
    so a clean file gives the same Measurements either way."""
    header = _header_cells(path)
    if header is None:
        return None
    try:
        pos = _resolve_header(
            header,
            _measurement_schema(spec),
            _Problems(str(path)),
            axis_names=list(spec.axis_names),
            model_name=spec.name,
        )
    except InputError:
        return None  # the text reading reports the header's problems in its order
    text_columns = {pos["station"], pos["point"]}
    dtypes = {k: (str if k in text_columns else np.float64) for k in range(len(header))}
    try:
        body = pd.read_csv(
            path,
            header=None,
            skiprows=1,
            dtype=dtypes,
            **_CSV_OPTIONS,
        )
    except (ValueError, OSError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return None  # a cell that is not a number, a long row, not UTF-8, no rows ...
    if body.shape[1] != len(header) or body.shape[0] == 0:
        return None
    for k in range(len(header)):
        col = body[k]
        if k in text_columns:
            if col.isna().any() or _blank_cells(col).any():
                return None
        elif col.dtype != np.float64 or not np.isfinite(col.to_numpy()).all():
            return None  # nan, inf (the text reading names the cell as written)
    rows = np.arange(body.shape[0], dtype=int) + 2
    return _Raw(name if name is not None else str(path), list(header), body, rows)


# --------------------------------------------------------------------------------------
# column mapping (instrument exports)

#: units a mapped column may carry, with their factor to volcal's unit (mm, deg, s)
_MAP_UNITS = {
    "mm": ("mm", 1.0),
    "m": ("mm", 1000.0),
    "um": ("mm", 1e-3),
    "µm": ("mm", 1e-3),
    "in": ("mm", 25.4),
    "deg": ("deg", 1.0),
    "rad": ("deg", 180.0 / np.pi),
    "s": ("s", 1.0),
    "ms": ("s", 1e-3),
    "min": ("s", 60.0),
}


def parse_column_map(spec: Mapping[str, str] | str) -> dict[str, tuple[str, str | None]]:
    """``{volcal column: (file column, unit or None)}`` from ``"length=L[m],station=Tracker"``
    or a mapping ``{"length": "L[m]"}``; the unit in brackets is the file's (mm, m, um,
    in, deg, rad, s, ms, min).  Raises :class:`InputError` on a malformed entry."""
    items = (
        [tuple(part.split("=", 1)) for part in spec.split(",") if part.strip()]
        if isinstance(spec, str)
        else list(spec.items())
    )
    out: dict[str, tuple[str, str | None]] = {}
    for item in items:
        if len(item) != 2 or not str(item[0]).strip() or not str(item[1]).strip():
            raise InputError(
                f"column mapping entry {'='.join(map(str, item))!r}: expected "
                "VOLCAL_COLUMN=FILE_COLUMN[UNIT], e.g. length=L[m]",
                source="--columns",
            )
        key, val = str(item[0]).strip(), str(item[1]).strip()
        m = re.fullmatch(r"(.+?)\s*\[\s*([^\]]+?)\s*\]", val)
        col, unit = (m.group(1), m.group(2)) if m else (val, None)
        if unit is not None and unit not in _MAP_UNITS:
            raise InputError(
                f"column mapping {key}={val}: unknown unit {unit!r}; expected one of "
                f"{', '.join(_MAP_UNITS)}",
                source="--columns",
            )
        if key in out:
            raise InputError(
                f"column mapping: {key} is given twice ({key}={out[key][0]} and {key}={val}); "
                "give each volcal column once",
                source="--columns",
            )
        out[key] = (col, unit)
    return out


def _map_columns(raw: _Raw, mapping: dict[str, tuple[str, str | None]], spec) -> _Raw:
    """The raw table with the mapped file columns renamed to volcal's and their values
    converted to volcal's units (values that are not numbers are left for the validator
    to report by row and column)."""
    canon = {n: c for c in _measurement_schema(spec) for n in c.names}
    header = list(raw.header)
    body = raw.body.copy()
    taken: dict[int, str] = {}  # file column index -> the volcal column it became
    target: dict[str, str] = {}  # volcal column -> the mapping key that named it
    for key, (col, unit) in mapping.items():
        if key not in canon:
            close = _closest(key, canon)
            raise InputError(
                f"column mapping: volcal has no column {key!r}"
                + (f" (did you mean {close!r}?)" if close else "")
                + f"; columns: {', '.join(c.canonical for c in _measurement_schema(spec))}",
                source=raw.name,
            )
        if col not in raw.header and unit is not None:
            # a file column named with its unit ("Distance [m]"): the bracket is both part
            # of the name and the unit of the values
            col = next((c for c in (f"{col} [{unit}]", f"{col}[{unit}]") if c in raw.header), col)
        if col not in raw.header:
            raise InputError(
                f"column mapping {key}={col}: the file has no column {col!r}; its columns: "
                f"{', '.join(raw.header)}",
                source=raw.name,
                row=1,
            )
        k = list(raw.header).index(col)
        if k in taken:
            # one file column is one quantity: its values cannot be, say, both the length
            # and its uncertainty
            raise InputError(
                f"column mapping: the file column {col!r} is mapped to both {taken[k]} and "
                f"{key}; map each file column to one volcal column",
                source=raw.name,
            )
        if canon[key].canonical in target:
            raise InputError(
                f"column mapping: {target[canon[key].canonical]} and {key} both name volcal's "
                f"column {canon[key].canonical}; give it once",
                source=raw.name,
            )
        taken[k], target[canon[key].canonical] = key, key
        header[k] = canon[key].canonical
        if unit is not None:
            want = canon[key].unit
            key = canon[key].canonical
            base, factor = _MAP_UNITS[unit]
            if want and base != want:
                raise InputError(
                    f"column mapping {key}={col}[{unit}]: {key} is in {want}, a {unit} "
                    "value cannot be converted to it",
                    source=raw.name,
                )

            def conv(v, f=factor):
                try:
                    return repr(float(v) * f) if not _is_blank(v) else v
                except (TypeError, ValueError):
                    return v

            body[k] = body[k].map(conv)
    return _Raw(raw.name, header, body, raw.rows)


# --------------------------------------------------------------------------------------
# columns


def _resolve_columns(
    raw: _Raw,
    schema: list[_Col],
    problems: _Problems,
    *,
    axis_names: list[str] | None = None,
    model_name: str | None = None,
) -> dict[str, int]:
    """Map canonical names to positions in ``raw.body``; report naming problems (row 1).
    The header's rules are in :mod:`volcal.measurement.header` (standard library only, so
    that the command line checks a header before pandas is imported)."""
    return _resolve_header(
        raw.header, schema, problems, axis_names=axis_names, model_name=model_name
    )


# --------------------------------------------------------------------------------------
# values


_describe = _cells.describe


def _report(
    problems: _Problems, rows: np.ndarray, mask: np.ndarray, column: str, message: Any
) -> None:
    """One problem at the first row in ``mask`` (message(k) for index k), with a count."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return
    k = int(idx[0])
    msg = message(k) if callable(message) else message
    if idx.size > 1:
        msg += f" (and {idx.size - 1} more row(s) in this column)"
    problems.add(int(rows[k]), column, msg)


def _parse_float(
    values: pd.Series, rows: np.ndarray, column: str, unit: str, optional: bool, problems: _Problems
) -> np.ndarray:
    vals = values.to_numpy(dtype=object)
    kind = pd.api.types.infer_dtype(values, skipna=False)
    if kind in ("floating", "integer", "mixed-integer-float"):
        # numbers already (a DataFrame): no per-cell work
        num = values.to_numpy(dtype=float, copy=True)
        blank = np.isnan(num)
        bools = np.zeros(len(num), bool)
    elif kind == "string":
        # text cells (a CSV file): the same rules, vectorised.  The numbers are parsed as
        # read (the parser allows surrounding blanks); only the cells that are not a
        # number are looked at again (blank, a missing-value word or a bad value)
        num = pd.to_numeric(values, errors="coerce").to_numpy(dtype=float, copy=True)
        blank = np.zeros(len(num), bool)
        bools = np.zeros(len(num), bool)
        odd = np.flatnonzero(np.isnan(num))
        if odd.size:
            text = values.iloc[odd].str.strip()
            blank[odd] = (text.eq("") | text.str.lower().isin(_NA_STRINGS)).to_numpy(bool)
            num[odd] = pd.to_numeric(text, errors="coerce").to_numpy(dtype=float)
    else:
        blank = np.array(
            [
                _is_blank(v) or (isinstance(v, str) and v.strip().lower() in _NA_STRINGS)
                for v in vals
            ],
            dtype=bool,
        )
        bools = np.array([isinstance(v, (bool, np.bool_)) for v in vals], dtype=bool)
        cleaned = pd.Series([v.strip() if isinstance(v, str) else v for v in vals], dtype=object)
        num = pd.to_numeric(cleaned, errors="coerce").to_numpy(dtype=float, copy=True)
    num[blank] = np.nan
    bad = (~blank & np.isnan(num)) | bools
    num[bad] = np.nan
    _report(problems, rows, bad, column, lambda k: _cells.not_a_number(unit, vals[k]))
    if not optional:
        _report(problems, rows, blank, column, _cells.missing_number(unit))
    inf = np.isinf(num)
    _report(problems, rows, inf, column, lambda k: _cells.not_finite(unit, vals[k]))
    num[inf] = np.nan
    return num


def _id_text(v: Any) -> str | None:
    if _is_blank(v):
        return None
    if isinstance(v, str):
        return v.strip()
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return str(int(v)) if float(v).is_integer() else repr(float(v))
    return str(v).strip()


def _parse_ids(values: pd.Series, rows: np.ndarray, column: str, problems: _Problems) -> np.ndarray:
    if pd.api.types.infer_dtype(values, skipna=False) == "string":
        # text cells (a CSV file): _id_text vectorised (stripped; blank is missing)
        out = _stripped(values).fillna("").to_numpy(dtype=object)
        missing = out == ""
        out[missing] = None
    else:
        out = np.array([_id_text(v) for v in values.to_numpy(dtype=object)], dtype=object)
        missing = np.array([v is None for v in out], dtype=bool)
    _report(problems, rows, missing, column, _cells.MISSING_ID)
    return out


def _parse_bool(
    values: pd.Series, rows: np.ndarray, column: str, problems: _Problems
) -> np.ndarray:
    vals = values.to_numpy(dtype=object)
    out = np.zeros(len(vals), dtype=bool)
    bad = np.zeros(len(vals), dtype=bool)
    for k, v in enumerate(vals):
        if _is_blank(v):
            continue
        if isinstance(v, (bool, np.bool_)):
            out[k] = bool(v)
            continue
        s = (
            str(int(v) if isinstance(v, (int, float, np.number)) and float(v).is_integer() else v)
            .strip()
            .lower()
        )
        if s in _TRUE:
            out[k] = True
        elif s not in _FALSE:
            bad[k] = True
    _report(
        problems,
        rows,
        bad,
        column,
        lambda k: f"expected true or false (or yes/no, 1/0), got {_describe(vals[k])}",
    )
    return out


# --------------------------------------------------------------------------------------
# stations


_STATION_SCHEMA = [
    _Col("station", (), True, "id"),
    _Col("x_mm", ("x",), True, "float", "mm"),
    _Col("y_mm", ("y",), True, "float", "mm"),
    _Col("z_mm", ("z",), True, "float", "mm"),
    _Col("dead_length_mm", ("dead_length",), False, "optfloat", "mm"),
    _Col("dead_length_given", (), False, "bool"),
    _Col("fixed", (), False, "bool"),
]
STATION_COLUMNS = (
    "station",
    "x_mm",
    "y_mm",
    "z_mm",
    "dead_length_mm",
    "dead_length_given",
    "fixed",
)


def load_stations(source: str | Path | pd.DataFrame, *, name: str | None = None) -> pd.DataFrame:
    """Load and validate a stations table (CSV path or DataFrame; never modified).

    Returns a new DataFrame with columns ``station`` (str), ``x_mm, y_mm, z_mm`` (float,
    mm), ``dead_length_mm`` (float, mm, 0.0 where not given), ``dead_length_given`` (bool)
    and ``fixed`` (bool, default False), one row per station in input order.  Raises
    :class:`InputError` naming the source, row and column of every defect (missing or
    unknown columns, non-numeric or missing values, duplicate station ids).
    """
    raw = _read_raw(source, name, "stations table")
    problems = _Problems(raw.name)
    pos = _resolve_columns(raw, _STATION_SCHEMA, problems)
    body, rows = raw.body, raw.rows
    ids = _parse_ids(body[pos["station"]], rows, "station", problems)
    out: dict[str, Any] = {"station": ids}
    for c in ("x_mm", "y_mm", "z_mm"):
        label = raw.header[pos[c]]
        out[c] = _parse_float(body[pos[c]], rows, label, "mm", False, problems)
    if "dead_length_mm" in pos:
        label = raw.header[pos["dead_length_mm"]]
        dl = _parse_float(body[pos["dead_length_mm"]], rows, label, "mm", True, problems)
    else:
        dl = np.full(len(rows), np.nan)
    given = np.isfinite(dl)
    if "dead_length_given" in pos:
        flag = _parse_bool(body[pos["dead_length_given"]], rows, "dead_length_given", problems)
        given = given & flag
    out["dead_length_mm"] = np.where(given, dl, 0.0)
    out["dead_length_given"] = given
    out["fixed"] = (
        _parse_bool(body[pos["fixed"]], rows, "fixed", problems)
        if "fixed" in pos
        else np.zeros(len(rows), dtype=bool)
    )
    first: dict[str, int] = {}
    for k, s in enumerate(ids):
        if s is None:
            continue
        if s in first:
            problems.add(
                int(rows[k]),
                "station",
                f"station '{s}' is described twice (rows {first[s]} and {rows[k]})",
            )
        else:
            first[s] = int(rows[k])
    problems.raise_if_any()
    df = pd.DataFrame(out, columns=list(STATION_COLUMNS))
    df["station"] = df["station"].astype(object)
    return df


def load_instrument_stations(
    source: str | Path | pd.DataFrame,
    param_names: Sequence[str],
    *,
    name: str | None = None,
) -> pd.DataFrame:
    """Load a stations table of any instrument: ``station`` (id), one numeric column per
    station parameter in ``param_names`` (units as the names' suffixes) and optional
    ``fixed`` (bool).  Returns a new DataFrame in that column order; raises
    :class:`InputError` naming the source, row and column of every defect."""
    raw = _read_raw(source, name, "stations table")
    problems = _Problems(raw.name)
    schema = [_Col("station", (), True, "id")]
    schema += [
        _Col(p, (), True, "float", p.rsplit("_", 1)[-1] if "_" in p else "") for p in param_names
    ]
    schema.append(_Col("fixed", (), False, "bool"))
    pos = _resolve_columns(raw, schema, problems)
    body, rows = raw.body, raw.rows
    out: dict[str, Any] = {"station": _parse_ids(body[pos["station"]], rows, "station", problems)}
    for p in param_names:
        if p in pos:
            unit = p.rsplit("_", 1)[-1] if "_" in p else ""
            out[p] = _parse_float(body[pos[p]], rows, raw.header[pos[p]], unit, False, problems)
    out["fixed"] = (
        _parse_bool(body[pos["fixed"]], rows, "fixed", problems)
        if "fixed" in pos
        else np.zeros(len(rows), dtype=bool)
    )
    problems.raise_if_any()
    df = pd.DataFrame(out, columns=["station", *param_names, "fixed"])
    df["station"] = df["station"].astype(object)
    return df


def read_columns(
    source: str | Path | pd.DataFrame,
    columns: Sequence[tuple[str, bool, str]],
    *,
    what: str,
    name: str | None = None,
) -> tuple[dict[str, np.ndarray], np.ndarray, str]:
    """Read an instrument's own table (CSV path or DataFrame; never modified) with the
    rules of the measurement table: ``columns`` lists ``(name, required, kind)`` with kind
    ``"id"`` (text), ``"float"`` (a number in every row) or ``"optfloat"`` (blank allowed,
    NaN); the unit is the name's suffix.  Unknown, doubled or missing columns and bad
    cells raise :class:`InputError` naming the source, row and column.  Returns ({name:
    values} of the columns present, spreadsheet row of every row, source label)."""
    raw = _read_raw(source, name, what)
    problems = _Problems(raw.name)
    schema = [
        _Col(n, (), req, kind, n.rsplit("_", 1)[-1] if "_" in n else "") for n, req, kind in columns
    ]
    pos = _resolve_columns(raw, schema, problems)
    out: dict[str, np.ndarray] = {}
    for c in schema:
        if c.canonical not in pos:
            continue
        col = raw.body[pos[c.canonical]]
        if c.kind == "id":
            out[c.canonical] = _parse_ids(col, raw.rows, c.canonical, problems)
        else:
            out[c.canonical] = _parse_float(
                col, raw.rows, c.canonical, c.unit, c.kind == "optfloat", problems
            )
    problems.raise_if_any()
    return out, raw.rows, raw.name


def mm_or_um_columns(base: str, kind: str = "float") -> list[tuple[str, bool, str]]:
    """The two optional columns of one length quantity for :func:`read_columns`: ``base_mm``
    and ``base_um`` (a table gives one of them; :func:`mm_or_um` reads it)."""
    return [(f"{base}_mm", False, kind), (f"{base}_um", False, kind)]


@overload
def mm_or_um(
    values: dict[str, np.ndarray], base: str, label: str, *, required: Literal[True]
) -> np.ndarray: ...


@overload
def mm_or_um(
    values: dict[str, np.ndarray], base: str, label: str, *, required: bool
) -> np.ndarray | None: ...


def mm_or_um(
    values: dict[str, np.ndarray], base: str, label: str, *, required: bool
) -> np.ndarray | None:
    """The ``base_mm`` or ``base_um`` column of ``values`` (as :func:`read_columns` returns
    them) in mm.  Both present: an :class:`InputError` (the same quantity twice); neither:
    None, or an :class:`InputError` naming the column when ``required``."""
    mm, um = values.get(f"{base}_mm"), values.get(f"{base}_um")
    if mm is not None and um is not None:
        raise InputError(
            f"columns '{base}_mm' and '{base}_um' are the same quantity; keep one",
            source=label,
            row=1,
            column=f"{base}_um",
        )
    if um is not None:
        return um * 1e-3
    if mm is None and required:
        raise InputError(
            f"missing required column '{base}_mm' (or '{base}_um')", source=label, row=1
        )
    return mm


# --------------------------------------------------------------------------------------
# measurements


def _rot(i: int, a: np.ndarray) -> np.ndarray:
    """(N, 3, 3) right-hand rotations about machine axis i (0 x, 1 y, 2 z) by angles a."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((a.shape[0], 3, 3))
    j, k = [(1, 2), (2, 0), (0, 1)][i]
    R[:, i, i] = 1.0
    R[:, j, j] = c
    R[:, k, k] = c
    R[:, j, k] = -s
    R[:, k, j] = s
    return R


def _nominal_tool_points(spec: MachineSpec, q: np.ndarray, tool: np.ndarray) -> np.ndarray:
    """Nominal tool points (N, 3), mm, in the workpiece frame (no errors).

    Same conventions as :mod:`volcal.model.symbolic.chain` (a positive command moves the tool in
    +direction relative to the workpiece; workpiece-branch axes are traversed inversely);
    used here only for the geometry checks behind the warnings.
    """
    n = q.shape[0]
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    t = np.zeros((n, 3))
    for j, axis in enumerate(spec.axes):
        sign = axis.dir_sign if axis.branch == "tool" else -axis.dir_sign
        i = axis.dir_index
        if axis.kind == "linear":
            Rj = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
            tj = np.zeros((n, 3))
            tj[:, i] = sign * q[:, j]
        else:
            Rj = _rot(i, sign * q[:, j])
            c = np.asarray(axis.center, dtype=float)
            tj = c - Rj @ c
        if axis.branch == "workpiece":
            Rj = np.transpose(Rj, (0, 2, 1))
            tj = -np.einsum("nij,nj->ni", Rj, tj)
        t = t + np.einsum("nij,nj->ni", R, tj)
        R = R @ Rj
    return np.einsum("nij,nj->ni", R, tool) + t


def _min_readings(station: str, stations: pd.DataFrame | None) -> int:
    if stations is not None:
        hit = stations.loc[stations["station"] == station]
        if len(hit) and bool(hit["fixed"].iloc[0]):
            return 1  # known position: only the dead length is unknown
    return MIN_READINGS_PER_STATION


def load_measurements(
    source: str | Path | pd.DataFrame | ScannedTable,
    spec: MachineSpec,
    *,
    name: str | None = None,
    stations: pd.DataFrame | None = None,
    require_station_positions: bool = False,
    relative_lengths: bool = False,
    columns: Mapping[str, str] | str | None = None,
) -> Measurements:
    """Load and validate a measurement table (CSV path or DataFrame; never modified).

    source: CSV path or DataFrame (columns: see the module docstring), or a file already
        read by :func:`volcal.measurement.cells.scan_measurements` (the command line reads
        it before pandas' import, to report a bad cell at once).
    spec: the machine model (or a bundled model name / model file path); its axes name the
        axis columns and their travel bounds the positions.
    name: name of the source in messages (default: the path, or ``"<DataFrame>"``).
    stations: a stations table (raw or :func:`load_stations` output, validated here).
    require_station_positions: every station used must then be described in ``stations``.
    relative_lengths: lengths are relative to an unknown dead length (interferometer in
        relative mode) and may be zero or negative; only ``|length| <= MAX_LENGTH_MM`` is
        checked.  By default lengths must lie in ``(0, MAX_LENGTH_MM]``.
    columns: a column mapping for instrument exports (:func:`parse_column_map`):
        ``{"length": "L[m]", "station": "Tracker"}`` or the text
        ``"length=L[m],station=Tracker"``: which column of the file holds each of volcal's
        columns, with the unit of the file's values in brackets (converted to volcal's).

    Errors (:class:`InputError`, naming source, row and column): missing, misnamed
    (closest expected name suggested), unknown or doubled columns; axis columns that do not
    match the model; non-numeric, missing or infinite values; lengths <= 0 or > 100 m;
    axis positions outside the travel by more than ``TRAVEL_TOLERANCE`` x travel range;
    sigma <= 0; duplicate readings (same station, point, axis positions and tool offset:
    both rows named; repeated readings of one pose need distinct point ids); a station
    with fewer than 4 readings (1 when the stations table marks it ``fixed``); stations
    not in the stations table when positions are required.  Time order is not checked.

    Warnings (:class:`DataWarning`): a station whose points are coplanar (nominal
    geometry, relative tolerance ``COPLANAR_RTOL``); a station with fewer than
    ``FEW_READINGS_PER_STATION`` readings; a tool offset identical in every row (the
    angular error motions of the last axis of the chain then cannot be separated from its
    translational ones); one point id used for different axis positions or tool offsets.
    """
    spec = resolve_model(spec)
    if isinstance(source, (str, Path)) and not columns:
        # a small file is read and its cells checked without pandas (the same errors),
        # and its numbers parsed once (volcal.measurement.cells); None: pandas reads it
        source = (
            scan_measurements(source, spec, name=name, relative_lengths=relative_lengths) or source
        )
    raw = None
    if isinstance(source, (str, Path)) and not columns and TYPED_READING:
        raw = _read_typed(Path(source), spec, name)  # None: read as text below
    if raw is None:
        raw = _read_raw(source, name, "measurement table")
    if columns:
        raw = _map_columns(raw, parse_column_map(columns), spec)
    problems = _Problems(raw.name)
    schema = _measurement_schema(spec)
    axis_names = spec.axis_names
    pos = _resolve_columns(raw, schema, problems, axis_names=axis_names, model_name=spec.name)
    body, rows = raw.body, raw.rows
    n = len(rows)
    label = {c: raw.header[p] for c, p in pos.items()}

    station = _parse_ids(body[pos["station"]], rows, label["station"], problems)
    point = _parse_ids(body[pos["point"]], rows, label["point"], problems)
    q_file = np.empty((n, len(axis_names)))
    for j, a in enumerate(spec.axes):
        unit = "deg" if a.is_rotary else "mm"
        q_file[:, j] = _parse_float(body[pos[a.name]], rows, label[a.name], unit, False, problems)
    tool = np.zeros((n, 3))
    for j, c in enumerate(("tool_x", "tool_y", "tool_z")):
        if c in pos:
            tool[:, j] = _parse_float(body[pos[c]], rows, label[c], "mm", False, problems)
    length = _parse_float(body[pos["length"]], rows, label["length"], "mm", False, problems)
    time = (
        _parse_float(body[pos["time"]], rows, label["time"], "s", True, problems)
        if "time" in pos
        else np.full(n, np.nan)
    )
    sigma = (
        _parse_float(body[pos["sigma"]], rows, label["sigma"], "mm", True, problems)
        if "sigma" in pos
        else np.full(n, np.nan)
    )

    # ranges
    L = label["length"]
    if relative_lengths:
        _report(
            problems,
            rows,
            np.abs(length) > MAX_LENGTH_MM,
            L,
            lambda k: _cells.length_too_long_relative(float(length[k])),
        )
    else:
        _report(
            problems,
            rows,
            length <= 0,
            L,
            lambda k: _cells.length_not_positive(float(length[k])),
        )
        _report(
            problems,
            rows,
            length > MAX_LENGTH_MM,
            L,
            lambda k: _cells.length_too_long(float(length[k])),
        )
    for j, a in enumerate(spec.axes):
        lo, hi = a.travel
        tol = TRAVEL_TOLERANCE * (hi - lo)
        qa = q_file[:, j]
        _report(
            problems,
            rows,
            (qa < lo - tol) | (qa > hi + tol),
            label[a.name],
            lambda k, qa=qa, a=a: _cells.outside_travel(a, float(qa[k])),
        )
    _warn_radians(raw.name, spec, q_file, label)
    if "sigma" in pos:
        _report(
            problems,
            rows,
            sigma <= 0,
            label["sigma"],
            lambda k: _cells.sigma_not_positive(float(sigma[k])),
        )
    problems.raise_if_any()

    stations_df = None
    if stations is not None:
        stations_df = load_stations(
            stations, name=None if isinstance(stations, (str, Path)) else "<stations DataFrame>"
        )

    # duplicates
    table = pd.DataFrame({"station": station, "point": point})
    for j, axis_name in enumerate(axis_names):
        table[axis_name] = q_file[:, j]
    for j, c in enumerate(("tool_x", "tool_y", "tool_z")):
        table[c] = tool[:, j]
    table["length"] = length
    table["time"] = time
    table["sigma"] = sigma
    key = ["station", "point", *axis_names, "tool_x", "tool_y", "tool_z"]
    dup = table.duplicated(subset=key, keep=False).to_numpy()
    if dup.any():
        groups = table.loc[dup].groupby(key, sort=False).groups
        listed = sorted(
            (sorted(int(rows[i]) for i in idx) for idx in groups.values()), key=lambda r: r[1]
        )
        for r in listed:
            k = int(np.flatnonzero(rows == r[0])[0])
            listed_rows = ", ".join(str(x) for x in r[:-1]) + f" and {r[-1]}"
            problems.add(
                r[1],
                label["point"],
                f"duplicate reading: rows {listed_rows} have the same station "
                f"'{station[k]}', point '{point[k]}', axis positions and tool offset "
                "(give repeated readings of one pose distinct point ids)",
            )

    # stations
    # ids in order of first appearance and each reading's index into them, as
    # dict.fromkeys and a lookup per reading give them (pandas' hash table, no Python
    # per reading)
    codes, uniques = pd.factorize(station)
    station_ids = list(uniques.tolist())
    station_index = codes.astype(int, copy=False)
    counts = np.bincount(station_index, minlength=len(station_ids))
    first_row = {
        s: int(rows[np.flatnonzero(station_index == i)[0]]) for i, s in enumerate(station_ids)
    }
    for i, s in enumerate(station_ids):
        need = _min_readings(s, stations_df)
        if counts[i] < need:
            where = ", ".join(str(int(r)) for r in rows[station_index == i])
            problems.add(
                first_row[s],
                label["station"],
                f"station '{s}' has {counts[i]} reading(s) (row(s) {where}); at least "
                f"{need} are needed to locate it (3 position coordinates and a dead "
                "length)"
                if need == MIN_READINGS_PER_STATION
                else f"station '{s}' has {counts[i]} reading(s); at least {need} needed",
            )
    if stations_df is not None:
        _check_station_ids(
            raw.name, station_ids, first_row, stations_df, label["station"], problems
        )
    if require_station_positions:
        if stations_df is None:
            problems.add(
                None,
                label["station"],
                "station positions are required "
                "(require_station_positions=True) but no stations table was given",
            )
        else:
            described = set(stations_df["station"])
            absent = [s for s in station_ids if s not in described]
            for s in absent:
                problems.add(
                    first_row[s],
                    label["station"],
                    f"station '{s}' (first used in row {first_row[s]}) is not described "
                    f"in the stations table, and station positions are required; the "
                    f"stations table describes: "
                    f"{', '.join(map(str, stations_df['station']))}",
                )
    problems.raise_if_any()

    codes, uniques = pd.factorize(point)
    point_ids = list(uniques.tolist())
    point_index = codes.astype(int, copy=False)
    q_internal = q_file.copy()
    for j, a in enumerate(spec.axes):
        if a.is_rotary:
            q_internal[:, j] = np.deg2rad(q_internal[:, j])

    _warn_geometry(
        raw.name,
        spec,
        station_ids,
        station_index,
        first_row,
        counts,
        point,
        point_index,
        q_internal,
        tool,
        rows,
        stations_df,
    )

    given = tuple(c.canonical for c in schema if c.canonical in pos)
    for arr in (station_index, point_index, q_internal, tool, length, sigma, time, rows):
        arr.setflags(write=False)
    return Measurements(
        table=table,
        source=raw.name,
        axis_names=tuple(axis_names),
        station_ids=station_ids,
        station_index=station_index,
        point_ids=point_ids,
        point_index=point_index,
        q_internal=q_internal,
        tool=tool,
        length=length,
        sigma=sigma,
        time=time,
        rows=rows.copy(),
        given_columns=given,
        stations=stations_df,
    )


def _warn_radians(name: str, spec: MachineSpec, q_file: np.ndarray, label: dict[str, str]) -> None:
    """Rotary axis positions are in degrees: a column whose values all lie within +-2 pi,
    spread over more than one unit and are not whole numbers, on an axis whose travel spans
    180 deg or more, is most likely in radians."""
    for j, a in enumerate(spec.axes):
        if not a.is_rotary:
            continue
        v = q_file[:, j]
        v = v[np.isfinite(v)]
        lo, hi = a.travel
        if (
            len(v)
            and hi - lo >= 180.0
            and np.all(np.abs(v) <= 2 * np.pi + 1e-9)
            and np.ptp(v) > 1.0
            and not np.all(v == np.round(v))
        ):
            warnings.warn(
                _cells.looks_like_radians(name, label[a.name], a, v.min(), v.max()),
                DataWarning,
                stacklevel=3,
            )


def _id_list(ids: Iterable[str], n: int = 8) -> str:
    ids = [f"'{i}'" for i in ids]
    return ", ".join(ids[:n]) + (f", ... ({len(ids)} in all)" if len(ids) > n else "")


def _check_station_ids(
    name: str,
    station_ids: list[str],
    first_row: dict[str, int],
    stations_df: pd.DataFrame,
    column: str,
    problems: _Problems,
) -> None:
    """The stations table must describe the stations of the data: no common id at all is
    an error (the table is for other data, or its ids are spelt differently); stations in
    the table without readings, above all ones marked ``fixed``, and stations of the data
    the table does not describe (they are then located from the data) are warnings."""
    described = [str(s) for s in stations_df["station"]]
    used = set(station_ids)
    common = used.intersection(described)
    if not common:
        problems.add(
            first_row[station_ids[0]],
            column,
            f"no station of the data is described in the stations table: the data "
            f"use {_id_list(station_ids)}, the stations table describes "
            f"{_id_list(described)}; station ids must match exactly (as text)",
        )
        return
    unknown = [s for s in described if s not in used]
    if unknown:
        fixed = set(stations_df.loc[stations_df["fixed"].astype(bool), "station"].astype(str))
        held = [s for s in unknown if s in fixed]
        warnings.warn(
            f"{name}: the stations table describes station(s) with no reading in "
            f"the data: {_id_list(unknown)}"
            + (f" (marked fixed: {_id_list(held)})" if held else "")
            + "; they are ignored",
            DataWarning,
            stacklevel=4,
        )
    missing = [s for s in station_ids if s not in common]
    if missing:
        warnings.warn(
            f"{name}: station(s) {_id_list(missing)} (first in row "
            f"{first_row[missing[0]]}) are not described in the stations table; "
            "their positions and dead lengths are estimated from the data",
            DataWarning,
            stacklevel=4,
        )


def _warn_geometry(
    name: str,
    spec: MachineSpec,
    station_ids: list[str],
    station_index: np.ndarray,
    first_row: dict[str, int],
    counts: np.ndarray,
    point: np.ndarray,
    point_index: np.ndarray,
    q: np.ndarray,
    tool: np.ndarray,
    rows: np.ndarray,
    stations_df: pd.DataFrame | None,
) -> None:
    pts = _nominal_tool_points(spec, q, tool)
    for i, s in enumerate(station_ids):
        if counts[i] < FEW_READINGS_PER_STATION:
            warnings.warn(
                f"{name}: station '{s}' has only {counts[i]} readings (fewer than "
                f"{FEW_READINGS_PER_STATION}); its position and dead length rest on "
                "little redundancy",
                DataWarning,
                stacklevel=3,
            )
        p = pts[station_index == i]
        c = p - p.mean(axis=0)
        sv = np.linalg.svd(c, compute_uv=False) if len(p) else np.zeros(1)
        sv = np.concatenate([sv, np.zeros(3 - len(sv))]) if len(sv) < 3 else sv
        if sv[0] == 0 or sv[2] <= COPLANAR_RTOL * sv[0]:
            rank = int(np.sum(sv > COPLANAR_RTOL * sv[0])) if sv[0] > 0 else 0
            shape = {0: "a single position", 1: "one line", 2: "one plane"}[min(rank, 2)]
            warnings.warn(
                f"{name}: the nominal tool points measured from station '{s}' "
                f"(first row {first_row[s]}) lie in {shape} (rank {rank} < 3); the "
                "station position is then determined only up to its mirror image in "
                "that plane and poorly perpendicular to it",
                DataWarning,
                stacklevel=3,
            )
    if len(tool) and np.all(tool == tool[0]):
        last = spec.axes[-1].name
        warnings.warn(
            f"{name}: the tool offset is the same in every row "
            f"({', '.join(f'{v:g}' for v in tool[0])}) mm; with a single tool offset "
            f"the angular error motions of the last axis of the chain ({last}: "
            f"EA{last}, EB{last}, EC{last}, and what they mix with) cannot be separated "
            "from translational error motions with these data; the identification names "
            "every parameter it leaves out",
            DataWarning,
            stacklevel=3,
        )
    # one point id should be one commanded pose
    pose = np.concatenate([q, tool], axis=1)
    first = np.full(point_index.max() + 1, -1)
    seen, first_k = np.unique(point_index, return_index=True)  # each id's first reading
    first[seen] = first_k
    ref = pose[first[point_index]]
    differ = np.flatnonzero(np.any(pose != ref, axis=1))
    if differ.size:
        k = int(differ[0])
        warnings.warn(
            f"{name}: point '{point[k]}' has different axis positions or tool "
            f"offsets in rows {rows[first[point_index[k]]]} and {rows[k]} "
            f"({differ.size} row(s) differ from the first use of their point id); a "
            "point id names one commanded pose",
            DataWarning,
            stacklevel=3,
        )


# --------------------------------------------------------------------------------------
# the public toolkit for reading and validating tables
#
# Every reader of a user table (measurements, stations, plans, parameter and point tables,
# budgets' CSV parts) goes through these, so that a bad cell is reported the same way
# everywhere: the file, the row (spreadsheet numbering: header = row 1) and the column,
# what was found and what was expected, all problems of a column at once (InputError).
#
#   raw = read_raw(path_or_df, name, "plan")          # text cells, row numbers, source name
#   problems = Problems(raw.name)
#   pos = resolve_columns(raw, [Column("X", ("X_mm",), True, "float", "mm")], problems)
#   x = parse_float(raw.body[pos["X"]], raw.rows, "X", "mm", False, problems)
#   problems.raise_if_any()

Column = _Col
Problems = _Problems
read_raw = _read_raw
resolve_columns = _resolve_columns
parse_float = _parse_float
parse_ids = _parse_ids
report_rows = _report
nominal_tool_points = _nominal_tool_points

__all__ += [
    "mm_or_um",
    "mm_or_um_columns",
    "Column",
    "Problems",
    "read_raw",
    "resolve_columns",
    "parse_float",
    "parse_ids",
    "report_rows",
    "nominal_tool_points",
]
