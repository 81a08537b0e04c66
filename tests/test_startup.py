"""What a command imports before it needs it (issue 27): ``volcal --help`` loads none of
the numerics, and a bad measurement table is reported before SciPy, the solver or the
plotting library is imported (and before the model is built: tests/test_input_first.py).
Each check runs in a fresh interpreter, where ``sys.modules`` starts empty."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

HEAVY = ("numpy", "pandas", "scipy", "casadi", "sympy", "matplotlib", "jinja2")


def _imported_after(code: str) -> tuple[set[str], str]:
    """The heavy packages in sys.modules after ``code`` ran in a new interpreter (code
    leaves its exit code in ``rc``), and the interpreter's stderr."""
    probe = f"import sys\n{code}\nprint(rc, *[m for m in {HEAVY!r} if m in sys.modules])\n"
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    rc, *mods = r.stdout.split()
    return {"rc=" + rc, *mods}, r.stderr


def test_help_imports_no_numerics():
    mods, _ = _imported_after(
        "from volcal.cli.main import build_parser\n"
        "p = build_parser(); rc = 0\n"
        "assert 'identify' in p.format_help() and 'demo' in p.format_help()"
    )
    assert mods == {"rc=0"}, mods


def test_bad_table_reported_before_scipy_and_plots(tmp_path: Path):
    bad = tmp_path / "bad.csv"
    pd.DataFrame(
        {
            "station": ["A"] * 4,
            "point": ["1", "2", "3", "4"],
            "X": [0.0, 10.0, 20.0, 30.0],
            "Y": 0.0,
            "Z": 0.0,
            "length": ["800", "801", "4x5", "803"],
        }
    ).to_csv(bad, index=False)
    out = tmp_path / "out"
    mods, err = _imported_after(
        "from volcal.cli.main import main\n"
        f"rc = main(['identify', '--model', 'mcv754_wxyzt', '--data', {str(bad)!r}, "
        f"'--out', {str(out)!r}])"
    )
    assert "rc=2" in mods
    assert "bad.csv, row 4, column 'length'" in err and "got '4x5'" in err
    # reading a table needs numpy and pandas; the solver's and the plots' libraries wait
    assert not mods & {"scipy", "sympy", "matplotlib", "jinja2"}, mods
    assert not out.exists()


def test_command_runs_numpy_blas_on_one_thread():
    """The command line limits BLAS to one thread (volcal.base.threads) although its parser
    no longer imports numpy: numpy's BLAS is loaded before the limit is set (a library
    loaded after threadpoolctl's call would keep its threads), and SciPy's own BLAS,
    loaded later by a command's first scipy.linalg import, starts with one thread."""
    import os

    code = (
        "import sys\n"
        "from volcal.cli.main import main\n"
        "rc = main(['-q', 'models'])\n"
        "import numpy\n"
        "import scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "blas = [d for d in threadpool_info() if d['user_api'] == 'blas' and\n"
        "        ('numpy' in d['filepath'] or 'scipy' in d['filepath'])]\n"
        "print(rc, *[d['num_threads'] for d in blas])\n"
    )
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2")
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env
    )
    assert r.returncode == 0, r.stderr
    rc, *threads = r.stdout.splitlines()[-1].split()  # after the command's listing
    if not threads:
        pytest.skip("numpy uses a BLAS of the system, not its own")
    assert rc == "0" and set(threads) == {"1"}, r.stdout


def test_ids_with_blanks_read_as_without(tmp_path: Path):
    """Reading skips the per-cell strip of an id column with no blank in it
    (volcal.measurement.tables._stripped): ids padded with spaces, a tab, a no-break and an
    ideographic space read as the same ids written without them, and an id of blanks
    only is still a missing id."""
    from volcal.base.exceptions import InputError
    from volcal.measurement.simulate import example, simulate
    from volcal.measurement.tables import load_measurements

    ex = example("mcv754")
    args = (ex.machine, ex.error_model, ex.theta_true, ex.stations, ex.plan, ex.tools)
    clean = simulate(*args, ex.budget, 0).measurements
    padded = clean.copy()
    pads = [" ", "\t", "\u00a0", "\u3000"]
    padded["station"] = [f"{s}{pads[k % 4]}" for k, s in enumerate(padded["station"])]
    padded["point"] = [f"{pads[(k + 1) % 4]}{p} " for k, p in enumerate(padded["point"])]
    a, b = tmp_path / "clean.csv", tmp_path / "padded.csv"
    clean.to_csv(a, index=False)
    padded.to_csv(b, index=False)
    ma = load_measurements(a, "mcv754_wxyzt")
    mb = load_measurements(b, "mcv754_wxyzt")
    assert mb.station_ids == ma.station_ids and mb.point_ids == ma.point_ids
    assert (mb.station_index == ma.station_index).all()
    assert (mb.point_index == ma.point_index).all()
    padded.loc[3, "point"] = " \t "
    padded.to_csv(b, index=False)
    with pytest.raises(InputError, match=r"row 5, column 'point'.*missing id"):
        load_measurements(b, "mcv754_wxyzt")


def test_point_reused_for_another_pose_names_its_first_row(tmp_path: Path):
    """The first reading of each point id is found without a loop over the readings:
    the warning names the row of the id's first use and the first row that differs from
    it, and counts the differing rows (here known by construction)."""
    from volcal.measurement.simulate import example, simulate
    from volcal.measurement.tables import DataWarning, load_measurements

    ex = example("mcv754")
    args = (ex.machine, ex.error_model, ex.theta_true, ex.stations, ex.plan, ex.tools)
    table = simulate(*args, ex.budget, 0).measurements
    first = table.index[table["point"] == table.loc[1, "point"]][0]  # 0-based table row
    later = [k for k in range(len(table)) if table.loc[k, "point"] != table.loc[1, "point"]]
    k1, k2 = later[40], later[90]
    table.loc[[k1, k2], "point"] = table.loc[1, "point"]  # same id, other poses
    path = tmp_path / "reused.csv"
    table.to_csv(path, index=False)
    with pytest.warns(DataWarning) as record:
        load_measurements(path, "mcv754_wxyzt")
    text = " ".join(str(w.message) for w in record)
    rows = sorted([k1, k2])
    assert (
        f"point '{table.loc[1, 'point']}' has different axis positions or tool offsets in "
        f"rows {first + 2} and {rows[0] + 2} (2 row(s) differ" in text
    ), text
