"""Several instruments in one problem (issue 32): a tracker, laser interferometer lines and
ballbar circles simulated on the independent simulator (tests/indep_sim.py, readings from
tests/fusion_sim.py, not volcal's instruments) with a truth volcal's cubic basis can hold
but that satisfies no datum."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import fusion_sim as fs
import indep_sim as ind
from volcal.analysis.identify import field_jacobian
from volcal.base.exceptions import InputError
from volcal.measurement.instruments import Ballbar, LaserInterferometer, get_instrument
from volcal.model.spec import resolve_model
from volcal.workflow import identify

MODEL = "mcv754_wxyzt"
LINES = [
    ("X", {"Y": 250.0, "Z": -275.0}),
    ("Y", {"X": 377.0, "Z": -275.0}),
    ("Z", {"X": 377.0, "Y": 250.0}),
]
CIRCLES = [("XY", {"X": 377.0, "Y": 250.0, "Z": -275.0}, 150.0)]


def _data(noise: bool, seed: int = 3):
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(seed)
    truth = ind.draw_truth(geom, rng, "representable")
    poses = ind.grid(geom, {"X": 4, "Y": 4, "Z": 4})
    tools = np.array([[0.0, 0.0, 100.0], [0.0, 80.0, 150.0]])
    sim = ind.simulate(
        geom, truth, poses, tools, rng, n_stations=4, noise=ind.Noise() if noise else None
    )
    trk = sim.measurements.copy()
    trk["sigma"] = sim.sigma_mm
    ifm = fs.interferometer_lines(geom, truth, LINES, rng, noise=noise)
    bb = fs.ballbar_circles(geom, truth, CIRCLES, rng, noise=noise)
    return geom, truth, {"tracker": trk, "interferometer": ifm, "ballbar": bb}


@pytest.fixture(scope="module")
def noisy():
    return _data(True)


def _line_arrays(geom, ifm):
    axes = [f"{a.name}_{'deg' if a.rotary else 'mm'}" for a in geom.axes]
    q = geom.to_internal(ifm[axes].to_numpy(float))
    t = ifm[["tool_x_mm", "tool_y_mm", "tool_z_mm"]].to_numpy(float)
    return q, t


def line_error_um(res, geom, truth, ifm) -> float:
    """RMS (um) of the predicted minus true error along each interferometer line at its
    targets, each line's mean removed: the positioning error an interferometer determines."""
    q, t = _line_arrays(geom, ifm)
    pred = res.predict(q, t, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    true = ind.true_error_um(geom, truth, q, t)
    P0 = ind.tool_points(geom, q, t)
    out = []
    for _, rows in ifm.groupby("setup").indices.items():
        u = P0[rows[-1]] - P0[rows[0]]
        d = (pred[rows] - true[rows]) @ (u / np.linalg.norm(u))
        out.append(d - d.mean())
    return float(np.sqrt(np.mean(np.concatenate(out) ** 2)))


def line_uncertainty_um(res, ifm, geom) -> float:
    """RMS standard uncertainty (um) of the positioning error along each line relative to
    its first target, from the result's covariance."""
    q, t = _line_arrays(geom, ifm)
    P0, _, G = field_jacobian(res.machine, res.error_model, res.theta, q, t)
    C = np.nan_to_num(res.cov_theta)
    out = []
    for _, rows in ifm.groupby("setup").indices.items():
        u = P0[rows[-1]] - P0[rows[0]]
        u = u / np.linalg.norm(u)
        g = np.einsum("i,nij->nj", u, G[rows] - G[rows[0]])
        out.append(np.einsum("nj,jk,nk->n", g, C, g))
    return float(np.sqrt(np.mean(np.concatenate(out)))) * 1e3


def field_error_um(res, geom, truth, trk) -> float:
    q, t = ind.measurement_arrays(geom, trk)
    pred = res.predict(q, t, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    return ind.field_error_modulo_gauge(
        pred, ind.true_error_um(geom, truth, q, t), ind.tool_points(geom, q, t)
    )


# ---- the instruments' readings ----------------------------------------------------------


def test_readings_are_their_formulas():
    rng = np.random.default_rng(0)
    P = rng.uniform(-300, 300, (5, 3))
    u = np.array([0.0, 1.0, 0.0])
    st = np.tile(np.r_[u, 0.0, 0.0, 2.5], (5, 1))
    v, d = LaserInterferometer().evaluate(P, st)
    np.testing.assert_allclose(v, P[:, 1] - 2.5, atol=1e-12)
    np.testing.assert_allclose(d, np.tile(u, (5, 1)), atol=1e-12)
    # a misaligned beam: the cosine error of a 1 mrad misalignment along the line
    st[:, 3] = 1e-3
    line = np.outer(np.linspace(0, 500, 5), u)
    v, _ = LaserInterferometer().evaluate(line, st)
    np.testing.assert_allclose(v + 2.5, line[:, 1] * np.cos(1e-3), rtol=0, atol=1e-12)
    C, R = np.array([10.0, -20.0, 5.0]), 150.0
    v, _ = Ballbar().evaluate(P, np.tile(np.r_[C, R], (5, 1)))
    np.testing.assert_allclose(v, np.linalg.norm(P - C, axis=1) - R, atol=1e-12)


def test_ballbar_table_gives_the_circle_positions_and_bad_rows_are_named(tmp_path):
    spec = resolve_model(MODEL)
    geom, truth, d = _data(False)
    tab = Ballbar().read_table(d["ballbar"], spec)
    ang = np.deg2rad(d["ballbar"]["angle_deg"].to_numpy())
    np.testing.assert_allclose(tab["X_mm"], 377.0 + 150.0 * np.cos(ang))
    np.testing.assert_allclose(tab["Y_mm"], 250.0 + 150.0 * np.sin(ang))
    np.testing.assert_allclose(tab["length_mm"], d["ballbar"]["deviation_um"] * 1e-3)
    bad = d["ballbar"].copy()
    bad.loc[3, "plane"] = "XQ"
    path = tmp_path / "circles.csv"
    bad.to_csv(path, index=False)
    before = path.read_bytes()
    with pytest.raises(InputError, match=r"circles.csv, row 5, column 'plane'.*two linear axes"):
        Ballbar().read_table(path, spec)
    assert path.read_bytes() == before  # inputs never modified


def test_iso230_2_file_reads_as_interferometer_readings():
    from importlib.resources import files

    spec = resolve_model(MODEL)
    src = files("volcal.data") / "iso230_2_example.csv"
    tab = LaserInterferometer().read_table(str(src), spec)
    raw = pd.read_csv(str(src))
    assert len(tab) == len(raw) and set(tab["station"]) == {"X-line"}
    # actual position = target + deviation, the other axes at their reference
    first = raw.iloc[0]
    row = tab.loc[tab["X_mm"] == first["target_mm"]].iloc[0]
    assert abs(row["length_mm"] - (first["target_mm"] + first["deviation_um"] * 1e-3)) < 1e-9
    assert (tab["Y_mm"] == 0).all() and (tab["Z_mm"] == 0).all()


def test_station_ids_must_differ_between_tables(noisy):
    _, _, d = noisy
    other = d["tracker"].copy()
    with pytest.raises(InputError, match="station .*'S1'.* also appears"):
        identify(MODEL, [d["tracker"], ("tracker", other, None, "second")], degree=3)


def test_interferometer_without_sigma_or_budget_is_refused(noisy):
    _, _, d = noisy
    with pytest.raises(InputError, match="no sigma_mm .*budget"):
        identify(
            MODEL, [d["tracker"], ("interferometer", d["interferometer"].drop(columns="sigma_um"))]
        )


# ---- one problem, several instruments -----------------------------------------------------


def test_tracker_interferometer_and_both_on_the_independent_truth(noisy):
    geom, truth, d = noisy
    trk = identify(MODEL, d["tracker"], degree=3)
    ifm = identify(MODEL, [("interferometer", d["interferometer"])], degree=3)
    both = identify(MODEL, [d["tracker"], ("interferometer", d["interferometer"])], degree=3)
    for r in (trk, ifm, both):
        assert r.success
    # interferometer lines alone leave most of the field undetermined, by name
    unid = {n for n, ok in zip(ifm.error_model.param_names, ifm.identifiable) if not ok}
    assert len(unid) > 0.5 * len(ifm.identifiable)
    # straightness is invisible along a line; X's positioning error is seen only mixed
    # with the Abbe terms of its angular errors (one tool offset): named, not determined
    assert {"EYX_1", "EZX_1", "EXY_1", "EXX_1", "EBX_1"} <= unid, sorted(unid)
    # what each determines: the whole field (tracker), the positioning along the lines
    # (interferometer); the joint fit is no worse than the better instrument on either
    f_trk, f_both = (
        field_error_um(trk, geom, truth, d["tracker"]),
        field_error_um(both, geom, truth, d["tracker"]),
    )
    lines = {
        k: line_error_um(r, geom, truth, d["interferometer"])
        for k, r in (("trk", trk), ("ifm", ifm), ("both", both))
    }
    u = {
        k: line_uncertainty_um(r, d["interferometer"], geom)
        for k, r in (("trk", trk), ("ifm", ifm), ("both", both))
    }
    print(f"field {f_trk:.3f} -> {f_both:.3f} um; lines {lines}; u(lines) {u}")
    assert f_both <= 1.05 * f_trk + 0.01
    assert lines["both"] <= 1.1 * min(lines["trk"], lines["ifm"]) + 0.02
    # the uncertainty of the positioning errors shrinks to the interferometer's level
    assert u["both"] < 0.5 * u["trk"]
    assert u["both"] <= 1.1 * u["ifm"]
    # the adequacy check per instrument
    fit = both.instruments.set_index("instrument")
    assert list(fit.index) == ["tracker", "interferometer"]
    assert (fit["verdict"] == "fits").all(), fit
    # what each determines alone, and the field uncertainty as tables are added
    assert fit.loc["interferometer", "determined_alone"] < fit.loc["tracker", "determined_alone"]
    assert "EYX_1" in fit.loc["interferometer", "undetermined_alone"].split()
    cum = fit["field_u_cumulative_um"].to_numpy()
    assert cum[1] <= cum[0]
    # the degrees of freedom of the instruments add up to the problem's
    n_free = int((~both.state.fixed).sum())
    total = len(both.residuals) - n_free + both.identifier.problem.C.shape[0]
    assert abs(fit["dof"].sum() - total) < 1e-6 * total


@pytest.mark.parametrize(
    "combo",
    [
        ("tracker",),
        ("interferometer",),
        ("tracker", "interferometer"),
        ("ballbar",),
        ("tracker", "ballbar"),
        ("interferometer", "ballbar"),
        ("tracker", "interferometer", "ballbar"),
    ],
)
def test_noise_free_twin_identifies_to_rounding(combo, twin):
    geom, truth, d = twin
    res = identify(MODEL, [(c, d[c]) for c in combo], degree=3)
    assert res.success
    # every reading reproduced; the error left is the first-order model's against the
    # simulator's exact transforms (second order: 1e-4 um here) and the beam's cosine
    # error (1e-3 um over the X travel)
    assert res.residual_rms_um < 2e-3, res.residual_rms_um
    if "tracker" in combo:
        assert field_error_um(res, geom, truth, d["tracker"]) < 2e-3
    if "interferometer" in combo:
        assert line_error_um(res, geom, truth, d["interferometer"]) < 2e-3


@pytest.fixture(scope="module")
def twin():
    return _data(False)


def test_variance_components_recover_a_budget_wrong_by_two(noisy):
    _, _, d = noisy
    ifm = d["interferometer"].copy()
    ifm["sigma_um"] = ifm["sigma_um"] / 2  # the table claims twice the real precision
    res = identify(
        MODEL, [d["tracker"], ("interferometer", ifm)], degree=3, variance_components=True
    )
    fit = res.instruments.set_index("instrument")
    print(fit[["dof", "scale_factor", "u_scale_factor", "scale_low_95", "scale_high_95"]])
    lo, hi = fit.loc["interferometer", ["scale_low_95", "scale_high_95"]]
    assert lo <= 2.0 <= hi
    lo, hi = fit.loc["tracker", ["scale_low_95", "scale_high_95"]]
    assert lo <= 1.0 <= hi
    # after the re-weighting every instrument fits its scaled budget
    assert np.allclose(fit["chi2_per_dof"], 1.0, atol=1e-3)
    assert any("variance components" in n for n in res.notes)


def test_a_budget_wrong_by_two_is_blamed_on_its_own_table(noisy):
    # the detection side of the per-table check: the interferometer's table claims twice
    # its real precision (its readings' variance is 4x the budget's), so its chi2/dof is
    # far above its interval and it alone is named; the tracker's table still fits
    _, _, d = noisy
    ifm = d["interferometer"].copy()
    ifm["sigma_um"] = ifm["sigma_um"] / 2
    res = identify(MODEL, [d["tracker"], ("interferometer", ifm)], degree=3)
    fit = res.instruments.set_index("instrument")
    assert fit.loc["interferometer", "verdict"] == "too large", fit
    assert fit.loc["interferometer", "chi2_per_dof"] > 2.0, fit
    assert fit.loc["tracker", "verdict"] == "fits", fit


def test_registry_has_the_new_instruments():
    assert get_instrument("interferometer").name == "interferometer"
    assert get_instrument("ballbar").name == "ballbar"


def test_cli_simulates_and_identifies_several_instruments(tmp_path, capsys):
    """`volcal simulate --instruments` writes each instrument's readings of one true
    machine; `volcal identify --data ... --data INSTRUMENT=...` identifies them as one
    problem and writes each table's chi2/dof; a bad table exits 2 naming file, row, column."""
    import json

    from volcal.cli.main import main

    sim = tmp_path / "sim"
    args = ["simulate", "--model", MODEL, "--plan", "grid", "--grid", "3", "--degree", "2"]
    args += ["--tools", "0,0,0;0,0,-100;80,0,-100", "--instruments", "interferometer,ballbar"]
    assert main([*args, "--seed", "5", "--out", str(sim), "-q"]) == 0
    assert (sim / "interferometer.csv").is_file() and (sim / "ballbar.csv").is_file()
    out = tmp_path / "res"
    data = ["--data", str(sim / "measurements.csv")]
    data += ["--data", f"interferometer={sim / 'interferometer.csv'}"]
    data += ["--data", f"ballbar={sim / 'ballbar.csv'}"]
    code = main(
        ["identify", "--model", MODEL, *data, "--degree", "2", "--out", str(out)]
        + ["--no-plots", "-q"]
    )
    assert code == 0
    meta = json.loads((out / "result.json").read_text())
    inst = {r["instrument"]: r for r in meta["instruments"]}
    assert set(inst) == {"tracker", "interferometer", "ballbar"}
    assert all(r["verdict"] == "fits" for r in inst.values()), inst
    table = pd.read_csv(out / "instruments.csv")
    assert list(table["instrument"]) == ["tracker", "interferometer", "ballbar"]
    assert "## Instruments" in (out / "report.md").read_text()
    # commands that redo an identification from its folder say they cannot (yet)
    capsys.readouterr()
    assert main(["analyze", "--result", str(out), "--out", str(tmp_path / "an"), "-q"]) == 2
    assert "several instruments" in capsys.readouterr().err
    # a bad ballbar row: exit code 2, the file, row and column named
    bad = pd.read_csv(sim / "ballbar.csv", dtype=str)
    bad.loc[4, "angle_deg"] = "x"
    bad.to_csv(tmp_path / "bad.csv", index=False)
    capsys.readouterr()
    code = main(
        [
            "identify",
            "--model",
            MODEL,
            data[0],
            data[1],
            "--data",
            f"ballbar={tmp_path / 'bad.csv'}",
            "--out",
            str(tmp_path / "r2"),
            "-q",
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "row 6" in err and "angle_deg" in err, err
    assert not (tmp_path / "r2").exists()


def test_one_table_through_the_combined_instrument_is_the_plain_identification(noisy):
    """The combined instrument adds nothing of its own: a tracker table alone through it
    reaches the plain identification's minimum and covariance."""
    _, _, d = noisy
    plain = identify(MODEL, d["tracker"], degree=3)
    joined = identify(MODEL, [d["tracker"]], degree=3)
    assert abs(joined.conditions["chi2_per_dof"] / plain.conditions["chi2_per_dof"] - 1) < 1e-6
    np.testing.assert_allclose(joined.theta, plain.theta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        np.nan_to_num(joined.cov_theta), np.nan_to_num(plain.cov_theta), rtol=1e-5, atol=1e-16
    )
    fit = joined.instruments.iloc[0]
    assert abs(fit["chi2_per_dof"] - plain.conditions["chi2_per_dof"]) < 1e-6
