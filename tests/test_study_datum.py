"""studies/datum in its smoke mode: the default (minimal) datum matches the plain
least-squares reference on independent data, and imposing every ISO 230 condition does not
when the tool offset varies."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def test_datum_study_smoke(tmp_path):
    path = Path(__file__).resolve().parents[1] / "studies" / "datum" / "run.py"
    spec = importlib.util.spec_from_file_location("datum_study", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    df = mod.main(["--smoke", "--out", str(tmp_path / "r.csv")])
    assert (tmp_path / "r.csv").is_file()
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
