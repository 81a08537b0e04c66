"""Instruments behind one interface.

* A new instrument (tests/coordinate_probe.py: a probe reading 3-D coordinates) is one
  file; identification runs on it unchanged, and on data from the independent rigid-body
  simulator (tests/indep_sim.py) with a truth outside volcal's error basis it recovers the
  error field to the level a plain scipy least-squares fit of the same model reaches.
* Every instrument's reading Function agrees with a finite difference of itself and with
  the formula it documents (numpy, written here).
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import scipy.optimize as so

import coordinate_probe  # noqa: F401  (registers the instrument)
import indep_sim as ind
from volcal.measurement.instruments import (
    MultiLaserInstrument,
    SequentialMultilateration,
    get_instrument,
    instruments,
)
from volcal.model.machine import Machine
from volcal.workflow import identify

MODEL = "mcv754_wxyzt"


def test_registry_names_the_instruments():
    assert {"tracker", "multilaser", "coordinate-probe"} <= set(instruments())
    assert get_instrument("coordinate-probe").n_station_params == 4
    with pytest.raises(Exception, match="unknown instrument"):
        get_instrument("sonar")


@pytest.mark.parametrize("ins", [SequentialMultilateration(), MultiLaserInstrument()])
def test_reading_function_matches_its_formula(ins):
    rng = np.random.default_rng(3)
    P = rng.uniform(-500, 500, (20, 3))
    S = np.column_stack([rng.uniform(-900, 900, (20, 3)), rng.uniform(0, 50, 20)])
    g = np.array([0.1, -0.2, 0.3, 1e-4, -2e-4, 3e-4])
    v, d = ins.evaluate(P, S, g)
    if isinstance(ins, SequentialMultilateration):
        Q = S[:, :3] + g[:3] + np.cross(g[3:], S[:, :3])
        ref = np.linalg.norm(P - Q, axis=1) - S[:, 3]
    else:
        rx, ry, rz = g[3:]
        Rx = np.array([[1, 0, 0], [0, np.cos(rx), -np.sin(rx)], [0, np.sin(rx), np.cos(rx)]])
        Ry = np.array([[np.cos(ry), 0, np.sin(ry)], [0, 1, 0], [-np.sin(ry), 0, np.cos(ry)]])
        Rz = np.array([[np.cos(rz), -np.sin(rz), 0], [np.sin(rz), np.cos(rz), 0], [0, 0, 1]])
        PI = P @ (Rz @ Ry @ Rx).T + g[:3]
        ref = np.linalg.norm(PI - S[:, :3], axis=1) - S[:, 3]
    np.testing.assert_allclose(v, ref, rtol=0, atol=1e-9)
    h = 1e-5
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (ins.evaluate(P + e, S, g)[0] - ins.evaluate(P - e, S, g)[0]) / (2 * h)
        np.testing.assert_allclose(d[:, j], fd, atol=1e-7)


def _probe_data(seed: int = 5):
    """Coordinate readings of the tool point from the independent simulator: a truth
    drawn outside volcal's basis, unknown probe offsets, white noise of 0.5 um."""
    rng = np.random.default_rng(seed)
    geom = ind.load_geometry(MODEL)
    truth = ind.draw_truth(geom, rng, "nonrep")
    poses = ind.grid(geom, {a.name: 5 for a in geom.axes})
    tools = np.array([[0.0, 0.0, 0.0], [80.0, 0.0, 40.0], [0.0, 80.0, 40.0]])
    q = np.repeat(geom.to_internal(poses), len(tools), axis=0)
    t = np.tile(tools, (len(poses), 1))
    P = ind.tool_points(geom, q, t, truth)
    offsets = {"X": 12.5, "Y": -3.0, "Z": 40.0}
    rows = []
    sigma = 0.5e-3
    for j, sid in enumerate("XYZ"):
        m = P[:, j] - offsets[sid] + rng.normal(0, sigma, len(P))
        for i in range(len(P)):
            rows.append({**{a.name + ("_deg" if a.rotary else "_mm"): v for a, v in
                            zip(geom.axes, np.repeat(poses, len(tools), axis=0)[i])},
                         "tool_x_mm": t[i, 0], "tool_y_mm": t[i, 1], "tool_z_mm": t[i, 2],
                         "station": sid, "point": f"P{i}", "length_mm": m[i],
                         "sigma_mm": sigma})
    meas = pd.DataFrame(rows)
    return geom, truth, meas, q, t


def test_new_instrument_identifies_an_independent_truth():
    geom, truth, meas, q, t = _probe_data()
    res = identify(MODEL, meas, instrument="coordinate-probe", degree=3)
    assert res.success
    chi2 = res.conditions["chi2_per_dof"]
    # the truth is outside the cubic basis and coordinates are read to 0.5 um: the fit
    # says it does not fit (chi2/dof well above 1) instead of hiding it
    assert chi2 > 2, chi2
    # the field against the independent truth, modulo the gauge (the probe offsets make
    # a translation invisible; the rigid motion is removed as in every other test)
    pred = res.predict(q, t, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    true = ind.true_error_um(geom, truth, q, t)
    P0 = ind.tool_points(geom, q, t)
    err = ind.field_error_modulo_gauge(pred, true, P0)
    # the reference figure: a plain scipy fit of the same first-order model (volcal's basis
    # as a design matrix) with the offsets as the only instrument unknowns
    machine = Machine.from_model(MODEL)
    em = res.error_model
    p0, dp0, G = _design(machine, em, q, t)
    n = em.n_params
    k = np.array(["XYZ".index(s) for s in meas["station"]])
    idx = np.tile(np.arange(len(q)), 3)
    y = meas["length_mm"].to_numpy()

    def resid(z):
        th, off = z[:n], z[n:]
        pts = p0 + np.einsum("nij,j->ni", G, th)
        return (pts[idx, k] - off[k] - y) / 0.5e-3

    sol = so.least_squares(resid, np.zeros(n + 3), method="lm", x_scale="jac")
    ref_field = np.einsum("nij,j->ni", G, sol.x[:n]) * 1e3
    ref_err = ind.field_error_modulo_gauge(ref_field, true, P0)
    print(f"probe: volcal {err:.3f} um, scipy reference {ref_err:.3f} um, chi2/dof {chi2:.2f}")
    assert err <= 1.05 * ref_err + 0.05, (err, ref_err)
    # and the stations table carries the probe's own parameters, directions held
    st = res.stations.set_index("station")
    assert list(st.columns[:4]) == ["ux", "uy", "uz", "offset_mm"]
    np.testing.assert_allclose(st.loc["X", ["ux", "uy", "uz"]].to_numpy(float), [1, 0, 0])


def _design(machine, em, q, t):
    """First-order model as a design matrix: nominal points (N, 3), errors at theta=0 and
    G (N, 3, n) = d point / d theta."""
    p0, dp, Je = machine.evaluate(q, t, np.zeros(machine.n_errors))
    return p0, dp, np.matmul(Je, em.basis(q))


def test_multilaser_model_on_tracker_data_reaches_the_tracker_minimum():
    """The multi-laser head's reading is the tracker's with an exact frame rotation and the
    lasers in the head's own frame: on tracker data (stations as lasers) it must reach the
    same minimum, from its own start values (ICRS stations and the matching frame)."""
    from test_identify import simulated

    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    a = identify(machine, sim.measurements, error_model=em)
    b = identify(machine, sim.measurements, error_model=em, instrument="multilaser")
    assert a.success and b.success
    assert abs(b.conditions["chi2_per_dof"] / a.conditions["chi2_per_dof"] - 1) < 1e-6


def test_stations_csv_of_another_instrument_is_read_with_its_columns(tmp_path):
    """A stations CSV for a non-tracker instrument is read with that instrument's station
    parameters as columns, and a defect names the file, row and column."""
    from volcal.base.exceptions import InputError
    from volcal.measurement.instruments import get_instrument
    from volcal.measurement.tables import load_instrument_stations

    names = get_instrument("multilaser").station_param_names
    good = tmp_path / "lasers.csv"
    good.write_text("station,x_mm,y_mm,z_mm,offset_mm\nlaser1,0,0,0,1\nlaser2,100,0,0,2\n")
    df = load_instrument_stations(good, names)
    assert list(df.columns) == ["station", *names, "fixed"]
    assert df["offset_mm"].tolist() == [1.0, 2.0]
    bad = tmp_path / "bad.csv"
    bad.write_text("station,x_mm,y_mm,z_mm,offset_mm\nlaser1,0,0,0,1\nlaser2,100,0,0,x\n")
    with pytest.raises(InputError, match=r"bad.csv, row 3, column 'offset_mm'"):
        load_instrument_stations(bad, names)
    nocol = tmp_path / "nocol.csv"
    nocol.write_text("station,x_mm,y_mm,z_mm\nlaser1,0,0,0\n")
    with pytest.raises(InputError, match="offset_mm"):
        load_instrument_stations(nocol, names)
