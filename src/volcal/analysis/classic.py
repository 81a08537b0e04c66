"""The classic two-step pipeline: calibrate stations -> multilaterate points -> fit errors.

This is what TRAC-CAL-style software and paper 000 do: stations are self-calibrated on
the nominal (commanded) points, each point is then multilaterated from the calibrated
stations, and the error motions are fitted to the point deviations by linear least squares
with the datum constraints and a free rigid motion (the station frame is only known up to
the errors the calibration absorbed).  Its weakness is the first step: stations fitted on
nominal points absorb part of the machine's errors, which then bias everything after.
The one-NLP strategies in :mod:`volcal.analysis.identify` avoid that; this one is here so that
researchers can compare, with the condition numbers of every system it solves.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
import scipy.linalg as sla

from volcal.analysis import analyse_jacobian
from volcal.analysis.identifiability import rigid_columns
from volcal.base.exceptions import SolverError
from volcal.base.units import solver_scale
from volcal.measurement.instruments import get_instrument
from volcal.measurement.multilateration import calibrate_stations, multilaterate
from volcal.measurement.tables import Measurements
from volcal.model.datum import candidate_conditions, condition_table, select_conditions
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.solve.outcome import SolveOutcome


def classic_pipeline(
    machine: Machine,
    em: ErrorModel,
    meas: Measurements,
    st0: np.ndarray,
    sigma: np.ndarray,
    *,
    station_method: str = "sqrt",
    point_method: str = "sqrt",
    t_start: float | None = None,
    sigma_source: str = "",
    notes: list[str] | None = None,
):
    """Run the classic pipeline; returns an
    :class:`~volcal.analysis.identify.IdentificationResult`."""
    from volcal.analysis.identify import IdentificationResult

    t_start = time.perf_counter() if t_start is None else t_start
    notes = list(notes or [])
    t0 = time.perf_counter()
    zeros = np.zeros(machine.n_errors)
    p_nom, _, _ = machine.evaluate(meas.q_internal, meas.tool, zeros)
    ids = np.asarray(meas.station_ids, dtype=object)[meas.station_index]
    cal = calibrate_stations(ids, p_nom, meas.length, method=station_method, sigma=sigma)
    order = [list(map(str, cal.stations)).index(s) for s in meas.station_ids]
    S = cal.positions[order]
    d = cal.dead_lengths[order]
    if not np.all(cal.converged):
        bad = [str(s) for s, ok in zip(cal.stations, cal.converged) if not ok]
        raise SolverError(
            f"classic pipeline: station calibration failed for {bad}",
            status="; ".join(map(str, cal.status)),
        )
    out_cal = SolveOutcome(
        np.r_[S.ravel(), d],
        float("nan"),
        "stations calibrated",
        True,
        int(np.max(cal.iterations)),
        time.perf_counter() - t0,
    )

    # one multilateration problem per (commanded pose, tool offset)
    t0 = time.perf_counter()
    key = pd.DataFrame(
        {"p": meas.point_index, "tx": meas.tool[:, 0], "ty": meas.tool[:, 1], "tz": meas.tool[:, 2]}
    )
    group = key.groupby(["p", "tx", "ty", "tz"], sort=False).ngroup().to_numpy()
    n_pts = int(group.max()) + 1
    K = len(meas.station_ids)
    lengths = np.full((n_pts, K), np.nan)
    sig = np.full((n_pts, K), np.nan)
    lengths[group, meas.station_index] = meas.length
    sig[group, meas.station_index] = sigma
    first = np.zeros(n_pts, int)
    first[group[::-1]] = np.arange(len(group))[::-1]
    ml = multilaterate(
        S,
        d,
        lengths,
        method=point_method,
        sigma=np.where(np.isfinite(sig), sig, 1.0),
        initial=p_nom[first],
    )
    if not np.all(ml.converged):
        notes.append(
            f"classic pipeline: {int((~ml.converged).sum())} of {n_pts} points could "
            f"not be multilaterated and were left out ({ml.status})"
        )
    ok = ml.converged
    out_ml = SolveOutcome(
        ml.points.ravel(),
        float("nan"),
        f"points multilaterated ({ml.status})",
        bool(ok.any()),
        int(np.max(ml.iterations)),
        time.perf_counter() - t0,
    )

    # linear fit of the error parameters (+ rigid motion) to the point deviations
    t0 = time.perf_counter()
    q_pts, t_pts, p0_pts = meas.q_internal[first][ok], meas.tool[first][ok], p_nom[first][ok]
    dev = (ml.points[ok] - p0_pts).ravel()
    _, _, Je = machine.evaluate(q_pts, t_pts, zeros)
    G = em.apply_basis(Je, q_pts).reshape(-1, em.n_params)
    A = np.hstack([G, rigid_columns(p0_pts)])
    scale = np.r_[solver_scale(em.param_units), solver_scale(["mm"] * 3 + ["rad"] * 3)]
    As = A * scale
    # the datum: the candidate conditions that remove a null direction of this linear fit
    # (the same rule as the one-step identification, volcal.model.datum)
    conds = candidate_conditions(em, em.datum)
    C_all = np.array([c.row for c in conds]) if conds else np.zeros((0, em.n_params))
    C_all = np.hstack([C_all * scale[: em.n_params], np.zeros((len(C_all), 6))])
    datum_active = select_conditions(As, C_all)
    Cs = C_all[datum_active]
    names = em.param_names + [
        "frame_tx_mm",
        "frame_ty_mm",
        "frame_tz_mm",
        "frame_rx_rad",
        "frame_ry_rad",
        "frame_rz_rad",
    ]
    ident = analyse_jacobian(As, names, Cs, prefer=np.r_[np.ones(em.n_params), np.zeros(6)])
    fixed = np.zeros(len(names), bool)
    fixed[ident.pivots] = True
    free = np.flatnonzero(~fixed)
    Cf = Cs[:, free]
    Cf = Cf[np.linalg.norm(Cf, axis=1) > 0]
    Z = sla.null_space(Cf) if len(Cf) else np.eye(len(free))
    AZ = As[:, free] @ Z
    y, *_ = np.linalg.lstsq(AZ, dev, rcond=None)
    xs = np.zeros(len(names))
    xs[free] = Z @ y
    resid = dev - As @ xs
    dof = max(len(dev) - AZ.shape[1], 1)
    s2 = float(resid @ resid / dof)
    Minv = np.linalg.pinv(AZ.T @ AZ)
    cov_s = np.full((len(names), len(names)), np.nan)
    cov_s[np.ix_(free, free)] = s2 * Z @ Minv @ Z.T
    x = xs * scale
    cov = cov_s * scale[:, None] * scale[None, :]
    theta = x[: em.n_params]
    out_fit = SolveOutcome(
        x, 0.5 * float(resid @ resid), "error motions fitted", True, 1, time.perf_counter() - t0
    )

    # reading residuals of the final model, for the report
    e = em.values(meas.q_internal, theta)
    p, _, _ = machine.evaluate(meas.q_internal, meas.tool, e)
    frame_a, frame_w = x[em.n_params : em.n_params + 3], x[em.n_params + 3 :]
    # the fitted rigid motion moves the points; move the stations the opposite way (the
    # tracker's frame motion, so the reading itself is the instrument's one Function)
    tracker = get_instrument("tracker")
    Sm = S - frame_a - np.cross(frame_w, S)
    stations = np.c_[S, d][meas.station_index]
    model, _ = tracker.evaluate(p, stations, np.r_[-frame_a, -frame_w])
    res_mm = model - meas.length
    residuals = meas.table.copy()
    residuals["residual_um"] = res_mm * 1e3
    residuals["normalised_residual"] = res_mm / sigma
    residuals["rejected"] = False
    conditions = {
        f"station_{station_method}_{sid}": float(c)
        for sid, c in zip(meas.station_ids, cal.condition[order])
    }
    conditions.update(
        {
            f"station_{station_method}_scaled_{sid}": float(c)
            for sid, c in zip(meas.station_ids, cal.condition_scaled[order])
        }
    )
    conditions["points_median"] = float(np.nanmedian(ml.condition))
    conditions["points_max"] = float(np.nanmax(ml.condition))
    conditions["fit_scaled"] = ident.condition
    conditions["fit_unscaled"] = ident.condition_unscaled
    conditions["chi2_per_dof"] = float(np.mean(residuals["normalised_residual"] ** 2))
    stations_out = pd.DataFrame(
        {
            "station": meas.station_ids,
            "x_mm": Sm[:, 0],
            "y_mm": Sm[:, 1],
            "z_mm": Sm[:, 2],
            "dead_length_mm": d,
            "fixed": False,
        }
    )
    notes.append(
        f"classic pipeline: stations by '{station_method}', points by "
        f"'{point_method}', errors by constrained linear least squares on {ok.sum()} "
        "point deviations with a free rigid motion; standard uncertainties from the "
        "scatter of the point deviations"
    )
    identifiable = ~ident.unidentifiable[: em.n_params] & ~fixed[: em.n_params]
    return IdentificationResult(
        machine,
        em,
        "classic",
        theta,
        cov[: em.n_params, : em.n_params],
        identifiable,
        stations_out,
        x[em.n_params :],
        residuals,
        ident,
        [out_cal, out_ml, out_fit],
        conditions,
        residuals.iloc[0:0].assign(row=[]),
        time.perf_counter() - t_start,
        sigma_source,
        notes,
        condition_table(conds, datum_active, theta),
    )
