"""The measurement table's header checked before pandas is imported (issue 27: a bad CSV
reported in < 0.5 s): :func:`volcal.measurement.header.check_header` reads the first
line with the standard library and raises the error the full loader raises for that
header, or leaves the file to the loader when one line cannot decide; a bad cell further
down is still the loader's, and the program then ends without the interpreter's teardown
with the same message and exit code 2."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.measurement.header import check_header
from volcal.measurement.tables import DataWarning, load_measurements
from volcal.model.spec import resolve_model

HEAVY = ("numpy", "pandas", "scipy", "casadi", "sympy", "matplotlib", "jinja2")


def _table() -> pd.DataFrame:
    return pd.DataFrame(
        {
            "station": ["A"] * 4 + ["B"] * 4,
            "point": [f"p{k}" for k in range(8)],
            "X": [0.0, 100.0, 200.0, 300.0] * 2,
            "Y": [0.0, 50.0, 0.0, 50.0] * 2,
            "Z": [-10.0, -20.0, -30.0, -40.0] * 2,
            "length": [800.0 + k for k in range(8)],
        }
    )


def _loader_error(path: Path, spec) -> str | None:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)  # the small table's geometry
            load_measurements(path, spec)
    except InputError as exc:
        return str(exc)
    return None


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d.rename(columns={"length": "lenght"}),  # misspelled: closest suggested
        lambda d: d.drop(columns=["Z"]),  # an axis of the model missing
        lambda d: d.assign(B=0.0),  # an axis the model does not have
        lambda d: d.assign(temperature=20.0),  # unknown column
        lambda d: d.assign(length_mm=d["length"]),  # one quantity twice
        lambda d: d.drop(columns=["station"]).assign(x=d["X"]),  # several problems at once
    ],
)
def test_header_error_is_the_loaders(tmp_path: Path, edit):
    """A header the loader refuses is refused by the first line alone, with the loader's
    message word for word (the truth here is the loader, which reads the whole table)."""
    spec = resolve_model("mcv754_wxyzt")
    path = tmp_path / "meas.csv"
    edit(_table()).to_csv(path, index=False)
    expected = _loader_error(path, spec)
    assert expected is not None and "row 1" in expected
    with pytest.raises(InputError) as info:
        check_header(path, spec)
    assert str(info.value) == expected


@pytest.mark.parametrize(
    "header",
    [
        "station,point,X,Y,Z,length,",  # a trailing separator: an empty unnamed column
        '"station",point,X,Y,Z,length',  # quoted names
        "station;point;X;Y;Z;length",  # another separator: the loader explains it
        "",  # an empty first line
    ],
)
def test_undecidable_first_line_is_left_to_the_loader(tmp_path: Path, header: str):
    """A first line that the cheap reading could read otherwise than pandas does is not
    judged: check_header returns, and the loader accepts the table or reports it."""
    spec = resolve_model("mcv754_wxyzt")
    body = _table().to_csv(index=False).splitlines()[1:]
    sep = ";" if ";" in header else ","
    trail = "," if header.endswith(",") else ""
    path = tmp_path / "meas.csv"
    path.write_text(
        "\n".join([header, *(line.replace(",", sep) + trail for line in body)]) + "\n",
        encoding="utf-8",
    )
    check_header(path, spec)  # no verdict
    err = _loader_error(path, spec)
    if header.startswith(("station,", '"station"')):
        assert err is None  # the loader reads these tables
    else:
        assert err is not None


def test_good_header_passes(tmp_path: Path):
    path = tmp_path / "meas.csv"
    _table().to_csv(path, index=False)
    check_header(path, resolve_model("mcv754_wxyzt"))
    check_header(tmp_path / "absent.csv", resolve_model("mcv754_wxyzt"))  # the loader's


def _run_probe(code: str) -> tuple[int, list[str], str]:
    probe = f"import sys\n{code}\nprint(rc, *[m for m in {HEAVY!r} if m in sys.modules])\n"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    rc, *mods = r.stdout.split()
    return int(rc), mods, r.stderr


def test_bad_header_reported_before_pandas(tmp_path: Path):
    """From the command line a bad header exits 2 naming file, row and column before
    pandas (and everything after it) is imported."""
    path = tmp_path / "meas.csv"
    _table().rename(columns={"length": "lenght"}).to_csv(path, index=False)
    out = tmp_path / "out"
    rc, mods, err = _run_probe(
        "from volcal.cli.main import main\n"
        f"rc = main(['identify', '--model', 'mcv754_wxyzt', '--data', {str(path)!r}, "
        f"'--out', {str(out)!r}])"
    )
    assert rc == 2
    assert "meas.csv, row 1, column 'length'" in err and "'lenght' meant to be 'length'" in err
    assert not mods, mods  # no numerical package yet
    assert not out.exists()


def test_bad_cell_exit_as_program(tmp_path: Path):
    """A bad cell deep in the table needs the loader; run as the program, the command
    then ends at once (no teardown) with the whole message on stderr and exit code 2,
    and writes nothing."""
    table = _table()
    table["length"] = table["length"].astype(str)
    table.loc[6, "length"] = "4x5.2"
    path = tmp_path / "meas.csv"
    table.to_csv(path, index=False)
    out = tmp_path / "out"
    r = subprocess.run(
        [sys.executable, "-m", "volcal", "identify", "--model", "mcv754_wxyzt", "--data",
         str(path), "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (
        f"volcal identify: error: {path}, row 8, column 'length': expected a number (mm), "
        "got '4x5.2'"
    )
    assert not out.exists()
