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

        # One reading as SX functions of the *scaled* variables, weight included: the value
        # (all IPOPT needs for f and its gradient) and, separately, its Jacobian row (for
        # the Gauss-Newton Hessian and the analysis).  The Jacobian is then assembled
        # explicitly instead of by AD through the map.
        nt = em.n_params
        qs, ts = ca.SX.sym("q", n_ax), ca.SX.sym("t", 3)
        ths, ss, gs = ca.SX.sym("theta", nt), ca.SX.sym("s", n_ps), ca.SX.sym("g", n_g)
        ms, ws = ca.SX.sym("m"), ca.SX.sym("w")
        sc = self.scale
        th_phys = ths * ca.DM(sc[:nt])
        s_phys = ss * ca.DM(sc[nt:nt + n_ps])
        g_phys = gs * ca.DM(sc[nt + n_ps * n_st:]) if n_g else gs
        e = em.values_function()(qs, th_phys)
        point = m["tool_point_exact" if self.exact else "tool_point"](qs, ts, e)[0]
        val = ins.reading(point, s_phys, g_phys)
        res = ws * (val - ms)
        row = ca.jacobian(res, ca.vertcat(ths, ss, gs)).T
        ins_ = [qs, ts, ths, ss, gs, ms, ws]
        names_ = ["q", "t", "theta", "s", "g", "m", "w"]
        f_res = ca.Function("residual1", ins_, [res], names_, ["r"], {"cse": True})
        f_row = ca.Function("jacobian1", ins_, [row], names_, ["dr_dx"], {"cse": True})

        # all readings in MX (x is the scaled variable vector)
        xs = ca.MX.sym("x", self.n_x)
        th = xs[:nt]
        sp = xs[nt:nt + n_ps * n_st]
        g = xs[nt + n_ps * n_st:]
        Q, T = ca.MX.sym("q", n_ax, N), ca.MX.sym("t", 3, N)
        meas, w = ca.MX.sym("m", N), ca.MX.sym("w", N)
        p = ca.vertcat(ca.vec(Q), ca.vec(T), meas, w)
        st_idx = np.asarray(lay.station_index, int)
        sel = ca.DM(ca.Sparsity.triplet(n_st, N, [int(i) for i in st_idx], list(range(N))), 1.0)
        S = ca.mtimes(ca.reshape(sp, n_ps, n_st), sel)
        args = (Q, T, th, S, g, meas.T, w.T)
        r = f_res.map(N)(*args).T
        rows = f_row.map(N)(*args)  # (n_vars_per_reading, N)

        # J: dense columns for theta and the globals, one nonzero per row in the columns of
        # the reading's own station.  Built from its sparsity pattern and nonzeros.
        rr, cc = [], []
        for j in range(nt):
            rr.append(np.arange(N)); cc.append(np.full(N, j))
        for k in range(n_ps):
            rr.append(np.arange(N)); cc.append(nt + n_ps * st_idx + k)
        for j in range(n_g):
            rr.append(np.arange(N)); cc.append(np.full(N, nt + n_ps * n_st + j))
        rr, cc = np.concatenate(rr), np.concatenate(cc)
        # nonzeros of rows stacked reading-major per variable: index v * N + i
        src = np.concatenate([np.arange(N) + v * N for v in range(nt + n_ps + n_g)])
        order = np.lexsort((rr, cc))  # column-major order of the sparsity
        colind = np.concatenate([[0], np.cumsum(np.bincount(cc, minlength=self.n_x))])
        sp_J = ca.Sparsity(N, self.n_x, colind.tolist(), rr[order].tolist())
        nz = ca.vec(rows.T)[src[order].tolist()]
        J = ca.MX(sp_J, nz)
        self.residual = ca.Function("residual", [xs, p], [r], ["x", "p"], ["r"])
        self.jacobian = ca.Function("jacobian", [xs, p], [r, J], ["x", "p"], ["r", "J"])

        self.C, self.constraint_labels = em.constraints()
        Cs = self.C * self.scale[None, :nt]
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
