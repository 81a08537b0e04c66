"""The datum fixes only what the data cannot see.

Invariant, on every bundled model and every datum option: the weighted residuals (so chi2)
equal those of the fit without any datum, and the identified volumetric field is the same
modulo the rigid motion no multilateration sees.  The truth is drawn directly as random
parameters (it satisfies no datum), with several tool offsets (the case where an ISO 230
datum imposed blindly forbids the tool orientation the data see).

The readings here come from the first-order model itself: that model's gauge (a rigid
motion of the point cloud expressed through the error parameters) is exact only to first
order in the errors, so with readings from the exact model the datums agree to the model's
own second-order accuracy (about 1e-7 relative in chi2 on the bundled example, see
studies/datum) rather than to rounding.  Small errors keep that term below the tolerance.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from volcal.analysis.identify import declared_poses, identify, rigid_fit
from volcal.measurement.plans import default_stations, grid_plan
from volcal.model.datum import DATUMS, candidate_conditions, select_conditions
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import bundled_models

# a low order keeps the 5-axis plans small and every error motion identifiable
DEGREE = 1
TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 120.0], [90.0, 0.0, 60.0], [0.0, 90.0, 60.0]])


def _data(name: str, seed: int = 3):
    """Readings of the first-order model at random parameters (never datum-projected)."""
    m = Machine.from_model(name)
    spec = m.spec
    rot = {a.name: 5 for a in spec.axes if a.is_rotary}
    plan = grid_plan(spec, {**{a.name: 4 if len(spec.axes) <= 3 else 2 for a in spec.axes
                               if not a.is_rotary}, **rot})
    st = default_stations(spec, 5, seed=seed, tools=TOOLS)
    em = ErrorModel(spec, default=ErrorForm("poly", DEGREE))
    rng = np.random.default_rng(seed)
    theta = rng.normal(size=em.n_params) * np.where(
        np.asarray(em.param_units) == "mm", 5e-5, 5e-8)  # a field of a few um
    q = m.axis_to_internal(plan[spec.axis_names].to_numpy(float))
    rows = []
    S = st[["x_mm", "y_mm", "z_mm"]].to_numpy()
    for k, t in enumerate(TOOLS):
        T = np.tile(t, (len(q), 1))
        _, dp, _ = m.evaluate(q, T, em.values(q, theta))
        p0, _, _ = m.evaluate(q, T, np.zeros(m.n_errors))
        P = p0 + dp
        for j, s in enumerate(S):
            L = np.linalg.norm(P - s, axis=1) - st["dead_length_mm"].iloc[j]
            df = plan.copy()
            df.insert(0, "point", [f"P{k}_{i}" for i in range(len(q))])
            df.insert(0, "station", st["station"].iloc[j])
            df[["tool_x", "tool_y", "tool_z"]] = t
            df["length"] = L + rng.normal(scale=5e-4, size=len(L))
            df["sigma"] = 5e-4
            rows.append(df)
    return m, em, pd.concat(rows, ignore_index=True), st


@pytest.fixture(scope="module", params=sorted(bundled_models()))
def fits(request):
    m, em, data, st = _data(request.param)
    out = {}
    for d in DATUMS:
        e = ErrorModel(m.spec, default=ErrorForm("poly", DEGREE), datum=d)
        out[d] = identify(m, data, st, error_model=e)
    return m, out


def test_every_datum_gives_the_residuals_of_the_fit_without_datum(fits):
    _, res = fits
    chi = {d: float(np.sum(r.residuals["normalised_residual"] ** 2)) for d, r in res.items()}
    for d in DATUMS:
        assert res[d].success, res[d].status
        assert chi[d] == pytest.approx(chi["none"], rel=1e-8), chi


def test_every_datum_gives_the_same_field_modulo_the_gauge(fits):
    m, res = fits
    q = declared_poses(m.spec, 300)
    Q = np.repeat(q, len(TOOLS), axis=0)
    T = np.tile(TOOLS, (len(q), 1))
    p0, _, _ = m.evaluate(Q, T, np.zeros(m.n_errors))
    base = res["none"].predict(Q, T)
    ref = base[["dx_um", "dy_um", "dz_um"]].to_numpy()
    for d in ("iso230", "reference"):
        pred = res[d].predict(Q, T)
        # the poses whose error the data determine are the same whatever the datum
        assert (pred["determined"] == base["determined"]).all(), d
        ok = base["determined"].to_numpy()
        assert ok.mean() > 0.5
        f = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
        _, dev = rigid_fit(p0[ok], (f - ref)[ok] * 1e-3)
        assert np.abs(dev).max() * 1e3 < 1e-4 * max(1.0, np.abs(ref).max()), d


def test_the_result_says_which_conditions_hold(fits):
    _, res = fits
    tab = res["iso230"].datum
    assert {"condition", "class", "imposed", "value", "unit"} <= set(tab.columns)
    imposed = tab[tab["imposed"]]
    # imposed conditions hold to rounding (values in um / urad)
    assert (np.abs(imposed["value"]) < 1e-6).all()
    # with four tool offsets the spindle's orientation is seen: its conditions are not
    # imposed, and they take the values the data give
    free = set(tab.loc[~tab["imposed"], "condition"])
    assert {"EA0T = 0", "EB0T = 0"} <= free, free
    assert res["none"].datum.empty


def test_selection_removes_only_null_directions():
    """Greedy selection on a toy Jacobian: the second of two rows on the same null
    direction, and a row on an observable direction, are not imposed."""
    J = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 2.0]])  # null: (1, -1, 0)
    C = np.array([[1.0, 0.0, 0.0],    # touches the null direction: imposed
                  [0.0, 1.0, 0.0],    # the same direction again: not imposed
                  [0.0, 0.0, 1.0],    # observable only: not imposed
                  [1.0, 1.0, 0.0]])   # observable only: not imposed
    assert select_conditions(J, C).tolist() == [True, False, False, False]


def test_candidates_follow_the_documented_order():
    em = ErrorModel(Machine.from_model("mcv754_wxyzt").spec)
    conds = candidate_conditions(em, "iso230")
    classes = [c.klass for c in conds]
    order = ["positioning", "straightness", "angular", "tool position", "tool orientation",
             "location"]
    assert [k for k in dict.fromkeys(classes)] == order
    assert sum(k == "straightness" for k in classes) == 12  # two per straightness
    assert sum(k == "straightness" for k in
               (c.klass for c in candidate_conditions(em, "reference"))) == 6
    assert candidate_conditions(em, "none") == []


def test_predict_flags_poses_the_data_cannot_determine():
    """One tool offset (0, 0, 0): the angular error motions of the last axis and the tool's
    orientation are invisible.  Predicting at that offset is determined; at a 150 mm offset
    it depends on them, so the rows say so and carry no uncertainty."""
    m, em, data, st = _data("xfyz")
    one = data[(data[["tool_x", "tool_y", "tool_z"]] == 0).all(axis=1)]
    res = identify(m, one, st, error_model=ErrorModel(m.spec, default=ErrorForm("poly", DEGREE)))
    assert res.success
    q = declared_poses(m.spec, 50)
    at0 = res.predict(q, np.zeros(3))
    assert at0["determined"].all()
    assert np.isfinite(at0[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()).all()
    far = res.predict(q, np.array([0.0, 0.0, 150.0]))
    assert not far["determined"].any()
    assert far[["u_dx_um", "u_dy_um", "u_dz_um"]].isna().all().all()
    # the held directions are named: gauge at the measured offset, not "unidentifiable"
    assert res.identifiability.gauge_combinations
    assert any("EA0T" in c or "EAZ" in c for c in res.identifiability.gauge_combinations)
