"""studies/datum in its smoke mode: the default (minimal) datum matches the plain
least-squares reference on independent data, and imposing every ISO 230 condition does not
when the tool offset varies."""
from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "studies" / "datum"
sys.path.insert(0, str(ROOT / "studies"))
import readme_tables as rt  # noqa: E402


# The study's whole smoke run: the default datum against the reference fit and an imposed
# datum that forbids what the data see are checked in the default suite on single cases
# (tests/test_datum.py, tests/test_independent_truth.py); CI runs this one (-m slow).
@pytest.mark.slow
def test_datum_study_smoke(capsys):
    spec = importlib.util.spec_from_file_location("datum_study", STUDY / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    before = rt.folder_state(STUDY)
    df = mod.main(["--smoke"])
    out = Path(re.search(r"results in (\S+)", capsys.readouterr().out).group(1))
    assert rt.folder_state(STUDY) == before           # nothing written into the repository
    assert out.is_file() and ROOT not in out.resolve().parents
    mini = df[df["mode"] == "minimal"]
    # every option of the minimal datum gives the reference fit's field and residuals
    for _, r in mini.iterrows():
        assert r["field_error_um"] == pytest.approx(r["reference_fit_field_error_um"],
                                                    rel=0.05, abs=0.01)
        assert 0.7 < r["chi2_per_dof"] < 1.3
    # with four tool offsets, imposing every ISO 230 condition constrains what the data see
    forced = df[(df["mode"] == "impose-all") & (df["datum"] == "iso230")
                & (df["tool_offsets"] == 4)].iloc[0]
    best = mini[mini["tool_offsets"] == 4]["field_error_um"].max()
    assert forced["field_error_um"] > 2 * best
    assert forced["chi2_per_dof"] > 1.3
    # the README's table is run.py's table of the committed 5-seed run, figure for figure,
    # and the smoke run's table has the same rows and imposes the same conditions (exact
    # counts); its field errors and chi2 are one seed's, not the 5 seeds' means: not compared
    committed = mod.results_table(pd.read_csv(STUDY / "results.csv"))
    assert rt.check_readme_against(STUDY / "README.md", {"results": committed},
                                   key_cols=3, tolerance=0.0) == []
    smoke = json.loads((out.parent / "tables.json").read_text())
    col = "conditions imposed / candidates"
    assert rt.check_readme_against(
        STUDY / "README.md", smoke, key_cols=3,
        tolerance={"results": {c: None for c in (
            "field error um, mean / max", "chi2/dof, mean (max)", "reference fit um, mean",
            "seeds")} | {col: 0.0}}) == []
