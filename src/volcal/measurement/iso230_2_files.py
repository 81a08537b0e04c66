"""Loading and validation of ISO 230-2 positioning readings: the one reader of the file
format, used by ``volcal iso230-2`` (:mod:`volcal.iso230_2`) and by the laser
interferometer (:mod:`volcal.measurement.instruments.interferometer`), so that a file is
accepted or refused by both alike, with the same numbers and the same messages.

One row per reading.  Columns (names are matched case-insensitively, surrounding blanks
ignored; other columns are allowed and ignored):

======================  ========  ===========================================================
column                  unit      meaning
======================  ========  ===========================================================
``axis``                -         axis name (``X``, ``C``, ...); several axes per file allowed
``target_mm``           mm        target position P_i of a linear axis, or
``target_deg``          deg       target position of a rotary axis
``cycle``               -         measurement cycle j = 1..n (integer)
``direction``           -         approach direction: ``+``/``up`` or ``-``/``down``
``deviation_um``        um        positional deviation x_ij = P_ij - P_i (linear axis), or
``actual_mm``           mm        actual position P_ij (linear axis), or
``deviation_arcsec``    arcsec    positional deviation (rotary axis), or
``actual_deg``          deg       actual position (rotary axis)
======================  ========  ===========================================================

Exactly one target column and one value column; a linear target with a rotary value (or
the reverse), two target columns, or a deviation column next to an actual column is a
"mixed units" error.  Every (cycle, direction) run of an axis must hold each target exactly
once, listed in monotonic (ascending or descending) row order; both directions must have
the same cycles 1..n without gaps.  Row numbers in messages are 1-based as a spreadsheet
shows them (header = row 1, first data row = row 2); for a DataFrame they are the
position + 2, i.e. the row it would have once saved with ``to_csv(index=False)``.

Internally positions and deviations are in mm (linear) or rad (rotary).
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

__all__ = [
    "AxisUnits",
    "LINEAR",
    "ROTARY",
    "AxisReadings",
    "Iso230File",
    "is_iso230_2_table",
    "load_readings",
    "read_iso230_2_file",
]


@dataclass(frozen=True)
class AxisUnits:
    """Units of an axis: the internal unit and the unit used in files and reports."""

    kind: str  # "linear" or "rotary"
    internal: str  # "mm" or "rad" (positions and deviations inside the code)
    position: str  # report unit of positions: "mm" or "deg"
    deviation: str  # report unit of deviations: "um" or "arcsec"
    position_scale: float  # report position = internal * position_scale
    deviation_scale: float  # report deviation = internal * deviation_scale


LINEAR = AxisUnits("linear", "mm", "mm", "um", 1.0, 1000.0)
ROTARY = AxisUnits("rotary", "rad", "deg", "arcsec", 180.0 / math.pi, 180.0 / math.pi * 3600.0)


@dataclass(frozen=True)
class AxisReadings:
    """Validated readings of one axis.

    ``up[i, j]`` / ``down[i, j]`` is the positional deviation x_ij (internal unit: mm or
    rad) at target ``targets[i]`` (ascending, internal unit) in cycle j + 1, approached in
    the positive / negative direction.
    """

    axis: str
    units: AxisUnits
    targets: np.ndarray
    up: np.ndarray
    down: np.ndarray
    source: str

    @property
    def m(self) -> int:
        return int(self.targets.size)

    @property
    def n(self) -> int:
        return int(self.up.shape[1])


@dataclass(frozen=True)
class Iso230File:
    """A validated ISO 230-2 table: its readings per axis (:attr:`axes`, what the ISO
    evaluation uses) and per row in table order (what an instrument reading the rows uses),
    with the table's cells for further columns (:meth:`number_column`).

    Per row: ``row`` the spreadsheet row (header = row 1), ``axis`` the axis name as written
    (blanks stripped), ``cycle`` (1..n), ``direction`` (``"up"`` or ``"down"``), ``target``
    and ``deviation`` in the internal unit (mm or rad; the deviation x_ij = actual - target,
    whichever of the two value columns the file gives).
    """

    source: str
    units: AxisUnits
    axes: list[AxisReadings]
    row: np.ndarray
    axis: np.ndarray
    cycle: np.ndarray
    direction: np.ndarray
    target: np.ndarray
    deviation: np.ndarray
    cells: pd.DataFrame  # the table's cells, columns named in lower case, blanks stripped
    columns: dict[str, str]  # lower-case name -> name as written

    def number_column(self, name: str, what: str, *, optional: bool = False) -> np.ndarray | None:
        """A further numeric column (``name`` matched case-insensitively), read with the
        rules of the ISO columns: every cell a finite number (``optional``: a blank cell is
        NaN).  None when the table has no such column; an :class:`InputError` naming the
        source, row and column otherwise."""
        key = name.strip().lower()
        if key not in self.columns:
            return None
        out = np.empty(len(self.row))
        for k, raw in enumerate(self.cells[key].tolist()):
            text = "" if raw is None else str(raw).strip()
            if optional and (text == "" or text.lower() == "nan"):
                out[k] = np.nan
                continue
            out[k] = _number(raw, self.source, int(self.row[k]), self.columns[key], what)
        return out


def is_iso230_2_table(source) -> bool:
    """Is the table (CSV path or DataFrame) meant as an ISO 230-2 file: no ``setup`` column
    and one of the columns only this format has (``cycle``, ``direction``, ``target_mm``,
    ``target_deg``)?  Loose on purpose: a file with a misnamed ISO column is then refused
    by this format's reader, which names the column.  False for a file that cannot be read
    (its reader says why)."""
    if isinstance(source, pd.DataFrame):
        names = [str(c).strip().lower() for c in source.columns]
    else:
        try:
            with open(source, newline="", encoding="utf-8-sig") as fh:
                names = [c.strip().lower() for c in next(csv.reader(fh), [])]
        except (OSError, UnicodeDecodeError, csv.Error):
            return False
    iso_only = ("cycle", "direction", *_TARGET_COLS)
    return "setup" not in names and any(c in names for c in iso_only)


_TARGET_COLS = {"target_mm": LINEAR, "target_deg": ROTARY}
_VALUE_COLS = {  # name -> (units, form)
    "deviation_um": (LINEAR, "deviation"),
    "actual_mm": (LINEAR, "actual"),
    "deviation_arcsec": (ROTARY, "deviation"),
    "actual_deg": (ROTARY, "actual"),
}
_DIRECTIONS = {
    "+": "up",
    "up": "up",
    "pos": "up",
    "positive": "up",
    "-": "down",
    "down": "down",
    "neg": "down",
    "negative": "down",
    "\u2191": "up",
    "\u2193": "down",
}
# target values closer than this (in file units: mm or deg) are the same target
_TARGET_DECIMALS = 6


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def _number(raw, src: str, row: int, column: str, what: str) -> float:
    """One cell as a finite number, or an :class:`InputError` naming its row and column."""
    text = "" if raw is None else str(raw).strip()
    if text == "" or text.lower() == "nan":
        raise InputError(f"empty cell; expected {what}", source=src, row=row, column=column)
    try:
        x = float(text)
    except ValueError:
        raise InputError(
            f"'{text}' is not a number; expected {what}", source=src, row=row, column=column
        ) from None
    if not math.isfinite(x):
        raise InputError(
            f"'{text}' is not finite; expected {what}", source=src, row=row, column=column
        )
    return x


def _read_csv(path: Path) -> tuple[pd.DataFrame, np.ndarray]:
    """Read a CSV as text cells; returns the table and the spreadsheet row of each record
    (header = row 1; blank lines are skipped but counted, as a spreadsheet shows them)."""
    src = str(path)
    if not path.exists():
        raise FileNotFoundError(f"{src}: no such file")
    if path.is_dir():
        raise InputError("is a folder; expected a CSV file of readings", source=src)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            records = list(csv.reader(fh))
    except UnicodeDecodeError as exc:
        raise InputError(f"not a UTF-8 text file ({exc.reason})", source=src) from None
    except csv.Error as exc:
        raise InputError(f"malformed CSV: {exc}", source=src) from None
    if not records or not any(h.strip() for h in records[0]):
        raise InputError(
            "the file is empty or its first line is blank; expected a header row", source=src, row=1
        )
    header = [h.strip() for h in records[0]]
    names = [h.lower() for h in header]
    for k, name in enumerate(names):
        if name and names.index(name) != k:
            raise InputError(
                f"column '{header[k]}' appears twice in the header",
                source=src,
                row=1,
                column=header[k],
            )
    rows, numbers = [], []
    for r, rec in enumerate(records[1:], start=2):
        if not any(c.strip() for c in rec):
            continue
        if len(rec) != len(header):
            raise InputError(
                f"{len(rec)} fields, but the header has {len(header)}", source=src, row=r
            )
        rows.append(rec)
        numbers.append(r)
    return pd.DataFrame(rows, columns=header, dtype=object), np.array(numbers, dtype=int)


def load_readings(data, *, source: str | None = None) -> list[AxisReadings]:
    """Validate a readings table (CSV path or DataFrame) and return one object per axis.

    Raises :class:`volcal.base.exceptions.InputError` naming the source, row and column of the
    first problem.  The input (file or DataFrame) is never modified.
    """
    return read_iso230_2_file(data, source=source).axes


def read_iso230_2_file(data, *, source: str | None = None) -> Iso230File:
    """Validate a readings table (CSV path or DataFrame): its readings per axis and per row
    (:class:`Iso230File`).  Raises :class:`volcal.base.exceptions.InputError` naming the
    source, row and column of the first problem; the input is never modified."""
    if isinstance(data, pd.DataFrame):
        src = source or "<DataFrame>"
        df = data.copy()
        df.columns = [str(c) for c in df.columns]
        df = df.reset_index(drop=True)
        rownum = np.arange(len(df)) + 2
    elif isinstance(data, (str, os.PathLike)):
        path = Path(data)
        src = source or str(path)
        df, rownum = _read_csv(path)
    else:
        raise TypeError(f"expected a CSV path or a pandas DataFrame, got {type(data).__name__}")

    original = {c.strip().lower(): c for c in df.columns}
    if len(original) != len(df.columns):
        raise InputError(
            "two columns have the same name (ignoring case and blanks)", source=src, row=1
        )
    df = df.rename(columns={c: c.strip().lower() for c in df.columns})
    cols = set(df.columns)

    # --- which columns, in which units --------------------------------------------------
    targets = [c for c in _TARGET_COLS if c in cols]
    values = [c for c in _VALUE_COLS if c in cols]
    if len(targets) > 1:
        raise InputError(
            "mixed units: both 'target_mm' and 'target_deg' are present; use "
            "one target column per file (target_mm for linear axes, target_deg "
            "for rotary axes)",
            source=src,
            row=1,
            column=original[targets[1]],
        )
    if len(values) > 1:
        raise InputError(
            f"mixed units: columns {', '.join(repr(original[v]) for v in values)} "
            "are all present; give exactly one of deviation_um or actual_mm "
            "(linear axis) or deviation_arcsec or actual_deg (rotary axis)",
            source=src,
            row=1,
            column=original[values[1]],
        )
    for need, hint in (
        ("axis", "the axis name, e.g. X"),
        ("cycle", "the cycle number 1..n"),
        ("direction", "the approach direction + or -"),
    ):
        if need not in cols:
            raise InputError(
                f"missing column '{need}' ({hint}); columns found: "
                f"{', '.join(map(repr, df.columns))}",
                source=src,
                row=1,
                column=need,
            )
    if not targets:
        unitless = [original[c] for c in cols if c in ("target", "position", "target_position")]
        extra = f" (column '{unitless[0]}' has no unit in its name)" if unitless else ""
        raise InputError(
            "missing target column: expected 'target_mm' (linear axis) or "
            f"'target_deg' (rotary axis){extra}",
            source=src,
            row=1,
            column="target_mm",
        )
    if not values:
        unitless = [original[c] for c in cols if c in ("deviation", "actual", "error")]
        extra = f" (column '{unitless[0]}' has no unit in its name)" if unitless else ""
        raise InputError(
            "missing value column: expected 'deviation_um' or 'actual_mm' "
            "(linear axis), or 'deviation_arcsec' or 'actual_deg' (rotary axis)"
            f"{extra}",
            source=src,
            row=1,
            column="deviation_um",
        )
    tcol, vcol = targets[0], values[0]
    units = _TARGET_COLS[tcol]
    vunits, form = _VALUE_COLS[vcol]
    if vunits is not units:
        raise InputError(
            f"mixed units: target column '{original[tcol]}' is for a "
            f"{units.kind} axis but value column '{original[vcol]}' is for a "
            f"{vunits.kind} axis",
            source=src,
            row=1,
            column=original[vcol],
        )
    if len(df) == 0:
        raise InputError("no readings: the table has a header but no data rows", source=src, row=2)

    # --- cell by cell ---------------------------------------------------------------------
    n_rows = len(df)
    axis = np.empty(n_rows, dtype=object)
    cycle = np.empty(n_rows, dtype=np.int64)
    direction = np.empty(n_rows, dtype=object)
    target = np.empty(n_rows)
    value = np.empty(n_rows)

    def number(raw, r, col, what):
        return _number(raw, src, r, original[col], what)

    tu = "mm" if units is LINEAR else "deg"
    vu = {
        "deviation_um": "um",
        "actual_mm": "mm",
        "deviation_arcsec": "arcsec",
        "actual_deg": "deg",
    }[vcol]
    for k, rec in enumerate(
        df[["axis", "cycle", "direction", tcol, vcol]].itertuples(index=False, name=None)
    ):
        r = int(rownum[k])
        a = "" if rec[0] is None else str(rec[0]).strip()
        if a == "" or a.lower() == "nan":
            raise InputError(
                "empty cell; expected the axis name, e.g. X",
                source=src,
                row=r,
                column=original["axis"],
            )
        axis[k] = a
        c = number(rec[1], r, "cycle", "the cycle number, an integer 1..n")
        if c != int(c) or c < 1:
            raise InputError(
                f"'{str(rec[1]).strip()}' is not a cycle number; expected an integer 1..n",
                source=src,
                row=r,
                column=original["cycle"],
            )
        cycle[k] = int(c)
        d = "" if rec[2] is None else str(rec[2]).strip().lower()
        if d not in _DIRECTIONS:
            raise InputError(
                f"'{str(rec[2]).strip()}' is not a direction; expected '+' or "
                "'up' (positive approach), '-' or 'down' (negative approach)",
                source=src,
                row=r,
                column=original["direction"],
            )
        direction[k] = _DIRECTIONS[d]
        target[k] = number(rec[3], r, tcol, f"the target position in {tu}")
        value[k] = number(rec[4], r, vcol, f"the {form} in {vu}")

    # --- per axis ---------------------------------------------------------------------------
    out = []
    deviation = np.empty(n_rows)  # per row, internal unit (filled axis by axis)
    axes_in_order = list(dict.fromkeys(axis.tolist()))
    per_row = (cycle, direction, target, value, units, form, src, original, tcol, vcol, rownum)
    for name in axes_in_order:
        rows = np.flatnonzero(axis == name)
        readings, deviation[rows] = _one_axis(name, rows, *per_row)
        out.append(readings)
    return Iso230File(
        source=src,
        units=units,
        axes=out,
        row=np.asarray(rownum, dtype=int),
        axis=axis,
        cycle=cycle,
        direction=direction,
        target=target if units is LINEAR else np.deg2rad(target),
        deviation=deviation,
        cells=df,
        columns=original,
    )


def _one_axis(
    name, rows, cycle, direction, target, value, units, form, src, original, tcol, vcol, rownum
) -> tuple[AxisReadings, np.ndarray]:
    """Validate the readings of one axis: its arrays, and the deviation (internal unit) of
    each of its rows in the order of ``rows``."""
    tu = "mm" if units is LINEAR else "deg"
    tkey = np.round(target[rows], _TARGET_DECIMALS)
    dirs = set(direction[rows])
    if dirs != {"up", "down"}:
        only = "+" if "up" in dirs else "-"
        raise InputError(
            f"axis {name}: readings only in direction '{only}'; ISO 230-2 "
            "bidirectional evaluation needs both '+' and '-' approaches",
            source=src,
            column=original["direction"],
        )
    # cycles: 1..n without gaps, same n in both directions
    n_by_dir = {}
    for d, sym in (("up", "+"), ("down", "-")):
        cyc = sorted(set(cycle[rows][direction[rows] == d].tolist()))
        missing = sorted(set(range(1, max(cyc) + 1)) - set(cyc))
        if missing:
            raise InputError(
                f"axis {name}, direction '{sym}': missing cycle(s) "
                f"{', '.join(map(str, missing))} (cycles found: "
                f"{', '.join(map(str, cyc))}); cycles must be numbered 1..n "
                "without gaps",
                source=src,
                column=original["cycle"],
            )
        n_by_dir[d] = len(cyc)
    if n_by_dir["up"] != n_by_dir["down"]:
        raise InputError(
            f"axis {name}: unequal cycle counts: direction '+' has "
            f"{n_by_dir['up']} cycles, direction '-' has {n_by_dir['down']}; "
            "ISO 230-2 needs the same number of cycles n in both directions",
            source=src,
            column=original["cycle"],
        )
    n = n_by_dir["up"]

    # runs: (cycle, direction) -> row indices in file order
    runs: dict[tuple[int, str], list[int]] = {}
    for k in rows:
        runs.setdefault((int(cycle[k]), direction[k]), []).append(int(k))
    n_runs = len(runs)
    # duplicates and order inside each run
    for (c, d), ks in runs.items():
        sym = "+" if d == "up" else "-"
        keys = np.round(target[ks], _TARGET_DECIMALS)
        seen: dict[float, int] = {}
        for k, t in zip(ks, keys):
            if t in seen:
                raise InputError(
                    f"axis {name}, cycle {c}, direction '{sym}': second reading "
                    f"at target {_fmt(t)} {tu} (first at row {rownum[seen[t]]}); "
                    "each run must hold each target once",
                    source=src,
                    row=int(rownum[k]),
                    column=original[tcol],
                )
            seen[t] = k
        if len(keys) >= 3:
            step = np.sign(np.diff(keys))
            ref = step[0]
            bad = np.flatnonzero(step != ref)
            if bad.size:
                k = ks[bad[0] + 1]
                raise InputError(
                    f"targets out of order: axis {name}, cycle {c}, direction '{sym}': target "
                    f"{_fmt(keys[bad[0] + 1])} {tu} follows {_fmt(keys[bad[0]])} {tu} after "
                    f"{'ascending' if ref > 0 else 'descending'} targets; list the rows of a "
                    "run in ascending or descending target order",
                    source=src,
                    row=int(rownum[k]),
                    column=original[tcol],
                )
    # every run covers the same targets
    all_targets = np.unique(tkey)
    runs_with = {t: 0 for t in all_targets}
    for ks in runs.values():
        for t in set(np.round(target[ks], _TARGET_DECIMALS).tolist()):
            runs_with[t] += 1
    common = [t for t in all_targets if runs_with[t] == n_runs]
    for t in all_targets:
        if runs_with[t] * 2 <= n_runs:
            # rare target: most likely a typo in the rows that hold it
            k = int(rows[np.flatnonzero(tkey == t)[0]])
            raise InputError(
                f"axis {name}: target {_fmt(t)} {tu} appears in only "
                f"{runs_with[t]} of {n_runs} runs (cycle x direction); every run "
                "must cover the same targets "
                f"({', '.join(_fmt(v) for v in common)} {tu})",
                source=src,
                row=int(rownum[k]),
                column=original[tcol],
            )
    for t in all_targets:
        if runs_with[t] == n_runs:
            continue
        lacking = [
            f"cycle {c} '{'+' if d == 'up' else '-'}'"
            for (c, d), ks in sorted(runs.items())
            if t not in set(np.round(target[ks], _TARGET_DECIMALS).tolist())
        ]
        raise InputError(
            f"axis {name}: no reading at target {_fmt(t)} {tu} in "
            f"{', '.join(lacking)}; every run must cover the same targets",
            source=src,
            column=original[tcol],
        )
    m = all_targets.size
    if m < 2:
        raise InputError(
            f"axis {name}: only {m} target position; at least 2 are needed "
            "(ISO 230-2 asks for at least 5)",
            source=src,
            column=original[tcol],
        )
    if n < 2:
        raise InputError(
            f"axis {name}: only {n} cycle; at least 2 are needed to estimate "
            "the standard uncertainty s_i (ISO 230-2 asks for 5)",
            source=src,
            column=original["cycle"],
        )

    up = np.empty((m, n))
    down = np.empty((m, n))
    row_dev: dict[int, float] = {}
    index = {t: i for i, t in enumerate(all_targets)}
    for k in rows:
        i = index[np.round(target[k], _TARGET_DECIMALS)]
        j = int(cycle[k]) - 1
        if form == "deviation":
            dev = value[k]
        else:
            dev = value[k] - target[k]
            if units is ROTARY:  # wrap to (-180, 180] deg
                dev = -((-dev + 180.0) % 360.0 - 180.0)
        (up if direction[k] == "up" else down)[i, j] = dev
        row_dev[k] = dev

    # target positions: mean of the (rounded-equal) file values, converted to internal units
    tgt = np.array([target[rows][tkey == t].mean() for t in all_targets])
    if units is LINEAR:
        targets_int = tgt  # mm
        scale_dev = 1e-3 if form == "deviation" else 1.0  # um -> mm / mm
    else:
        targets_int = np.deg2rad(tgt)
        scale_dev = (math.pi / 180.0 / 3600.0) if form == "deviation" else math.pi / 180.0
    dev_rows = np.array([row_dev[int(k)] for k in rows]) * scale_dev
    readings = AxisReadings(
        axis=name,
        units=units,
        targets=targets_int,
        up=up * scale_dev,
        down=down * scale_dev,
        source=src,
    )
    return readings, dev_rows
