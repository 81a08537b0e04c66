"""Gauge, unidentifiable and imposed kept apart in the tables, plots and reports.

* ``volcal analyze``: the singular values below the rank tolerance are labelled gauge
  (rigid motion of the station set, held by the datum) or unidentifiable, in
  singular_values.csv and singular_values.png, with the counts of the null space;
* ``parameters.csv``: parameters the datum sets to zero carry ``imposed = True`` (the
  datum's single-parameter conditions, u = 0), the others do not;
* a single tool offset: the result names every parameter it leaves out, says why and what
  to measure, in the terminal warning, report.md and the HTML report.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pandas as pd
import pytest

import volcal.cli.main
from volcal.analysis.identify import identify
from volcal.base.threads import blas_threads
from volcal.measurement.simulate import example
from volcal.outputs import html_report as hr
from volcal.outputs.analysis_report import (
    analyze_plan,
    plot_singular_values,
    singular_value_kinds,
)
from volcal.outputs.results import load_result, save_result


@pytest.fixture(scope="module")
def ex():
    return example("mcv754")


@pytest.fixture(scope="module")
def one_tool(ex, tmp_path_factory):
    """The example's readings at the spindle reference point only, identified and saved."""
    tmp = tmp_path_factory.mktemp("one_tool")
    sim = ex.simulate()
    m = sim.measurements
    m = m[(m["tool_x"] == 0) & (m["tool_y"] == 0) & (m["tool_z"] == 0)].reset_index(drop=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the single tool offset is warned about
        res = identify(ex.machine, m, error_model=ex.error_model)
    data = tmp / "one_tool.csv"
    m.to_csv(data, index=False)
    return {"res": res, "out": save_result(res, tmp / "r", plots=False), "data": data}


def test_analyze_labels_gauge_and_unidentifiable_singular_values_apart(ex, tmp_path):
    with blas_threads(1):
        rep = analyze_plan(ex.machine, ex.plan, ex.stations, np.zeros((1, 3)), ex.budget,
                           error_model=ex.error_model)
    kind = singular_value_kinds(rep)
    n_gauge = sum(d.dimension for d in rep.null if d.kind == "gauge")
    n_unid = sum(d.dimension for d in rep.unidentifiable_errors)
    assert (n_gauge, n_unid) == (6, 12)
    assert list(pd.Series(kind).value_counts().sort_index().items()) == [
        ("determined", rep.rank), ("gauge", n_gauge), ("unidentifiable", n_unid)]
    # the gauge holds the smallest values (a rigid motion changes no reading at all)
    s = rep.singular_values
    assert s[kind == "gauge"].max() <= s[kind == "unidentifiable"].min()
    fig = plot_singular_values(rep, tmp_path / "sv.png")
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any(t.startswith("gauge (6:") for t in labels), labels
    assert any(t.startswith("unidentifiable (12:") for t in labels), labels
    assert not any("below tolerance (unidentifiable)" in t for t in labels)
    # the parameter table: the frame and the stations' gauge part apart from errors the
    # data do not see, and from what the datum imposes
    par = rep.parameters()
    assert set(par.loc[par["kind"] == "frame", "status"]) == {"gauge"}
    err = par[par["kind"] == "error"]
    assert (err["status"] == "unidentifiable").sum() == (~err["identifiable"]).sum() > 0
    assert {n.split("_")[0] for n in err.loc[err["status"] == "unidentifiable", "name"]} == {
        "ECY", "EAZ", "EBZ", "ECZ"}
    imposed = err[err["status"] == "imposed"]
    assert len(imposed) and (imposed["u"] < 1e-9).all() and (imposed["value"] == 0).all()
    assert "gauge" not in set(err["status"])
    rep.save(tmp_path / "an", plots=False)
    csv = pd.read_csv(tmp_path / "an" / "singular_values.csv")
    assert (csv["kind"] == "gauge").sum() == 6 and (csv["kind"] == "unidentifiable").sum() == 12
    assert (csv.loc[csv["kind"] == "determined", "above_tolerance"]).all()


def test_parameters_csv_marks_what_the_datum_imposes(one_tool):
    res = one_tool["res"]
    par = pd.read_csv(one_tool["out"] / "parameters.csv")
    assert list(par.columns) == ["name", "value", "unit", "u", "identifiable", "imposed"]
    datum = pd.read_csv(one_tool["out"] / "datum.csv")
    # the single-parameter conditions of the datum ("EX0T = 0"), imposed
    single = {c.split(" = 0")[0] for c in datum.loc[datum["imposed"], "condition"]
              if c.endswith(" = 0")}
    imposed = set(par.loc[par["imposed"], "name"])
    assert imposed and imposed == single & set(par["name"])
    assert (par.loc[par["imposed"], "u"] == 0).all()
    assert (par.loc[par["imposed"], "value"] == 0).all()
    # parameters the data determine are not marked, unidentifiable ones neither
    free = par[par["identifiable"] & ~par["imposed"]]
    assert (free["u"] > 0).all()
    assert not (par["imposed"] & ~par["identifiable"]).any()
    assert load_result(one_tool["out"]).parameters()["imposed"].tolist() == par[
        "imposed"].tolist()
    assert res.parameters()["imposed"].sum() == len(imposed)


def test_a_single_tool_offset_names_every_parameter_it_leaves_out(one_tool, tmp_path,
                                                                  monkeypatch, caplog):
    res = one_tool["res"]
    unid = [n for n, ok in zip(res.error_model.param_names, res.identifiable) if not ok]
    assert {n.split("_")[0] for n in unid} == {"ECY", "EAZ", "EBZ", "ECZ"}
    why = res.unidentifiable_explanation()
    assert why["cause"] == "single_tool_offset" and why["parameters"] == unid
    assert all(n in why["text"] for n in unid) and "tool offsets" in why["text"]
    # the report: why and what to measure, in Markdown and in the HTML hand-over
    md = (one_tool["out"] / "report.md").read_text()
    assert "**Why, and what to measure:**" in md and "three or more tool offsets" in md
    html = hr.html_report(one_tool["out"], plots=False)
    box = html.split('id="unidentifiable-why"')[1].split("</p>")[0]
    assert all(n in box for n in unid) and "spindle orientations" in box
    # the terminal: one warning naming every one of them
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.cli.commands.identify"])
    with caplog.at_level(logging.WARNING):
        assert volcal.cli.main.main(["identify", "--model", "mcv754_wxyzt", "--data",
                                     str(one_tool["data"]), "--no-plots", "--out",
                                     str(tmp_path / "r")]) == 0
    said = [r.getMessage() for r in caplog.records if "Left out" in r.getMessage()]
    assert len(said) == 1 and all(n in said[0] for n in unid)


def test_every_parameter_identifiable_needs_no_explanation(ex):
    sim = ex.simulate()
    res = identify(ex.machine, sim.measurements, error_model=ex.error_model)
    assert res.identifiable.all() and res.unidentifiable_explanation() is None
