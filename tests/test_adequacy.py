"""Model adequacy (volcal.analysis.adequacy), its place in `volcal identify`, the report
and result.json; the default plan of a model with rotary axes; the volumetric summary
over the rotary axes' travel.

Small simulated data sets on model xfyz (Legendre degree 2, 4 tool offsets, 4 stations)
are identified once per module: the right budget, a truth with an error motion of X the
model cannot follow, blunders, and a budget three times too small.
"""
from __future__ import annotations

import json
import logging
import warnings

import numpy as np
import pandas as pd
import pytest

import volcal.cli.main
from volcal.analysis.adequacy import assess, assess_residuals, chi2_interval
from volcal.analysis.identify import identify
from volcal.measurement.plans import default_plan, default_stations, grid_plan, summary_grid
from volcal.measurement.simulate import (
    draw_true_parameters,
    max_volumetric_error_um,
    parse_tools,
    simulate,
)
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.outputs.results import load_result, save_result, volumetric_grid_table

TOOLS = np.array([[0, 0, 0], [0, 0, -100.0], [80, 0, -100.0], [0, 80, -100.0]])
DEFAULT_TOOLS = "0,0,0;0,0,-100;80,0,-100;0,80,-100"  # those of `volcal simulate`


@pytest.fixture(scope="module")
def xfyz(tmp_path_factory):
    """A right simulation (degree 2 truth, paper 002's budget) and its identification."""
    tmp = tmp_path_factory.mktemp("adequacy")
    machine = Machine.from_model("xfyz")
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 2))
    theta = draw_true_parameters(machine, em, np.random.default_rng(5), 30.0)
    plan = grid_plan(machine.spec, {"X": 9, "Y": 3, "Z": 3})
    stations = default_stations(machine.spec, 4, seed=5, tools=TOOLS)
    sim = simulate(machine, em, theta, stations, plan, TOOLS, "paper002", 5)
    res = identify(machine, sim.measurements, error_model=em)
    return {"tmp": tmp, "machine": machine, "em": em, "theta": theta, "plan": plan,
            "stations": stations, "sim": sim, "res": res}


def _identify(case, measurements):
    return identify(case["machine"], measurements, error_model=case["em"])


# --------------------------------------------------------------------------------------
# the verdict on identifications


def test_a_fit_with_the_right_budget_passes(xfyz):
    ad = assess(xfyz["res"])
    lo, hi = ad.interval
    assert ad.adequate and ad.verdict == "fits" and ad.causes == ()
    assert lo < 1.0 < hi and lo <= ad.chi2_per_dof <= hi
    assert ad.chi2_per_dof == pytest.approx(xfyz["res"].conditions["chi2_per_dof"])
    # dof = readings - free parameters + constraints
    n = len(xfyz["sim"].measurements)
    assert n - xfyz["em"].n_params - 4 * 4 <= ad.dof < n
    assert (lo, hi) == pytest.approx(chi2_interval(ad.dof))
    assert ad.n_stations == 4 and ad.warnings == ()
    assert {s.axis for s in ad.structure if s.kind == "axis"} == {"X", "Y", "Z"}
    # tool offsets, stations and time are tested too
    assert {s.kind for s in ad.structure} == {"axis", "tool_offset", "station", "time"}
    assert all(s.p_value > 1e-3 for s in ad.structure)
    assert ad.outliers["n_beyond_5_robust"] == 0
    assert 0.9 < ad.budget_factor < 1.1
    assert "the model fits" in ad.message
    assert assess(xfyz["res"]) is ad  # computed once per result


def test_structure_against_one_axis_is_flagged_naming_that_axis(xfyz):
    """The truth's positioning error of X has a degree-6 term the degree-2 model cannot
    follow: the residuals are structured against X."""
    machine = xfyz["machine"]
    em6 = ErrorModel(machine.spec, {"EXX": ErrorForm("poly", 6)},
                     default=ErrorForm("poly", 2))
    theta = draw_true_parameters(machine, em6, np.random.default_rng(5), 30.0)
    theta[em6.param_names.index("EXX_6")] = 4e-3  # mm: 4 um P6 wiggle
    sim = simulate(machine, em6, theta, xfyz["stations"], xfyz["plan"], TOOLS, "paper002", 6)
    ad = assess(_identify(xfyz, sim.measurements))
    assert not ad.adequate and ad.chi2_per_dof > ad.interval[1]
    assert ad.verdict == "does_not_fit"
    assert ad.cause == "basis"  # the basis, not the budget, and no scaling offered
    assert ad.causes[0].numbers["axis"] == "X" and ad.strongest_axis == "X"
    assert "budget" not in ad.cause_kinds
    assert "--scale-covariance" not in ad.message and "unstructured" not in ad.message
    assert "--degree auto" in ad.causes[0].text
    assert ad.structure[0].p_value < 1e-6
    assert ad.structure[0].explained_share > 0.3
    assert "the basis of axis X" in ad.message and "p < 1e-06" in ad.message


def test_outliers_are_flagged_as_outliers(xfyz):
    meas = xfyz["sim"].measurements.copy()
    bad = np.arange(7, len(meas), 97)  # 1 % of the readings, 50 um (about 100 sigma) off
    meas.loc[bad, "length"] += 0.05
    ad = assess(_identify(xfyz, meas))
    assert not ad.adequate
    assert ad.cause == "outliers"
    o = ad.outliers
    assert o["n_beyond_5_robust"] >= len(bad) and o["n_beyond_5_sigma"] >= len(bad)
    assert o["max_abs"] > 50 and o["excess_kurtosis"] > 10
    assert ad.causes[0].numbers["n_beyond_5_robust"] == o["n_beyond_5_robust"]
    # what result.json keeps reads back as the same verdict (causes, structure and all)
    from volcal.analysis.adequacy import Adequacy

    assert Adequacy.from_dict(json.loads(json.dumps(ad.to_dict()))) == ad


@pytest.mark.parametrize("scale", [1 / 3, 3.0])
def test_a_budget_off_by_three_is_flagged_as_budget(xfyz, scale):
    """The readings' sigma three times too small (chi2/dof ~ 9) or too large (~ 1/9)."""
    meas = xfyz["sim"].measurements.copy()
    meas["sigma"] *= scale
    ad = assess(_identify(xfyz, meas))
    assert [c.kind for c in ad.causes] == ["budget"]
    assert ad.budget_factor == pytest.approx(1 / scale, rel=0.15)
    assert ad.causes[0].numbers["factor"] == pytest.approx(ad.budget_factor)
    if scale < 1:
        assert ad.verdict == "does_not_fit" and not ad.adequate
        assert "too small" in ad.message and "--scale-covariance" in ad.message
    else:  # a pessimistic budget: the model fits, the uncertainties are conservative
        assert ad.verdict == "budget_pessimistic" and ad.adequate
        assert "NOT" not in ad.message and "pessimistic" in ad.message
        assert "conservative by a factor of about 3" in ad.message


# --------------------------------------------------------------------------------------
# the statistics on their own


def _synthetic(n=6000, seed=0):
    rng = np.random.default_rng(seed)
    pos = pd.DataFrame({"X": rng.choice(np.linspace(0, 800, 9), n),
                        "C": rng.choice(np.arange(-180, 180, 30.0), n)})
    st = rng.integers(0, 6, n)
    return rng, pos, st, rng.normal(size=n)


def test_structure_in_synthetic_residuals_names_the_rotary_axis():
    rng, pos, st, z = _synthetic()
    sign = np.array([1.0, -1.0, 0.6, -0.8, 0.9, -0.3])[st]  # beam directions differ
    z = z + 1.2 * sign * np.sin(4 * np.deg2rad(pos["C"].to_numpy()))
    ad = assess_residuals(z, len(z) - 100, stations=st, positions=pos, units=["mm", "deg"])
    assert ad.cause == "basis" and ad.strongest_axis == "C"
    assert ad.structure[0].unit == "deg" and ad.structure[0].n_bins == 12
    x = next(s for s in ad.structure if s.axis == "X")
    assert x.p_value > 1e-6 and not x.significant


def test_a_single_station_draws_a_warning():
    _, pos, _, z = _synthetic()
    ad = assess_residuals(z, len(z), stations=np.full(len(z), "S1"), positions=pos)
    assert ad.n_stations == 1 and ad.adequate
    assert len(ad.warnings) == 1 and "single station" in ad.warnings[0]
    ad6 = assess_residuals(z, len(z), stations=np.arange(len(z)) % 6, positions=pos)
    assert ad6.warnings == ()


def test_rejected_readings_are_left_out():
    _, pos, st, z = _synthetic()
    z = z.copy()
    z[:5] = 1e3
    rej = np.zeros(len(z), bool)
    rej[:5] = True
    ad = assess_residuals(z, len(z) - 5, stations=st, positions=pos, rejected=rej)
    assert ad.adequate and ad.n_readings == len(z) - 5


# --------------------------------------------------------------------------------------
# report, result.json, plot, terminal


def test_the_report_and_result_json_hold_the_verdict(xfyz, tmp_path):
    out = save_result(xfyz["res"], tmp_path / "ok")
    report = (out / "report.md").read_text()
    assert "## Model adequacy" in report and "model adequacy" in report
    assert "The model fits the data within their uncertainty" in report
    assert "(residuals_vs_axes.png)" in report
    assert (out / "residuals_vs_axes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((out / "result.json").read_text())
    assert doc["adequacy"]["verdict"] == "fits" and doc["adequacy"]["adequate"]
    assert doc["adequacy"]["cause_kinds"] == []
    assert len(doc["adequacy"]["interval"]) == 2
    assert load_result(out).adequacy["verdict"] == "fits"

    meas = xfyz["sim"].measurements.copy()
    meas["sigma"] /= 3
    out = save_result(_identify(xfyz, meas), tmp_path / "bad", plots=False)
    report = (out / "report.md").read_text()
    assert "WARNING: the model does not fit the data" in report
    assert "**budget**" in report and "**does NOT fit" in report
    assert "residuals_vs_axes.png" not in report
    assert json.loads((out / "result.json").read_text())["adequacy"]["causes"][0]["kind"] \
        == "budget"


def test_identify_warns_on_the_terminal_when_the_model_does_not_fit(xfyz, tmp_path, caplog,
                                                                    capsys, monkeypatch):
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.cli.commands.identify"])
    meas = xfyz["sim"].measurements.copy()
    meas["sigma"] /= 3
    data = tmp_path / "m.csv"
    meas.to_csv(data, index=False)
    with caplog.at_level(logging.WARNING):
        assert volcal.cli.main.main(["identify", "--model", "xfyz", "--data", str(data),
                                "--degree", "2", "--no-plots",
                                "--out", str(tmp_path / "r")]) == 0
    warns = [r for r in caplog.records if r.levelno == logging.WARNING
             and "does NOT fit" in r.getMessage()]
    assert len(warns) == 1 and "budget" in warns[0].getMessage()
    printed = capsys.readouterr().out
    assert "model adequacy           does NOT fit" in printed
    assert "likely cause: budget too small" in printed
    assert "grid over X, Y, Z, tool offset (0, 0, 0) mm" in printed


# --------------------------------------------------------------------------------------
# the default plan of a model with rotary axes


def test_the_default_plan_of_a_model_without_rotary_axes_is_the_grid():
    for m in ("xfyz", "mcv754_wxyzt"):
        pd.testing.assert_frame_equal(default_plan(m), grid_plan(m))
    assert len(default_plan("xfyz", degree=5)) == 7 ** 3


@pytest.mark.parametrize("model", ["trunnion_ac", "head_bc"])
def test_the_5_axis_default_plan_identifies_everything_but_the_gauge(model):
    """The default plan (with `volcal simulate`'s default tool offsets and stations)
    leaves only the rigid motion between station frame and machine frame undetermined:
    no error parameter is unidentifiable."""
    from volcal.outputs.analysis_report import analyze_plan

    machine = Machine.from_model(model)
    spec = machine.spec
    plan = default_plan(spec)
    assert 250 <= len(plan) <= 400  # simulate + identify in seconds
    for a in spec.axes:  # every axis over its whole travel
        v = plan[a.name]
        assert v.min() == pytest.approx(a.travel[0]) or (a.is_rotary and v.min() < -150)
        assert v.max() == pytest.approx(a.travel[1]) or (a.is_rotary and v.max() >= 150)
        if a.is_rotary:
            assert v.nunique() >= (12 if a.travel[1] - a.travel[0] >= 360 else 7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = analyze_plan(machine, plan, default_stations(spec, 6, seed=1),
                           parse_tools(DEFAULT_TOOLS), "paper002",
                           eval_points=grid_plan(spec, 2))
    assert [d.line() for d in rep.unidentifiable_errors] == []
    assert all(d.kind == "gauge" for d in rep.null)
    assert sum(d.dimension for d in rep.null) == 6  # the rigid motion of the station set
    assert rep.identifiable[:rep.n_theta].all()


# --------------------------------------------------------------------------------------
# the volumetric summary covers the rotary axes


def test_the_volumetric_summary_of_a_5_axis_model_covers_rotary_poses():
    machine = Machine.from_model("trunnion_ac")
    em = ErrorModel(machine.spec)
    theta = draw_true_parameters(machine, em, np.random.default_rng(1), 60.0)
    g = summary_grid(machine.spec)
    assert g["C"].nunique() == 8 and g["A"].nunique() == 6
    assert 0.0 in set(g["C"]) and 0.0 in set(g["A"])  # the reference is among them
    # the simulator's headline figure spans the rotary axes' travel
    assert max_volumetric_error_um(machine, em, theta) == pytest.approx(60.0, rel=1e-9)
    at_ref = grid_plan(machine.spec, {"C": 1, "A": 1, "X": 5, "Y": 5, "Z": 5})
    ref_max = max_volumetric_error_um(machine, em, theta, at_ref)
    # the result folder's grid (first-order model) too
    grid = volumetric_grid_table(machine, em, theta)
    assert grid["C"].nunique() == 8 and grid["A"].nunique() == 6
    assert grid["norm_um"].max() == pytest.approx(60.0, rel=0.05)
    assert grid["norm_um"].max() > 1.2 * ref_max
    old = volumetric_grid_table(machine, em, theta, rotary=False)
    assert old["C"].nunique() == 1 and old["norm_um"].max() == pytest.approx(ref_max,
                                                                              rel=0.05)


def test_one_biased_tool_offset_among_fifteen_is_named():
    """Fifteen tool offsets (more than the position bins of an axis), one of which reads
    0.6 sigma long at every station: the structure against the tool offset groups every
    offset on its own and names that one; without the bias nothing is flagged."""
    from volcal.analysis.adequacy import assess_residuals

    rng = np.random.default_rng(12)
    keys = [f"0,{10 * k},{-50 - 5 * k}" for k in range(15)]
    n_per = 60
    tools = np.repeat(np.arange(15), 4 * n_per)
    stations = np.tile(np.repeat(np.arange(4), n_per), 15)
    z = rng.standard_normal(len(tools))
    names = np.array(keys, dtype=object)[tools]
    calm = assess_residuals(z, stations=stations, tools=names)
    s0 = next(s for s in calm.structure if s.kind == "tool_offset")
    assert s0.n_bins == 15 and not s0.significant and s0.group == ""
    assert calm.verdict == "fits"
    z = z + 0.6 * (tools == 9)  # the offset (0, 90, -95) mm is wrong
    ad = assess_residuals(z, stations=stations, tools=names)
    s = next(s for s in ad.structure if s.kind == "tool_offset")
    assert s.significant and s.n_bins == 15
    assert s.group.startswith("(0, 90, -95) mm")
    assert ad.verdict == "does_not_fit" and ad.cause == "tool_offset"
    assert "most of all at tool offset (0, 90, -95) mm" in ad.causes[0].text
    assert "(0, 90, -95) mm" in ad.causes[0].short


def test_groupings_by_hashing_and_counting_are_np_uniques():
    """The adequacy test groups readings by hashing and counting (linear in the readings;
    np.unique sorts): the same distinct values in the same order and the same codes as
    np.unique gives, on texts, mixed objects, integer cells and positions with -0.0."""
    from volcal.analysis.adequacy import _dense, _factorize, position_bins

    rng = np.random.default_rng(11)
    texts = np.array(["LT2", "LT10", "LT1", "b", "A"], dtype=object)[rng.integers(0, 5, 500)]
    mixed = np.array([1, "1", 2.5, 1], dtype=object)
    for values in (texts, texts.astype(str), rng.integers(0, 40, 500), mixed):
        names, codes = _factorize(values)
        exp_names, exp_codes = np.unique(np.asarray(values).astype(str), return_inverse=True)
        np.testing.assert_array_equal(names, exp_names)
        np.testing.assert_array_equal(codes, exp_codes.ravel())
    for cells in (rng.integers(0, 50, 1000) * 7, np.array([5, 5, 0, 9_000_000, 5])):
        codes, counts = _dense(cells)
        exp = np.unique(cells, return_inverse=True)[1].ravel()
        np.testing.assert_array_equal(codes, exp)
        np.testing.assert_array_equal(counts, np.bincount(exp))
    v = rng.choice([-0.0, 0.0, 10.0, 20.5], 300)
    code, centres = position_bins(v)
    np.testing.assert_array_equal(centres, [0.0, 10.0, 20.5])
    np.testing.assert_array_equal(code, np.searchsorted(centres, v))
