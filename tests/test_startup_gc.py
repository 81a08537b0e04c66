"""The garbage collector paused through the program's start-up imports
(volcal.base.processes.pause_gc / resume_gc): as the program, `volcal identify` solves with
the collector running again and the start-up's objects frozen; a caller of ``main(argv)``
keeps its collector as it was.  Each check runs in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pandas as pd


def _run(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip().splitlines()[-1]


def test_pause_and_resume():
    out = _run(
        "import gc\n"
        "from volcal.base.processes import pause_gc, resume_gc\n"
        "a = pause_gc(); off = gc.isenabled()\n"
        "resume_gc(); on, frozen = gc.isenabled(), gc.get_freeze_count()\n"
        "resume_gc()  # again: nothing to do\n"
        "gc.disable(); b = pause_gc(); resume_gc(); still_off = not gc.isenabled()\n"
        "print(a, off, on, frozen > 0, b, still_off)\n"
    )
    assert out == "True False True True False True"


def test_identify_as_program_solves_with_the_collector_on(tmp_path: Path):
    """Run as the program, identify resumes the collector before the identification (the
    state is probed where the solve would start; the probe then stops the command)."""
    path = tmp_path / "meas.csv"
    pd.DataFrame(
        {"station": ["A"] * 4, "point": ["1", "2", "3", "4"], "X": [0.0, 10.0, 20.0, 30.0],
         "Y": 0.0, "Z": 0.0, "length": [800.0, 801.0, 802.0, 803.0]}
    ).to_csv(path, index=False)  # fmt: skip
    code = (
        "import gc, sys\n"
        "import volcal.workflow.dispatch as d\n"
        "from volcal.base.exceptions import InputError\n"
        "def probe(*a, **k):\n"
        "    raise InputError(f'probe {gc.isenabled()} {gc.get_freeze_count() > 0}')\n"
        "d.identify = probe\n"
        "from volcal.cli.main import main\n"
        "sys.argv = ['volcal', 'identify', '--model', 'mcv754_wxyzt', '--data', "
        f"{str(path)!r}, '--out', {str(tmp_path / 'out')!r}]\n"
        "rc = main()\n"
        "print(rc, gc.isenabled())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr  # the program ends at once on the probe's error
    assert "probe True True" in r.stderr, r.stderr


def test_main_with_argv_leaves_the_callers_collector_alone():
    out = _run(
        "import gc\n"
        "from volcal.cli.main import main\n"
        "rc = main(['-q', 'models'])\n"
        "print(rc, gc.isenabled(), gc.get_freeze_count())\n"
    )
    assert out == "0 True 0"


def test_plan_as_program_plans_with_the_collector_on(tmp_path: Path):
    """Run as the program, plan imports and reads its setting with the collector paused,
    then resumes it (the start-up's objects frozen) before the planning (probed where the
    setting is read and where the planning starts; the second probe stops the command)."""
    code = (
        "import gc, sys\n"
        "import volcal.analysis.planning as planning\n"
        "import volcal.analysis.planning.setting as setting\n"
        "from volcal.base.exceptions import InputError\n"
        "seen = []\n"
        "load = setting.load_setting\n"
        "def reading(*a, **k):\n"
        "    seen.append(gc.isenabled())\n"
        "    return load(*a, **k)\n"
        "def probe(*a, **k):\n"
        "    raise InputError(f'probe {seen} {gc.isenabled()} {gc.get_freeze_count() > 0}')\n"
        "setting.load_setting = reading\n"
        "planning.plan = probe\n"
        "from volcal.cli.main import main\n"
        "sys.argv = ['volcal', 'plan', '--setting', 'mcv754', '--no-plots', '--out', "
        f"{str(tmp_path / 'out')!r}]\n"
        "rc = main()\n"
        "print(rc, gc.isenabled())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "probe [False] True True" in r.stderr, r.stderr
    assert r.stdout.strip() == "2 True", r.stderr  # an error returns its code (exit 2)
    assert not (tmp_path / "out").exists()
