"""A project file (volcal.toml) holds one table of settings per command; flags override
it; bad keys name the file and the key (exit 2); the effective settings are recorded in
the result."""
from __future__ import annotations

import json
import subprocess
import sys


def _volcal(cwd, *args):
    return subprocess.run(
        [sys.executable, "-m", "volcal.cli.main", *args],
        cwd=cwd, capture_output=True, text=True,
    )


def _volcal_here(cwd, monkeypatch, capsys, *args):
    """The same command in this process (volcal.cli.main.main, what the program calls),
    run from ``cwd``: exit code and stderr."""
    from volcal.cli.main import main

    monkeypatch.chdir(cwd)
    capsys.readouterr()
    code = main(list(args))
    return code, capsys.readouterr().err


def test_project_file_settings_flags_and_errors(tmp_path, monkeypatch, capsys):
    (tmp_path / "volcal.toml").write_text(
        '[simulate]\nexample = "mcv754"\nseed = 3\nout = "sim"\n'
        '[identify]\nmodel = "mcv754_wxyzt"\ndata = "sim/measurements.csv"\n'
        'stations = "sim/stations.csv"\nout = "res"\nno-plots = true\n'
    )
    r = _volcal(tmp_path, "simulate", "-q")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "sim" / "measurements.csv").exists()
    r = _volcal(tmp_path, "identify", "-q", "--strategy", "two-phase")  # a flag overrides
    assert r.returncode == 0, r.stderr
    opts = json.loads((tmp_path / "res" / "result.json").read_text())["options"]
    assert opts["strategy"] == "two-phase" and opts["project_file"].endswith("volcal.toml")
    assert not (tmp_path / "res" / "component_errors.png").exists()  # no-plots from the file
    # --project elsewhere: relative paths are relative to that file (in this process: the
    # program's own start is checked above)
    sub = tmp_path / "p"
    sub.mkdir()
    (sub / "other.toml").write_text('[simulate]\nexample = "mcv754"\nseed = 4\nout = "s4"\n')
    code, err = _volcal_here(tmp_path, monkeypatch, capsys, "--project", "p/other.toml",
                             "simulate", "-q")
    assert code == 0, err
    assert (sub / "s4" / "measurements.csv").exists()
    (sub / "bad.toml").write_text('[identify]\nstrategi = "joint"\n')
    code, err = _volcal_here(tmp_path, monkeypatch, capsys, "--project", "p/bad.toml",
                             "identify")
    assert code == 2
    assert "bad.toml" in err and "strategi" in err and "strategy" in err
