"""One reader of the ISO 230-2 data files (issue 32): ``volcal iso230-2``
(:func:`volcal.iso230_2.load_readings`) and the laser interferometer
(:meth:`LaserInterferometer.read_table`) accept and refuse the same files.

Files are drawn by hypothesis: valid tables of the model's linear axes (targets ascending
or descending per run, either value column, the direction's spellings, ignored columns,
blank lines, axis names in either case), each possibly spoilt by one edit (a blank or
non-numeric cell, a bad direction or cycle, a row dropped, doubled or moved, a column
renamed or added).  A file one path accepts the other accepts with the same numbers (the
interferometer's actual position and line per row against the ISO arrays per axis, target
and cycle); a file one refuses the other refuses with the same message (file, row,
column).  What only the interferometer refuses (a rotary axis, an axis the model has not)
is outside the drawn files and checked on its own."""

from __future__ import annotations

import csv
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volcal.base.exceptions import InputError
from volcal.iso230_2 import load_readings
from volcal.measurement.instruments import LaserInterferometer
from volcal.model.spec import resolve_model

MODEL = "mcv754_wxyzt"
SPEC = resolve_model(MODEL)
LINEAR = [a.name for a in SPEC.axes if not a.is_rotary]
UP, DOWN = ("+", "up", "UP", "pos", "\u2191"), ("-", "down", "Down", "neg", "\u2193")
EDITS = (
    "none",
    "blank",
    "text",
    "direction",
    "cycle",
    "drop",
    "double",
    "move",
    "rename",
    "both_values",
)


@st.composite
def iso_files(draw) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of an ISO 230-2 table of the model's linear axes, perhaps spoilt."""
    axes = draw(st.lists(st.sampled_from(LINEAR), min_size=1, max_size=2, unique=True))
    actual = draw(st.booleans())
    extra = draw(st.booleans())
    header = ["axis", "target_mm", "cycle", "direction", "actual_mm" if actual else "deviation_um"]
    if extra:
        header.append("operator")
    rows: list[list[str]] = []
    for name in axes:
        m = draw(st.integers(2, 5))
        n = draw(st.integers(2, 3))
        start = draw(st.integers(-300, 300))
        step = draw(st.sampled_from([10, 25, 37.5]))
        targets = [start + step * i for i in range(m)]
        written = name.lower() if draw(st.booleans()) else name
        for j in range(1, n + 1):
            for up in (True, False):
                order = targets if draw(st.booleans()) else targets[::-1]
                d = draw(st.sampled_from(UP if up else DOWN))
                for t in order:
                    dev = draw(st.integers(-4000, 4000)) / 1000.0  # um, to 1 nm
                    value = f"{t + dev * 1e-3:.9f}" if actual else f"{dev:g}"
                    row = [written, f"{t:g}", str(j), d, value]
                    if extra:
                        row.append("ab")
                    rows.append(row)
    edit = draw(st.sampled_from(EDITS))
    k = draw(st.integers(0, len(rows) - 1))
    col = draw(st.integers(0, 4))
    if edit == "blank":
        rows[k][col] = ""
    elif edit == "text":
        rows[k][col] = draw(st.sampled_from(["abc", "1,5", "inf", "nan"]))
    elif edit == "direction":
        rows[k][3] = draw(st.sampled_from(["x", "", "upward", "+-"]))
    elif edit == "cycle":
        rows[k][2] = draw(st.sampled_from(["0", "1.5", "-1", "7"]))
    elif edit == "drop":
        del rows[k]
    elif edit == "double":
        rows.insert(k, list(rows[k]))
    elif edit == "move":
        rows.insert(draw(st.integers(0, len(rows) - 1)), rows.pop(k))
    elif edit == "rename":
        header[col] = draw(st.sampled_from(["target", "deviation", "Cycle ", "axes"]))
    elif edit == "both_values":
        header.append("deviation_um" if actual else "actual_mm")
        for r in rows:
            r.append("0")
    if draw(st.booleans()):  # a blank line: skipped, but counted in the row numbers
        rows.insert(draw(st.integers(0, len(rows))), [""] * len(header))
    return header, rows


def _write(path: Path, header: list[str], rows: list[list[str]]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in rows:
            if any(r):
                w.writerow(r)
            else:
                fh.write("\n")


def _outcome(read):
    try:
        return read(), None
    except InputError as exc:
        return None, (str(exc), exc.source, exc.row, exc.column)


@settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(iso_files())
def test_iso_reader_and_interferometer_accept_and_refuse_the_same_files(case):
    header, rows = case
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "axis.csv"
        _write(path, header, rows)
        before = path.read_bytes()
        iso, iso_err = _outcome(lambda: load_readings(path))
        ifm, ifm_err = _outcome(lambda: LaserInterferometer().read_table(path, SPEC))
        assert path.read_bytes() == before  # inputs never modified
    assert iso_err == ifm_err, (iso_err, ifm_err)
    if iso_err is not None:
        assert iso_err[1] == str(path)  # the message names the file
        return
    # the same numbers: every interferometer reading is one entry of the ISO arrays
    by_axis = {a.axis.upper(): a for a in iso}
    assert set(ifm["station"]) == {f"{a}-line" for a in by_axis}
    assert len(ifm) == sum(2 * a.m * a.n for a in iso)
    for _, r in ifm.iterrows():
        name = r["station"].split("-")[0]
        a = by_axis[name]
        target = r[f"{name}_mm"]
        i = int(np.argmin(np.abs(a.targets - target)))
        assert abs(a.targets[i] - target) < 1e-9
        cycle, sign = re.fullmatch(r"\w+-c(\d+)([+-])-r\d+", r["point"]).groups()
        dev = (a.up if sign == "+" else a.down)[i, int(cycle) - 1]
        assert abs(r["length_mm"] - (a.targets[i] + dev)) < 1e-9
        others = [b for b in LINEAR if b != name]
        for b in others:  # the other axes at their reference positions
            ref = next(x.reference for x in SPEC.axes if x.name == b)
            assert r[f"{b}_mm"] == ref


def _valid_rows(axis: str = "X") -> list[list[str]]:
    return [
        [axis, f"{t}", str(j), d, "1.5"]
        for j in (1, 2)
        for d in ("+", "-")
        for t in ((0, 100) if d == "+" else (100, 0))
    ]


def test_what_only_the_interferometer_refuses(tmp_path):
    """A rotary axis (target_deg) and an axis the model has not: the ISO evaluation reads
    them, the interferometer says it reads the model's linear axes, naming the cell."""
    path = tmp_path / "c.csv"
    _write(path, ["axis", "target_deg", "cycle", "direction", "deviation_arcsec"], _valid_rows("C"))
    assert load_readings(path)[0].units.kind == "rotary"
    with pytest.raises(InputError, match=r"c.csv, row 1, column 'target_deg': an interf"):
        LaserInterferometer().read_table(path, SPEC)
    path = tmp_path / "q.csv"
    _write(path, ["axis", "target_mm", "cycle", "direction", "deviation_um"], _valid_rows("Q"))
    assert load_readings(path)[0].axis == "Q"
    with pytest.raises(InputError, match=r"q.csv, row 2, column 'axis': axis 'Q': an interf"):
        LaserInterferometer().read_table(path, SPEC)


def test_the_interferometers_own_columns_are_read_with_row_and_column(tmp_path):
    """The further columns (other axes, tool offset, sigma) of an ISO file: numbers where
    given, a bad cell named by its file row (a blank line counted) and column."""
    path = tmp_path / "x.csv"
    rows = [r + ["250", "0.2"] for r in _valid_rows("X")]
    _write(
        path, ["axis", "target_mm", "cycle", "direction", "deviation_um", "Y_mm", "sigma_um"], rows
    )
    tab = LaserInterferometer().read_table(path, SPEC)
    assert (tab["Y_mm"] == 250.0).all() and np.allclose(tab["sigma_mm"], 0.2e-3)
    assert np.allclose(tab["length_mm"], tab["X_mm"] + 1.5e-3)
    rows[4][5] = "near"
    _write(
        path,
        ["axis", "target_mm", "cycle", "direction", "deviation_um", "Y_mm", "sigma_um"],
        rows[:2] + [[""] * 7] + rows[2:],
    )
    with pytest.raises(InputError, match=r"x.csv, row 7, column 'Y_mm': 'near' is not a number"):
        LaserInterferometer().read_table(path, SPEC)
