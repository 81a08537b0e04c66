"""Golden files of the C export: the hand-written files of an export (API header, driver,
example program, Makefile, README, plan) for one small fixed configuration, compared byte
for byte with what the templates in ``src/volcal/codegen/templates/`` write today.

Configuration: model ``xfyz``, simulated with
``volcal simulate --model xfyz --grid 3 --tools "0,0,0;0,0,-100" --seed 3`` (324 readings),
exported as a joint solver with the default options; and the model-only export of ``xfyz``.
The CasADi-generated files (``*_generated.c/.h``, which depend on the CasADi version) and
``manifest.json`` (hashes, timings) are not golden; the volcal and CasADi version numbers
in the files are replaced by ``<volcal-version>`` and ``<casadi-version>``.

A deliberate change of a template: regenerate the goldens with

    VOLCAL_UPDATE_GOLDEN=1 python -m pytest -q -p no:cacheprovider tests/test_codegen_golden.py

and review the diff of ``tests/golden/codegen/`` before committing it.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import casadi as ca
import pandas as pd
import pytest

from volcal import __version__
from volcal.outputs.codegen import export_model, export_solver

GOLDEN = Path(__file__).parent / "golden" / "codegen"
UPDATE = os.environ.get("VOLCAL_UPDATE_GOLDEN", "") not in ("", "0")


def _normalise(text: str) -> str:
    return (text.replace(f"volcal {__version__}", "volcal <volcal-version>")
            .replace(f"CasADi {ca.__version__}", "CasADi <casadi-version>"))


def _golden_files(folder: Path, name: str) -> dict[str, str]:
    names = [f"{name}.h", f"{name}.c", "main.c", "Makefile", "README.md", "plan.csv"]
    return {n: _normalise((folder / n).read_text()) for n in names if (folder / n).exists()}


def _compare(kind: str, folder: Path, name: str) -> None:
    files = _golden_files(folder, name)
    gdir = GOLDEN / kind
    if UPDATE:
        shutil.rmtree(gdir, ignore_errors=True)
        gdir.mkdir(parents=True)
        for name, text in files.items():
            (gdir / name).write_bytes(text.encode())
        return
    assert gdir.is_dir(), f"no golden files in {gdir}; set VOLCAL_UPDATE_GOLDEN=1 to write them"
    expected = sorted(p.name for p in gdir.iterdir())
    assert sorted(files) == expected
    for name in expected:
        want = (gdir / name).read_bytes()
        got = files[name].encode()
        if got != want:
            import difflib
            diff = "".join(list(difflib.unified_diff(
                want.decode().splitlines(True), got.decode().splitlines(True),
                f"golden/{kind}/{name}", f"generated/{name}"))[:60])
            pytest.fail(f"{name} differs from its golden file (VOLCAL_UPDATE_GOLDEN=1 "
                        f"regenerates deliberately):\n{diff}")


@pytest.fixture(scope="module")
def measurements(tmp_path_factory):
    """What ``volcal simulate --model xfyz --grid 3 --tools "0,0,0;0,0,-100" --seed 3``
    writes (through the Python API, so that this test does not depend on the command
    line)."""
    import numpy as np

    from volcal.measurement.plans import default_stations, grid_plan
    from volcal.measurement.simulate import draw_true_parameters, parse_tools, simulate
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.model.machine import Machine

    seed = 3
    machine = Machine.from_model("xfyz")
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 3))
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(99,)))
    theta = draw_true_parameters(machine, em, rng, 60.0)
    sim = simulate(machine, em, theta, default_stations(machine.spec, 6, seed=seed),
                   grid_plan(machine.spec, 3), parse_tools("0,0,0;0,0,-100"), "paper002",
                   seed)
    path = tmp_path_factory.mktemp("sim") / "measurements.csv"
    sim.measurements.to_csv(path, index=False)
    return path


def test_solver_export_matches_golden_files(measurements, tmp_path):
    info = export_solver("xfyz", pd.read_csv(measurements), tmp_path / "solver",
                         build_it=False)
    _compare("solver_xfyz", info.path, info.name)


def test_model_export_matches_golden_files(tmp_path):
    info = export_model("xfyz", tmp_path / "model", build_it=False)
    _compare("model_xfyz", info.path, info.name)


@pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("make") is None,
                    reason="needs gcc and make")
def test_golden_configuration_compiles_and_converges(measurements, tmp_path):
    """The golden configuration builds with -Wall -Werror and its example program
    converges on the simulated data."""
    info = export_solver("xfyz", pd.read_csv(measurements), tmp_path / "solver",
                         cflags="-O2 -Wall -Werror")
    out = tmp_path / "out"
    proc = subprocess.run([str(info.example), str(measurements), str(out)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    status = dict(line.split(" = ", 1) for line in (out / "status.txt").read_text().splitlines())
    assert status["converged"] == "1" and status["status_text"] == "converged"
    assert 0.5 < float(status["chi2_per_dof"]) < 2.0
