"""A measurement table read with the standard library (volcal.measurement.cells, issue 27:
a bad cell reported before numpy and pandas are imported) against pandas' reading of the
same file (the loader with the scan turned off): the same error word for word (file, row,
column, what was expected), the same warnings, or, for a file both accept, the same
Measurements.

Files are drawn by hypothesis: valid tables of a 3-axis and a 5-axis model (column order,
synonyms, optional columns, numbers written in several ways), spoilt by up to three edits
(a cell that is not a number, empty, blank, nan, inf, out of range, a decimal comma,
Python-only numbers such as 1_0 or Arabic digits, a quoted value, a short or long row,
a blank line, a doubled row, a misspelled column), written with LF, CRLF or CR line
ends, with or without a UTF-8 byte-order mark and a last line end."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volcal.base.exceptions import InputError
from volcal.measurement import cells
from volcal.measurement import tables as loader
from volcal.measurement.cells import ScannedTable, scan_measurements
from volcal.measurement.tables import load_measurements
from volcal.model.spec import resolve_model

SPECS = {m: resolve_model(m) for m in ("mcv754_wxyzt", "trunnion_ac")}
#: replacement cells: not numbers, blanks, missing-value words, infinities, numbers only
#: Python's float reads, numbers in odd but valid forms, out of range values
POOL = [
    "4x5.2", "abc", "1,5", " 1,5 ", "", " ", "nan", "NA", "None", "-nan", "inf", "-Infinity",
    "1e999", "1_0", "\u0661\u0662", "\u00a012.5", "1.5.2", "--1", "1e", ".", "+.5", "5.",
    " 7 ", "1E2", "0", "-5", "-0", "1e6", "0.0001", "400", "-400", "12",
]  # fmt: skip
EDITS = (
    "cell",
    "cell",
    "cell",
    "quote",
    "short",
    "long",
    "blank",
    "commas",
    "double",
    "rename",
    "tab",
)


@contextlib.contextmanager
def _pandas_only(typed: bool = False):
    """The loader with the standard-library reading turned off (every file to pandas);
    typed: with the typed reading of a clean file (numbers parsed by pandas' C parser,
    loader._read_typed) tried first, as for a file above MAX_SCAN_BYTES; otherwise the text
    reading alone (every cell read as text, then to_numeric: the reference)."""
    saved = cells.MAX_SCAN_BYTES, loader.TYPED_READING
    cells.MAX_SCAN_BYTES, loader.TYPED_READING = -1, typed
    try:
        yield
    finally:
        cells.MAX_SCAN_BYTES, loader.TYPED_READING = saved


def _number(draw, lo: float, hi: float) -> str:
    v = draw(st.floats(lo, hi, allow_nan=False, allow_infinity=False))
    form = draw(st.sampled_from(["repr", "fixed", "exp", "int"]))
    if form == "fixed":
        return f"{v:.3f}"
    if form == "exp":
        return f"{v:.6e}"
    if form == "int":
        return str(round(v))
    return repr(v)


@st.composite
def tables(draw) -> tuple[str, bytes]:
    model = draw(st.sampled_from(sorted(SPECS)))
    spec = SPECS[model]
    cols: list[tuple[str, str]] = [("station", "station"), ("point", "point")]
    for a in spec.axes:
        unit = "deg" if a.is_rotary else "mm"
        cols.append((a.name, draw(st.sampled_from([a.name, f"{a.name}_{unit}"]))))
    if draw(st.booleans()):
        cols += [(f"tool_{c}", f"tool_{c}") for c in "xyz"]
    cols.append(("length", draw(st.sampled_from(["length", "length_mm"]))))
    for opt in ("time", "sigma"):
        if draw(st.booleans()):
            cols.append((opt, opt))
    order = draw(st.permutations(range(len(cols))))
    cols = [cols[k] for k in order]
    radians = any(a.is_rotary for a in spec.axes) and draw(st.booleans())
    n = draw(st.integers(8, 14))
    rows: list[list[str]] = []
    for k in range(n):
        row = []
        for canon, _ in cols:
            if canon == "station":
                v = "A" if k < n // 2 else "B"
            elif canon == "point":
                v = f"p{k}"
            elif canon == "length":
                v = _number(draw, 100.0, 2000.0)
            elif canon.startswith("tool_"):
                v = _number(draw, -100.0, 100.0)
            elif canon == "time":
                v = "" if draw(st.integers(0, 4)) == 0 else f"{0.5 * k:g}"
            elif canon == "sigma":
                v = "" if draw(st.integers(0, 4)) == 0 else "0.001"
            else:
                a = next(x for x in spec.axes if x.name == canon)
                lo, hi = a.travel
                if radians and a.is_rotary:
                    lo, hi = -3.0, 3.0  # degrees that look like radians: a warning
                v = _number(draw, lo, hi)
            row.append(v)
        rows.append(row)
    header = [name for _, name in cols]
    for _ in range(draw(st.integers(0, 3))):
        edit = draw(st.sampled_from(EDITS))
        k = draw(st.integers(0, len(rows) - 1))
        j = draw(st.integers(0, len(cols) - 1))
        if not rows[k]:
            continue
        j = min(j, len(rows[k]) - 1)
        if edit == "cell":
            rows[k][j] = draw(st.sampled_from(POOL))
        elif edit == "quote":  # a quoted value, perhaps with a comma or a doubled quote
            v = draw(st.sampled_from([rows[k][j], "1,5", 'a"b', " 12.5", ""]))
            rows[k][j] = '"' + v.replace('"', '""') + '"'
        elif edit == "short":
            rows[k] = rows[k][: draw(st.integers(1, len(rows[k]) - 1))] if len(rows[k]) > 1 else []
        elif edit == "long":
            rows[k] = rows[k] + [draw(st.sampled_from(["", "1", "x"]))]
        elif edit == "blank":
            rows.insert(k, [])
        elif edit == "commas":
            rows.insert(k, [" "] * len(cols))
        elif edit == "double":
            rows.insert(k, list(rows[k]))
        elif edit == "rename":
            header[j] = draw(st.sampled_from(["lenght", "X_in", "temperature", "Point"]))
        elif edit == "tab":
            rows[k][j] = f" {rows[k][j]}\t"
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    lines = [",".join(header)] + [",".join(r) for r in rows]
    text = newline.join(lines) + (newline if draw(st.booleans()) else "")
    if draw(st.booleans()):
        text += newline * draw(st.integers(1, 2))  # blank lines at the end
    data = text.encode("utf-8")
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data  # a byte-order mark
    return model, data


def _DRAWN(max_examples: int):  # noqa: N802 - used as a decorator, like hypothesis' own
    """The drawn files' settings: a fixed sequence of examples (derandomised, no example
    database), so that a run checks the same files as the last."""
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow],
    )


@contextlib.contextmanager
def _written(case):
    """A drawn file written to a temporary folder: (spec, path, its bytes, the text
    reading's outcome); afterwards the file is checked unchanged (inputs never modified)."""
    model, data = case
    spec = SPECS[model]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "meas.csv"
        path.write_bytes(data)
        with _pandas_only():
            ref = _outcome(lambda: load_measurements(path, spec))
        yield spec, path, data, ref
        assert path.read_bytes() == data


def _outcome(read):
    """(result, error, warnings) of one reading."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result, error = read(), None
        except InputError as exc:
            result, error = None, (str(exc), exc.source, exc.row, exc.column)
    return result, error, [(w.category.__name__, str(w.message)) for w in caught]


def _same_measurements(a, b) -> None:
    for f in ("q_internal", "tool", "length", "sigma", "time", "rows"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f
    assert a.station_ids == b.station_ids and a.point_ids == b.point_ids
    assert a.given_columns == b.given_columns and a.source == b.source
    assert a.table.equals(b.table)


@_DRAWN(max_examples=100)
@given(tables())
def test_the_standard_library_reading_is_pandas_reading(case):
    with _written(case) as (spec, path, data, (ref, ref_err, ref_warn)):
        scanned, err, warn = _outcome(lambda: scan_measurements(path, spec))
        if err is not None:  # refused before pandas: the loader's error and warnings
            assert ref_err is not None, (err, data)
            assert err == ref_err, (data, err, ref_err)
            assert warn == ref_warn
            return
        # the drawn files are all read here (a plain header, standard quoting)
        assert isinstance(scanned, ScannedTable), data
        got, got_err, got_warn = _outcome(lambda: load_measurements(scanned, spec))
        assert got_err == ref_err, (data, got_err, ref_err)
        assert got_warn == ref_warn
        if ref is not None:
            _same_measurements(got, ref)


@_DRAWN(max_examples=60)
@given(tables())
def test_the_typed_reading_of_a_large_file_is_the_text_reading(case):
    """A file above MAX_SCAN_BYTES is first read with its number columns parsed by pandas'
    C parser (loader._read_typed); a file that is not clean goes to the text reading. On
    the drawn files (spoilt or not): the same error, warnings and Measurements as the text
    reading alone, and the typed reading takes every clean file it is given."""
    with _written(case) as (spec, path, data, (ref, ref_err, ref_warn)):
        with _pandas_only(typed=True):
            got, err, warn = _outcome(lambda: load_measurements(path, spec))
        assert (err, warn) == (ref_err, ref_warn), data
        if ref is not None:
            _same_measurements(got, ref)


def test_the_typed_reading_takes_a_clean_file_and_leaves_a_spoilt_one(tmp_path):
    """The typed reading reads a clean file (so that the test above compares it, not only
    its fallback) and declines one with a bad cell, a blank line, an infinity or an empty
    id, each of which the text reading then reports."""
    spec = SPECS["mcv754_wxyzt"]
    clean = "\n".join(GOOD) + "\n"
    raw = loader._read_typed(_write(tmp_path, clean), spec, None)
    assert raw is not None and raw.body[3].dtype == np.float64
    assert list(raw.rows) == list(range(2, len(GOOD) + 1))
    for spoilt in (
        clean.replace(",803,", ",4x5.2,"),
        clean.replace("\nA,p2,", "\n\nA,p2,"),
        clean.replace(",803,", ",inf,"),
        clean.replace("\nA,p2,", "\n,p2,"),
        clean.replace(",803,", ",nan,"),
    ):
        assert loader._read_typed(_write(tmp_path, spoilt), spec, None) is None, spoilt


def _write(tmp_path: Path, text: str, bom: bool = False) -> Path:
    path = tmp_path / "meas.csv"
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode("utf-8"))
    return path


GOOD = [
    "station,point,X,Y,Z,length,time",
    *[f"{'A' if k < 4 else 'B'},p{k},{100 * k % 700},{50 * (k % 3)},{-10 * k},{800 + k},{k}"
      for k in range(8)],
]  # fmt: skip


@pytest.mark.parametrize(
    ("edit", "bom", "newline", "where"),
    [
        (lambda r: r.__setitem__(4, r[4].replace(",803,", ",4x5.2,")), False, "\n", "row 5"),
        (lambda r: r.__setitem__(4, r[4].replace(",803,", ",,")), False, "\n", "row 5"),
        (lambda r: r.__setitem__(8, r[8] + ",1"), False, "\n", "row 9"),  # a long last row
        (lambda r: r.__setitem__(8, r[8].replace(",807,", ",inf,")), True, "\r\n", "row 9"),
        (lambda r: r.__setitem__(2, r[2].replace(",801,", ',"1,5",')), True, "\n", "row 3"),
        # one cell too many in row 3 and one too few in row 5: the same number of commas
        (
            lambda r: r.__setitem__(2, r[2] + ",1") or r.__setitem__(4, r[4].rsplit(",", 1)[0]),
            False,
            "\n",
            "row 3",
        ),
        # a short row (no length) after a blank line, which is counted
        (
            lambda r: r.__setitem__(7, r[7].rsplit(",", 2)[0]) or r.insert(3, ""),
            False,
            "\r\n",
            "row 9",
        ),
    ],
)
def test_each_kind_of_cell_error_is_the_loaders(tmp_path, edit, bom, newline, where):
    """A bad cell, an empty one, a row too long, an infinity, a quoted decimal comma, a
    blank line before a short row: the standard-library reading raises the error pandas'
    reading raises, naming the file, row and column."""
    spec = SPECS["mcv754_wxyzt"]
    rows = list(GOOD)
    edit(rows)
    path = _write(tmp_path, newline.join(rows) + newline, bom)
    with _pandas_only():
        _, ref_err, _ = _outcome(lambda: load_measurements(path, spec))
    with pytest.raises(InputError) as info:
        scan_measurements(path, spec)
    assert ref_err is not None and str(info.value) == ref_err[0]
    assert f"{path}, {where}" in str(info.value)


@pytest.mark.parametrize("value", POOL)
@pytest.mark.parametrize("column", ["length", "time", "station"])
def test_every_replacement_cell_is_read_as_pandas_reads_it(tmp_path, value, column):
    """Each drawn replacement in a required number column, an optional one and an id
    column: the same error, or the same numbers (the rare ones included: 1_0 and Arabic
    digits, which Python's float reads and pandas does not)."""
    spec = SPECS["mcv754_wxyzt"]
    rows = [r.split(",") for r in GOOD]
    rows[4][rows[0].index(column)] = value
    path = _write(tmp_path, "\n".join(",".join(r) for r in rows) + "\n")
    with _pandas_only():
        ref, ref_err, ref_warn = _outcome(lambda: load_measurements(path, spec))
    got, err, warn = _outcome(lambda: load_measurements(path, spec))
    assert (err, warn) == (ref_err, ref_warn)
    if ref is not None:
        _same_measurements(got, ref)


def test_a_large_file_is_left_to_pandas(tmp_path):
    """Above MAX_SCAN_BYTES the file is pandas' to read (no extra pass over a large
    table): the scan does not read it, the loader still reports its bad cell."""
    path = _write(tmp_path, "\n".join(GOOD).replace(",803,", ",4x5.2,") + "\n")
    saved = cells.MAX_SCAN_BYTES
    cells.MAX_SCAN_BYTES = path.stat().st_size - 1
    try:
        assert scan_measurements(path, SPECS["mcv754_wxyzt"]) is None
        with pytest.raises(InputError, match="row 5, column 'length': expected a number"):
            load_measurements(path, SPECS["mcv754_wxyzt"])
    finally:
        cells.MAX_SCAN_BYTES = saved


def test_tracker_reads_positive_lengths():
    """The command line scans a tracker's table with positive lengths before it imports
    the instruments: the tracker's readings are positive."""
    from volcal.measurement.instruments import get_instrument

    assert get_instrument("tracker").positive_readings


def test_bad_cell_reported_before_numpy(tmp_path: Path):
    """From the command line a bad cell in the last row exits 2 with the loader's message
    before numpy, pandas or anything after them is imported, and writes nothing."""
    path = _write(tmp_path, "\n".join(GOOD).replace(",807,", ",4x5.2,") + "\n")
    out = tmp_path / "out"
    heavy = ("numpy", "pandas", "scipy", "casadi", "sympy", "matplotlib")
    probe = (
        "import sys\nfrom volcal.cli.main import main\n"
        f"rc = main(['identify', '--model', 'mcv754_wxyzt', '--data', {str(path)!r}, "
        f"'--out', {str(out)!r}])\n"
        f"print(rc, *[m for m in {heavy!r} if m in sys.modules])\n"
    )
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert r.stdout.split() == ["2"], (r.stdout, r.stderr)
    assert r.stderr.strip() == (
        f"volcal identify: error: {path}, row 9, column 'length': expected a number (mm), "
        "got '4x5.2'"
    )
    assert not out.exists()
