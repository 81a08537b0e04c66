"""Every study's smoke run writes only into a temporary folder unless --out is given, and
the README table helpers (studies/readme_tables.py) round-trip.

The smoke runs of paper000, paper001, paper002, paper003 and datum are run and checked by
their own tests (tests/test_study_*.py); coverage is too slow to run twice in the suite, so
for every study this checks that its run.py resolves the smoke output folder through
``readme_tables.output_folder``."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


def test_every_smoke_run_resolves_a_temporary_folder():
    scripts = sorted((ROOT / "studies").glob("*/run.py"))
    assert len(scripts) >= 6
    for s in scripts:
        text = s.read_text(encoding="utf-8")
        if "--smoke" in text:
            assert "output_folder(" in text, f"{s}: --smoke without output_folder()"
            assert "results_smoke" not in text, s


def test_output_folder(tmp_path):
    a = rt.output_folder(None, True, tmp_path / "default", "x")
    b = rt.output_folder(None, True, tmp_path / "default", "x")
    assert a != b and a.is_dir() and ROOT not in a.resolve().parents
    assert rt.output_folder(tmp_path / "o", True, tmp_path / "d", "x") == tmp_path / "o"
    assert rt.output_folder(None, False, tmp_path / "d", "x") == tmp_path / "d"


def test_readme_tables_round_trip(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("text\n<!-- table: t1 -->\n| k | v |\n|---|---|\n| a | 1 |\n"
                      "<!-- /table -->\nmore\n", encoding="utf-8")
    new = {"t1": "| k | v |\n|---|---|\n| a | 2 |", "t2": "| k |\n|---|\n| z |"}
    assert rt.check_readme_against(readme, new) == []
    assert rt.update_readme(readme, new) == ["t1"]
    assert rt.readme_tables(readme.read_text())["t1"].endswith("| a | 2 |")
    assert "more" in readme.read_text()
    bad = {"t1": "| k | w |\n|---|---|\n| b | 2 |"}
    assert len(rt.check_readme_against(readme, bad)) == 2


def test_readme_values_compared_with_tolerance(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("<!-- table: t -->\n| k | exact | mc | note |\n|---|---|---|---|\n"
                      "| a | 55 of 61 | 5.30 | [100.7, 111.1] |\n<!-- /table -->\n",
                      encoding="utf-8")

    def run(exact, mc, note, tol):
        head = "| k | exact | mc | note |\n|---|---|---|---|\n"
        new = {"t": f"{head}| a | {exact} | {mc} | {note} |"}
        return rt.check_readme_against(readme, new, tolerance=tol)

    same = ("55 of 61", "5.30", "[100.7, 111.1]")
    assert run(*same, None) == [] and run(*same, 0.0) == []
    # keys only without a tolerance (the helper's old behaviour)
    assert run("58 of 64", "9.9", "x", None) == []
    # as printed: a different rank is a difference; a rounding of the same figure is not
    assert len(run("58 of 64", "5.30", "[100.7, 111.1]", 0.0)) == 1
    assert run("55 of 61", "5.3", "[100.7, 111.1]", 0.0) == []
    # per column: the Monte Carlo figure within 15 %, the interval within 0.5 absolute
    tol = {"t": {"mc": 0.15, "note": (0.0, 0.5)}}
    assert run("55 of 61", "5.71", "[100.3, 111.1]", tol) == []
    bad = run("55 of 61", "6.5", "[99.0, 111.1]", tol)
    assert len(bad) == 2 and "'mc'" in bad[0] and "'note'" in bad[1]
    # a column left out, and text that differs
    assert run("55 of 61", "6.5", "[100.7, 111.1]", {"t": {"mc": None}}) == []
    assert len(run("55 of 61", "5.30", "(100.7, 111.1)", tol)) == 1
