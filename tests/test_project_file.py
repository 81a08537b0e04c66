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


def test_project_file_settings_flags_and_errors(tmp_path):
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
    # --project elsewhere: relative paths are relative to that file
    sub = tmp_path / "p"
    sub.mkdir()
    (sub / "other.toml").write_text('[simulate]\nexample = "mcv754"\nseed = 4\nout = "s4"\n')
    r = _volcal(tmp_path, "--project", "p/other.toml", "simulate", "-q")
    assert r.returncode == 0, r.stderr
    assert (sub / "s4" / "measurements.csv").exists()
    (sub / "bad.toml").write_text('[identify]\nstrategi = "joint"\n')
    r = _volcal(tmp_path, "--project", "p/bad.toml", "identify")
    assert r.returncode == 2
    assert "bad.toml" in r.stderr and "strategi" in r.stderr and "strategy" in r.stderr
