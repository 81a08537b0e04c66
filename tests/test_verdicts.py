"""The adequacy verdict on data volcal did not generate (tests/indep_sim.py).

Each case has a known right answer: the truth is drawn by the independent simulator, the
noise is paper 002's budget (the one ``identify`` uses by default) or a quieter
instrument, and the strategy or basis is chosen to be right or wrong on purpose.

* right noise, right basis, joint: ``fits`` (the false-alarm side);
* noise below the budget, joint: ``budget_pessimistic``, exit code 0, no "does NOT fit";
* classic with four tool offsets: does not fit, a biased strategy named first, never the
  budget, never ``--scale-covariance``;
* a basis too poor (degree 1 for cubic error motions; a Fourier series on the full-turn
  C axis for an error that does not return after a turn): the basis of that axis is
  named, and following the advice printed (``--basis C=bspline:8``) makes the model fit.
"""

from __future__ import annotations

import functools
import json
import logging

import numpy as np
import pytest

import indep_sim as ind
import volcal.cli.main
from volcal.model.errors import parse_basis
from volcal.outputs.html_report import html_report
from volcal.workflow import identify

TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0], [0.0, 80.0, 60.0]])
#: an instrument about half as noisy as paper 002's budget says
QUIET = ind.Noise(
    laser_um=0.1,
    laser_per_m_um=0.15,
    rect_um=(0.3, 0.06, 0.02),
    repeat_um={"X": 0.5, "Y": 0.4, "Z": 0.2},
)


@functools.cache
def _three_axis(noise: str):
    """Cubic error motions on the 3-axis model, 4 tool offsets, 5 stations."""
    geom = ind.load_geometry("mcv754_wxyzt")
    truth = ind.draw_truth(geom, np.random.default_rng(21), "representable")
    plan = np.vstack([ind.grid(geom, {"X": 4, "Y": 3, "Z": 3}), ind.diagonals(geom, 4)])
    return ind.simulate(
        geom,
        truth,
        plan,
        TOOLS,
        np.random.default_rng(22),
        n_stations=5,
        noise=QUIET if noise == "quiet" else ind.Noise(),
    )


@functools.cache
def _five_axis_non_periodic():
    """trunnion_ac with cubic error motions of the full-turn C axis (a jump at +-180 deg:
    no Fourier series follows it), C at 12 angles."""
    geom = ind.load_geometry("trunnion_ac")
    rng = np.random.default_rng(31)
    truth = ind.draw_truth(geom, rng, "representable", full_turn="cubic", rotary_scale=1.5)
    lin = ind.grid(geom, {"X": 3, "Y": 3, "Z": 3}, {"A": 0.0, "C": 0.0})
    tet = np.array(
        [[-150, -125, -100], [150, -125, -350], [-150, 125, -350], [150, 125, -100]], float
    )
    rot = [
        [c, a, *p]
        for a in ind.linspace_travel(geom.axis("A"), 3)
        for c in ind.linspace_travel(geom.axis("C"), 12)
        for p in tet
    ]
    plan = np.vstack([lin, np.array(rot)])
    return ind.simulate(geom, truth, plan, TOOLS[:3], np.random.default_rng(32), n_stations=4)


def _no_budget_advice(ad):
    assert "budget" not in ad.cause_kinds, ad.message
    assert "--scale-covariance" not in ad.message
    assert "budget is too small" not in ad.message, ad.message
    assert ad.significant_structure and ad.verdict == "does_not_fit", ad.message


def test_a_right_fit_at_the_right_budget_fits():
    sim = _three_axis("paper002")
    ad = identify("mcv754_wxyzt", sim.measurements, sim.stations_start).adequacy
    assert ad.verdict == "fits" and ad.adequate and ad.causes == (), ad.message
    assert not ad.significant_structure
    assert "does NOT fit" not in ad.message and "fits" in ad.summary


def test_noise_below_the_budget_is_a_pessimistic_budget_with_exit_code_0(
    tmp_path, monkeypatch, caplog, capsys
):
    sim = _three_axis("quiet")
    data, stations = tmp_path / "m.csv", tmp_path / "s.csv"
    sim.measurements.to_csv(data, index=False)
    sim.stations_start.to_csv(stations, index=False)
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.cli.commands.identify"])
    args = ["identify", "--model", "mcv754_wxyzt", "--data", str(data), "--stations"]
    args += [str(stations), "--no-plots", "--out", str(tmp_path / "r")]
    with caplog.at_level(logging.WARNING):
        assert volcal.cli.main.main(args) == 0
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    printed = capsys.readouterr().out
    assert "model adequacy           fits; the budget is pessimistic" in printed
    assert "does NOT fit" not in printed and "INADEQUATE" not in printed
    ad = json.loads((tmp_path / "r" / "result.json").read_text())["adequacy"]
    assert ad["verdict"] == "budget_pessimistic" and ad["cause_kinds"] == ["budget"]
    assert ad["chi2_per_dof"] < ad["interval"][0]
    # the budget's sigmas are about twice the noise: conservative by about 2 (1 / factor)
    assert 1.3 < 1.0 / ad["budget_factor"] < 2.5
    assert "conservative by a factor of about" in ad["message"]
    report = (tmp_path / "r" / "report.md").read_text()
    assert "The model fits; the uncertainty budget is pessimistic" in report
    assert "WARNING" not in report.split("## Model adequacy")[1].split("\n## ")[0]
    # the HTML hand-over: a green banner, never the red one
    html = html_report(tmp_path / "r", plots=False)
    head = html.split('id="adequacy-verdict"')[0][-80:]
    banner = html.split('id="adequacy-verdict"')[1].split("</div>")[0]
    assert 'class="banner good"' in head and 'data-verdict="budget_pessimistic"' in banner
    assert "the uncertainty budget is pessimistic" in banner and "NOT" not in banner


def test_classic_with_tool_offsets_names_its_bias_not_the_budget():
    sim = _three_axis("paper002")
    ad = identify("mcv754_wxyzt", sim.measurements, sim.stations_start, strategy="classic").adequacy
    assert ad.verdict == "does_not_fit" and not ad.adequate
    assert ad.cause == "strategy" and ad.causes[0].numbers["strategy"] == "classic"
    assert "--strategy joint" in ad.causes[0].text
    assert "biased strategy (classic)" in ad.summary
    _no_budget_advice(ad)
    print("\nclassic:", ad.summary)


def test_too_low_a_degree_names_the_basis():
    sim = _three_axis("paper002")
    ad = identify("mcv754_wxyzt", sim.measurements, sim.stations_start, degree=1).adequacy
    assert ad.verdict == "does_not_fit"
    assert ad.cause == "basis" and ad.strongest_axis in ("X", "Y", "Z")
    assert "--degree auto" in ad.causes[0].text and "degree 1" in ad.causes[0].text
    _no_budget_advice(ad)


def test_a_fourier_basis_for_a_non_periodic_error_names_the_basis_and_its_remedy():
    sim = _five_axis_non_periodic()
    ad = identify("trunnion_ac", sim.measurements, sim.stations_start).adequacy
    assert ad.verdict == "does_not_fit"
    assert ad.cause == "basis" and ad.causes[0].numbers["axis"] == "C"
    assert "Fourier series" in ad.causes[0].text and "full turn" in ad.causes[0].text
    assert "--basis C=bspline:8" in ad.causes[0].text
    _no_budget_advice(ad)
    # the receiver's side of the advice: the printed basis makes the model fit
    forms = dict([parse_basis("C=bspline:8")])
    again = identify("trunnion_ac", sim.measurements, sim.stations_start, forms=forms).adequacy
    assert again.verdict == "fits", again.message
    print(f"\nFourier C: {ad.summary}\nC=bspline:8: {again.summary}")


@pytest.mark.parametrize("kind", ["station", "time"])
def test_structure_against_a_station_or_time_is_named(kind):
    """A dead path that jumps between two values on one station (its reflector seated
    two ways); a slow drift of every reading."""
    sim = _three_axis("paper002")
    meas = sim.measurements.copy()
    meas["time"] = np.arange(len(meas), dtype=float) * 2.0  # s, in the order measured
    if kind == "station":
        s2 = (meas["station"] == "S2").to_numpy()
        meas.loc[s2 & (np.arange(len(meas)) % 2 == 0), "length"] += 4e-3  # mm
    else:
        # every station's readings drift by up to 3 um during its part of the run
        meas["length"] += 3e-3 * (meas.groupby("station").cumcount() / 208.0) ** 2
    ad = identify("mcv754_wxyzt", meas, sim.stations_start).adequacy
    assert ad.verdict == "does_not_fit"
    wanted = "station" if kind == "station" else "drift"
    assert wanted in ad.cause_kinds, ad.message
    if kind == "station":
        assert "widest S2" in ad.summary
    _no_budget_advice(ad)
