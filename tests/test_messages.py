"""Messages that are true: a warning prints as ``volcal <command>: warning: <message>``
(not as a Python warning with a source path and code line), ``python -m volcal`` is the
command line, and the extras install what the tutorial notebook needs."""
from __future__ import annotations

import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import pytest

from volcal.cli import main as cli_main
from volcal.measurement.tables import DataWarning

ROOT = Path(__file__).resolve().parents[1]


def test_python_m_volcal_prints_warnings_as_messages(tmp_path):
    """``python -m volcal identify`` on readings taken at one tool offset: the data
    warning names the file and what is wrong, prefixed by the command, and nothing of
    volcal's source (path, line number, code line, warning class) reaches the user."""
    from volcal.measurement.simulate import example

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = example("mcv754").simulate().measurements
    one = m[(m["tool_x"] == 0) & (m["tool_y"] == 0) & (m["tool_z"] == 0)]
    data = tmp_path / "one_tool.csv"
    one.to_csv(data, index=False)
    cmd = [sys.executable, "-m", "volcal", "identify", "--model", "mcv754_wxyzt", "--data",
           str(data), "--degree", "1", "--no-plots", "--out", str(tmp_path / "res")]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    err = run.stderr.splitlines()
    warned = [ln for ln in err if ": warning: " in ln]
    assert any(
        ln.startswith(f"volcal identify: warning: {data}: the tool offset is the same in every")
        for ln in warned
    ), err
    # the inadequate fit is logged through the same form
    assert any(ln.startswith("volcal identify: warning: the model does NOT fit") for ln in warned)
    assert all(ln.startswith("volcal identify: warning: ") for ln in warned)
    assert not [ln for ln in err if ".py:" in ln or "DataWarning" in ln or "warnings.warn" in ln
                or ln.startswith(("WARNING:", "  "))], err
    assert "volcal identify: model 'mcv754_wxyzt'" in run.stdout


def test_warning_printer(capsys):
    show = cli_main._warning_printer("simulate", quiet=False)
    show(DataWarning("station 'S2': points lie in one plane"), DataWarning, "/x/tables.py", 9)
    show(RuntimeWarning("overflow"), RuntimeWarning, "/y/numpy.py", 3)
    assert capsys.readouterr().err.splitlines() == [
        "volcal simulate: warning: station 'S2': points lie in one plane",
        "volcal simulate: warning: overflow (RuntimeWarning)",
    ]
    cli_main._warning_printer("simulate", quiet=True)(UserWarning("x"), UserWarning, "f", 1)
    assert capsys.readouterr().err == ""


def test_main_restores_the_warning_hook(monkeypatch, capsys):
    before = warnings.showwarning
    monkeypatch.setattr(cli_main, "_COMMANDS", ["volcal.cli.commands.models"])
    assert cli_main.main(["models", "--format", "csv"]) == 0
    assert warnings.showwarning is before


@pytest.mark.parametrize("extra", ["test", "docs"])
def test_extras_install_what_the_tutorial_needs(extra):
    """tests/test_notebook.py runs the notebook with nbformat, nbclient and a Python
    kernel (ipykernel); `jupyter nbconvert --execute` (README) needs nbconvert."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    names = {
        r.split(">")[0].split("=")[0].split("~")[0].split("[")[0].strip().lower()
        for r in doc["project"]["optional-dependencies"][extra]
    }
    assert {"nbformat", "nbclient", "ipykernel", "nbconvert"} <= names
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert 'pip install -e ".[docs]"' in readme and "jupyter nbconvert" in readme
