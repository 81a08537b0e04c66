"""Several instruments' tables with the single table's options (issue 32): robust rejection
per table on its own scale, a tracker's stations table and an export's column mapping,
and the combinations that stay refused (with why).  Data: the independent simulator
(tests/indep_sim.py, interferometer lines from tests/fusion_sim.py), not volcal's model."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import fusion_sim as fs
import indep_sim as ind
from volcal.base.exceptions import InputError
from volcal.measurement.tables import DataWarning
from volcal.workflow import identify

MODEL = "mcv754_wxyzt"
LINES = [
    ("X", {"Y": 250.0, "Z": -275.0}),
    ("Y", {"X": 377.0, "Z": -275.0}),
    ("Z", {"X": 377.0, "Y": 250.0}),
]


@pytest.fixture(scope="module")
def sim():
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(11)
    truth = ind.draw_truth(geom, rng, "representable")
    poses = ind.grid(geom, {"X": 4, "Y": 4, "Z": 4})
    tools = np.array([[0.0, 0.0, 100.0], [0.0, 80.0, 150.0]])
    s = ind.simulate(geom, truth, poses, tools, rng, n_stations=4)
    trk = s.measurements.copy()
    trk["sigma"] = s.sigma_mm
    ifm = fs.interferometer_lines(geom, truth, LINES, rng)
    return geom, truth, s, trk, ifm


def _identify(*args, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return identify(*args, **kw)


def test_robust_rejects_each_tables_blunder_on_its_own_scale(sim):
    """A blunder in each table, and an interferometer budget twice too precise (its
    normalised residuals are 2x the tracker's): with one scale for all readings the
    interferometer's good readings would sit at 2 of its real sigma from a 4-sigma limit
    set by the tracker's; per table each limit is its own table's, so exactly the two
    blunders go, each named with its table and its own row, and the interferometer's
    budget is still blamed by its check."""
    _, _, _, trk, ifm = sim
    trk, ifm = trk.copy(), ifm.copy()
    ifm["sigma_um"] = ifm["sigma_um"] / 2
    trk.loc[37, "length"] += 0.03  # 30 um on a reading of about 1 um sigma
    ifm.loc[15, "displacement_mm"] += 0.002  # 2 um on 0.05 um readings
    data = [("tracker", trk, None, "trk"), ("interferometer", ifm, None, "ifm")]
    res = _identify(MODEL, data, degree=3, robust=True)
    rej = res.rejected
    assert sorted(zip(rej["data"], rej["row"])) == [("ifm", 17), ("trk", 39)], rej
    fit = res.instruments.set_index("data")
    assert fit.loc["ifm", "verdict"] == "too large", fit
    assert fit.loc["trk", "verdict"] == "fits", fit
    # the rejected readings have no share in the degrees of freedom
    assert fit.loc["ifm", "dof"] < 32 - 1e-9
    # with the variance components the interferometer's factor is estimated without its
    # blunder (true factor 2)
    vce = _identify(MODEL, data, degree=3, robust=True, variance_components=True)
    f = vce.instruments.set_index("data")
    assert sorted(zip(vce.rejected["data"], vce.rejected["row"])) == [("ifm", 17), ("trk", 39)]
    assert f.loc["ifm", "scale_low_95"] <= 2.0 <= f.loc["ifm", "scale_high_95"], f


def test_stations_table_applies_to_the_tracker_table(sim, tmp_path):
    """The tracker's true stations, fixed: a tracker table alone through the joined path
    reaches the single table's fit with the same stations table; with the interferometer's
    table added the tracker's stations stay where the table holds them."""
    _, _, s, trk, ifm = sim
    st = s.stations.copy()
    st["fixed"] = True
    path = tmp_path / "stations.csv"
    st.to_csv(path, index=False)
    plain = _identify(MODEL, trk, path, degree=3)
    joined = _identify(MODEL, [trk], path, degree=3)
    np.testing.assert_allclose(joined.theta, plain.theta, rtol=0, atol=1e-9)
    both = _identify(MODEL, [trk, ("interferometer", ifm)], path, degree=3)
    assert both.success
    got = both.stations.set_index("station")
    for _, row in st.iterrows():
        for c in ("x_mm", "y_mm", "z_mm", "dead_length_mm"):
            assert got.loc[row["station"], c] == pytest.approx(row[c], abs=1e-9)
    assert (got.loc[got["instrument"] == "interferometer", "fixed"] == False).all()  # noqa: E712
    # start values only (not fixed): the same minimum as from the instrument's own start
    st["fixed"] = False
    start = _identify(MODEL, [trk, ("interferometer", ifm)], st, degree=3)
    free = _identify(MODEL, [trk, ("interferometer", ifm)], degree=3)
    f_start, f_free = start.instruments["chi2_per_dof"], free.instruments["chi2_per_dof"]
    np.testing.assert_allclose(f_start, f_free, rtol=1e-6)


def test_stations_table_naming_another_instruments_setup_is_refused(sim):
    _, _, s, trk, ifm = sim
    st = s.stations.copy()
    st.loc[0, "station"] = "L1X"  # an interferometer set-up
    with pytest.raises(InputError, match="'L1X'.* set-up of .*interferometer.*tracker stations"):
        _identify(MODEL, [trk, ("interferometer", ifm)], st, degree=3)
    with pytest.raises(InputError, match="no table is a tracker's"):
        _identify(MODEL, [("interferometer", ifm)], s.stations, degree=3)


def test_column_mapping_applies_to_the_tracker_table(sim, tmp_path):
    """A tracker export (length in m under another name) with --columns gives the fit of
    the table in volcal's own columns; the interferometer's table is read as it is."""
    _, _, _, trk, ifm = sim
    export = trk.rename(columns={"station": "Tracker", "length": "Distance"})
    export["Distance"] = export["Distance"] * 1e-3
    path = tmp_path / "export.csv"
    export.to_csv(path, index=False)
    ref = _identify(MODEL, [trk, ("interferometer", ifm)], degree=3)
    got = _identify(
        MODEL,
        [path, ("interferometer", ifm)],
        degree=3,
        columns="length=Distance[m],station=Tracker",
    )
    np.testing.assert_allclose(got.theta, ref.theta, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("options", "why"),
    [
        ({"degree": "auto"}, "depend on the budgets' relative scale"),
        ({"strategy": "classic"}, "not a distance from a station"),
    ],
)
def test_meaningless_combinations_say_why(sim, options, why):
    _, _, _, trk, ifm = sim
    with pytest.raises(InputError, match=why):
        _identify(MODEL, [trk, ("interferometer", ifm)], **{"degree": 3, **options})
