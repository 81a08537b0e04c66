"""``volcal models`` and ``volcal show``: listings, formats, errors, and the printed
first-order formula checked against the compiled Jacobian."""
from __future__ import annotations

import csv
import io
import shutil
import subprocess
import sys

import numpy as np
import pytest

from volcal.cli.main import main
from volcal.model.machine import Machine
from volcal.model.spec import bundled_models

# independent counts: 6 component errors per axis; 3 squareness errors for three linear
# axes; 4 location errors (2 offsets, 2 tilts) per rotary axis (ISO 230-7)
# error quantities: those of the axes plus the tool's zero position and orientation (6)
EXPECTED = {"mcv754_wxyzt": (3, 27), "xfyz": (3, 27), "head_bc": (5, 47),
            "trunnion_ac": (5, 47)}


def run(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def csv_sections(text: str) -> dict[str, list[dict[str, str]]]:
    """Split 'volcal show --format csv' output (# name lines between tables)."""
    out: dict[str, list[str]] = {}
    current = None
    for line in text.splitlines():
        if line.startswith("# "):
            current = line[2:].strip()
            out[current] = []
        elif line.strip():
            out[current].append(line)
    return {k: list(csv.DictReader(io.StringIO("\n".join(v)))) for k, v in out.items()}


def test_models_text(capsys):
    rc, out, _ = run(capsys, "models")
    assert rc == 0
    lines = out.splitlines()
    assert lines[0].split()[:4] == ["name", "n_axes", "n_errors", "chain"]
    for name in bundled_models():
        row = next(ln for ln in lines if ln.split()[0] == name)
        if name in EXPECTED:
            assert row.split()[1:3] == [str(v) for v in EXPECTED[name]]
    assert "W-C-A-F-X-Y-Z-T" in out  # trunnion chain: workpiece side C, A


def test_models_csv(capsys):
    rc, out, _ = run(capsys, "models", "--format", "csv")
    assert rc == 0
    rows = {r["name"]: r for r in csv.DictReader(io.StringIO(out))}
    assert set(rows) == set(bundled_models())
    for name, (n_axes, n_err) in EXPECTED.items():
        assert (int(rows[name]["n_axes"]), int(rows[name]["n_errors"])) == (n_axes, n_err)
    assert "MCV 754" in rows["mcv754_wxyzt"]["description"]


def test_show_text_mcv754(capsys):
    rc, out, _ = run(capsys, "show", "mcv754_wxyzt")
    assert rc == 0
    assert "chain W-F-X-Y-Z-T" in out
    assert "0 .. 754 mm" in out and "-550 .. 0 mm" in out
    assert "µm" in out and "µrad" in out
    # paper 000 eq. (2)-(4) terms, in volcal's names (docs/conventions.md)
    assert "Δx = + EXX" in out
    for term in ("- Y*EC0Y", "+ Z*EB0Z", "- Z*EA0Z", "+ (Z + tool_z)*EBX",
                 "- (Y + tool_y)*ECX", "+ (Y + tool_y)*EAX", "- tool_x*EBZ"):
        assert term in out, term
    assert "no first-order effect" not in out


def test_show_csv_sections(capsys):
    rc, out, _ = run(capsys, "show", "trunnion_ac", "--format", "csv")
    assert rc == 0
    sec = csv_sections(out)
    assert list(sec) == ["axes", "errors", "volumetric"]
    axes = {r["axis"]: r for r in sec["axes"]}
    assert axes["A"]["unit"] == "deg" and axes["A"]["travel_min"] == "-120"
    assert axes["A"]["center_z_mm"] == "-100" and axes["X"]["center_x_mm"] == ""
    errs = {r["name"]: r for r in sec["errors"]}
    assert len(errs) == 47  # 41 of the axes and 6 of the tool
    assert (errs["EX0C"]["unit"], errs["EX0C"]["report_unit"]) == ("mm", "um")
    assert (errs["EAA"]["unit"], errs["EAA"]["report_unit"]) == ("rad", "urad")
    assert {r["component"] for r in sec["volumetric"]} == {"dx", "dy", "dz"}


def test_show_single_section_is_plain_csv(capsys):
    rc, out, _ = run(capsys, "show", "xfyz", "--format", "csv", "--section", "errors")
    assert rc == 0
    assert not out.startswith("#")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["name"] for r in rows][:3] == ["EXX", "EYX", "EZX"]


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_printed_formula_equals_compiled_jacobian(capsys, name, tmp_path, monkeypatch):
    """The coefficients 'show' prints, evaluated at random poses, equal the columns of the
    compiled first-order Jacobian (so the printout is the model, not an approximation)."""
    import sympy as sp

    monkeypatch.setenv("VOLCAL_CACHE_DIR", str(tmp_path))
    rc, out, _ = run(capsys, "show", name, "--format", "csv", "--section", "volumetric")
    assert rc == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    m = Machine.from_model(name)
    symbols = {a.name: sp.Symbol(a.name) for a in m.spec.axes}
    symbols.update({f"tool_{c}": sp.Symbol(f"tool_{c}") for c in "xyz"})
    units = {s.name: s.unit for s in m.errors}
    rng = np.random.default_rng(11)
    for _ in range(3):
        q = m.axis_to_internal(np.array([rng.uniform(*a.travel) for a in m.spec.axes]))
        t = rng.uniform(-100, 100, 3)
        J = np.asarray(m["tool_point"](q, t, np.zeros(m.n_errors))[2])
        printed = np.zeros_like(J)
        values = {symbols[a.name]: v for a, v in zip(m.spec.axes, q)}
        values.update({symbols[f"tool_{c}"]: v for c, v in zip("xyz", t)})
        for r in rows:
            assert r["error_unit"] == units[r["error"]]
            coef = sp.sympify(r["coefficient"], locals=symbols)
            printed["xyz".index(r["component"][1]), m.error_names.index(r["error"])] = \
                float(coef.xreplace(values))
        np.testing.assert_allclose(printed, J, rtol=1e-12, atol=1e-9)


def test_show_model_file_path(capsys, tmp_path):
    p = tmp_path / "my_machine.toml"
    shutil.copy(bundled_models()["xfyz"], p)
    rc, out, _ = run(capsys, "show", str(p), "--section", "axes")
    assert rc == 0
    assert "workpiece" in out and "0 .. 800 mm" in out


def test_show_unknown_model(capsys):
    rc, out, err = run(capsys, "show", "no_such_model")
    assert rc == 2
    assert "no bundled model named 'no_such_model'" in err and "mcv754_wxyzt" in err
    assert "Traceback" not in err


def test_show_bad_model_file(capsys, tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('name = "bad"\n[[axis]]\nname = "X"\nkind = "spiral"\ndirection = "+x"\n'
                 'branch = "tool"\ntravel = [0.0, 1.0]\n', encoding="utf-8")
    rc, out, err = run(capsys, "show", str(p))
    assert rc == 2 and out == ""
    assert str(p) in err and "'kind'" in err and "spiral" in err and "Traceback" not in err


def test_models_listing_does_not_load_sympy():
    code = ("import sys; from volcal.cli.main import main; rc = main(['models']); "
            "assert rc == 0; assert 'sympy' not in sys.modules, 'sympy imported'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_installed_volcal_help():
    exe = shutil.which("volcal")
    assert exe, "the volcal console script is not installed"
    r = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "models" in r.stdout and "show" in r.stdout
    r = subprocess.run([exe, "show", "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "MODEL" in r.stdout
