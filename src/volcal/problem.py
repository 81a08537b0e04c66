"""The identification as one NLP: variables, whitened residuals, datum constraints.

Variables  x = [theta (error parameters), station parameters (per station, stacked),
               global instrument parameters].
Parameters p = the data: axis positions q (n_axes x N), tool offsets t (3 x N), readings m
               (N), weights w = 1/sigma (N; 0 drops a reading, used by outlier rejection).
Residuals  r = w * (model(q, t, theta, station) - m), one per reading, from a single SX
           function replicated over the readings with ``Function.map``.
Constraints g = C theta = 0 (datum conventions, see :mod:`volcal.errors`).

The structure (how many readings, which station each belongs to) is fixed when the
problem is built; the numbers are parameters, so the solver built from it serves every
data set of that layout (Monte Carlo, studies, repeated identifications) without rebuild.
Fixing a variable is done with equal bounds, again without rebuild.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from volcal.errors import ErrorModel
from volcal.instruments import Instrument
from volcal.machine import Machine


@dataclass(frozen=True)
class Layout:
    """Structure of a data set: the station (0..n_stations-1) of every reading."""

    station_index: np.ndarray
    n_stations: int
    station_ids: tuple[str, ...] | None = None

    @property
    def n_readings(self) -> int:
        return int(len(self.station_index))


@dataclass
class IdentificationProblem:
    """One NLP for a machine, error model, instrument and data layout (see module doc)."""

    machine: Machine
    error_model: ErrorModel
    instrument: Instrument
    layout: Layout
    exact: bool = False
    # filled by __post_init__
    n_theta: int = field(init=False)
    n_x: int = field(init=False)
    names: list[str] = field(init=False)
    units: list[str] = field(init=False)
    C: np.ndarray = field(init=False, repr=False)
    constraint_labels: list[str] = field(init=False, repr=False)
    residual: ca.Function = field(init=False, repr=False)
    jacobian: ca.Function = field(init=False, repr=False)
    nlp: dict = field(init=False, repr=False)
    hess_lag: ca.Function = field(init=False, repr=False)

    def __post_init__(self) -> None:
        m, em, ins, lay = self.machine, self.error_model, self.instrument, self.layout
        n_ax, N = m.n_axes, lay.n_readings
        n_ps, n_st, n_g = ins.n_station_params, lay.n_stations, ins.n_global_params
        self.n_theta = em.n_params
        self.n_x = em.n_params + n_ps * n_st + n_g

        # Variables are scaled so that a unit step is a typical uncertainty (1 um, 1 urad,
        # 1 um for stations): IPOPT then sees a Hessian whose conditioning reflects the
        # geometry of the experiment, not the choice of units.
        self.scale = np.concatenate([
            [1e-3 if u == "mm" else 1e-6 for u in em.param_units],
            np.full(n_ps * n_st, 1e-3),
            [1e-3 if u == "mm" else 1e-6 for u in ins.global_param_units]])

        # one reading as an SX function returning its value and its own Jacobian row: the
        # Jacobian is then assembled explicitly instead of by AD through the map.
        qs, ts = ca.SX.sym("q", n_ax), ca.SX.sym("t", 3)
        ths, ss, gs = ca.SX.sym("theta", em.n_params), ca.SX.sym("s", n_ps), ca.SX.sym("g", n_g)
        e = em.values_function()(qs, ths)
        point = m["tool_point_exact" if self.exact else "tool_point"](qs, ts, e)[0]
        val = ins.reading(point, ss, gs)
        row = ca.jacobian(val, ca.vertcat(ths, ss, gs)).T
        reading = ca.Function("reading", [qs, ts, ths, ss, gs], [val, row],
                              ["q", "t", "theta", "s", "g"], ["m", "dm_dx"], {"cse": True})
        self.reading_function = reading

        # all readings in MX (x is the scaled variable vector)
        xs = ca.MX.sym("x", self.n_x)
        xp = xs * ca.DM(self.scale)
        th = xp[:em.n_params]
        sp = xp[em.n_params:em.n_params + n_ps * n_st]
        g = xp[em.n_params + n_ps * n_st:]
        Q, T = ca.MX.sym("q", n_ax, N), ca.MX.sym("t", 3, N)
        meas, w = ca.MX.sym("m", N), ca.MX.sym("w", N)
        p = ca.vertcat(ca.vec(Q), ca.vec(T), meas, w)
        st_idx = [int(i) for i in lay.station_index]
        sel = ca.DM(ca.Sparsity.triplet(n_st, N, st_idx, list(range(N))), 1.0)
        S = ca.mtimes(ca.reshape(sp, n_ps, n_st), sel)
        model, rows = reading.map(N)(Q, T, th, S, g)
        r = w * (model.T - meas)
        # Jacobian wrt the scaled variables, rows weighted by w
        Wd = ca.diag(w)
        J_th = ca.mtimes(Wd, rows[:em.n_params, :].T) * ca.repmat(
            ca.DM(self.scale[:em.n_params]).T, N, 1)
        J_st = None
        for k in range(n_ps):
            # station parameter k of reading i sits in column n_ps * station(i) + k
            pick = ca.DM(ca.Sparsity.triplet(N, n_ps * n_st, list(range(N)),
                                             [n_ps * i + k for i in st_idx]), 1.0)
            part = ca.mtimes(ca.diag(w * rows[em.n_params + k, :].T), pick)
            J_st = part if J_st is None else J_st + part
        blocks = [J_th, J_st]
        if n_g:
            blocks.append(ca.mtimes(Wd, rows[em.n_params + n_ps:, :].T))
        # chain rule for the variable scaling of the instrument columns
        J = ca.horzcat(*blocks)
        J = ca.horzcat(J[:, :em.n_params],
                       J[:, em.n_params:] * ca.repmat(ca.DM(self.scale[em.n_params:]).T, N, 1))
        self.residual = ca.Function("residual", [xs, p], [r], ["x", "p"], ["r"])
        self.jacobian = ca.Function("jacobian", [xs, p], [r, J], ["x", "p"], ["r", "J"])

        self.C, self.constraint_labels = em.constraints()
        Cs = self.C * self.scale[None, :em.n_params]
        gvec = ca.mtimes(ca.DM(Cs), xs[:em.n_params]) if self.C.shape[0] else ca.MX(0, 1)
        self.nlp = {"x": xs, "p": p, "f": 0.5 * ca.sumsqr(r), "g": gvec}
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", gvec.shape[0])
        # Gauss-Newton Hessian of the Lagrangian (constraints are linear: no curvature)
        H = lam_f * ca.mtimes(J.T, J)
        self.hess_lag = ca.Function("nlp_hess_l", [xs, p, lam_f, lam_g], [ca.triu(H)],
                                    ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])

        self.names = list(em.param_names)
        self.units = list(em.param_units)
        for k in range(n_st):
            sid = lay.station_ids[k] if lay.station_ids else f"station{k}"
            self.names += [f"{sid}.{nm}" for nm in ins.station_param_names]
            self.units += ["mm"] * n_ps
        self.names += list(ins.global_param_names)
        self.units += list(ins.global_param_units)

    # ---- packing ------------------------------------------------------------------------
    def pack_data(self, q: np.ndarray, t: np.ndarray, m: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Parameter vector p from q (N, n_axes), t (N, 3), readings m (N,), weights w (N,)."""
        return np.concatenate([np.asarray(q, float).ravel(), np.asarray(t, float).ravel(),
                               np.asarray(m, float), np.asarray(w, float)])

    def pack_x(self, theta: np.ndarray, stations: np.ndarray, glob: np.ndarray | None = None):
        """x from theta (n_theta,), stations (n_stations, n_station_params), globals."""
        glob = np.zeros(self.instrument.n_global_params) if glob is None else glob
        return np.concatenate([theta, np.asarray(stations, float).ravel(), glob])

    def unpack_x(self, x: np.ndarray):
        """(theta, stations (n_stations, n_station_params), globals) from x."""
        x = np.asarray(x, float).ravel()
        nt, nps, ns = self.n_theta, self.instrument.n_station_params, self.layout.n_stations
        return x[:nt], x[nt:nt + nps * ns].reshape(ns, nps), x[nt + nps * ns:]

    def to_scaled(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, float) / self.scale

    def from_scaled(self, xs: np.ndarray) -> np.ndarray:
        return np.asarray(xs, float).ravel() * self.scale

    def theta_slice(self) -> slice:
        return slice(0, self.n_theta)

    def station_slice(self) -> slice:
        nps, ns = self.instrument.n_station_params, self.layout.n_stations
        return slice(self.n_theta, self.n_theta + nps * ns)
