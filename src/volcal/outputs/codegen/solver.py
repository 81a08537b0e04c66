"""The numerical content of an exported solver: what is decided at export, and the CasADi
functions that become C.

Decided at export (from the model, the plan and the options), never at run time:

* the layout: number of readings N, of stations K, the station of every reading;
* the *phases* of the strategy, each with its set of fixed variables.  The fixed set is
  the one :meth:`volcal.analysis.identify.Identifier.run` uses (it is run at export on the plan):
  user-fixed stations, and the variables the identifiability analysis holds (one per
  null direction, at zero).  The analysis needs only the layout and start stations;
  with lengths in the plan it sees exactly what Python's ``identify`` sees;
* per phase, the elimination of the datum constraints C theta = 0: m *basic* variables
  (chosen by QR with column pivoting) are expressed through the others,
  x_B = -A_B^-1 (A_N x_N + A_X x_X).  The solver then works on the free non-basic
  variables z only, x = x_base + E z, and every iterate satisfies the constraints to
  rounding.  This is exact (no penalty, no regularisation), so the fixed point of the
  iteration is the KKT point of the constrained least-squares problem IPOPT solves.

The C functions (all take and return column vectors; x is the *scaled* variable vector of
:class:`volcal.problem.residuals.IdentificationProblem`, p its data vector with q in rad):

``rows<k>(x, p) -> (rw, A, B, G)``
    weighted residuals rw_i = w_i (model_i - m_i) and Jacobian rows of every reading in
    the local coordinates of phase k: A (n_a x N) the error-parameter part through the
    elimination (J_theta E_theta), B (4 x N) the part of the reading's own station, G
    (6 x N) the frame part.  The C driver sums the normal equations H = sum_i v_i v_i^T,
    g = sum_i v_i rw_i from these (a symmetric rank-one update per reading; a generic
    sparse product of CasADi was four times slower).
``solve<k>(H, g, |r|) -> (dx, gdx, kkt, kkt_rel, step)``
    the Gauss-Newton step of phase k: the rows and columns of the free variables z are
    taken from H, (J_z^T J_z) dz = -J_z^T r is solved with CasADi's ``ldl`` (or ``qr``)
    and dx = E dz; gdx = g^T dz (the directional derivative, for the line search);
    kkt = ||J_z^T r||_inf, the reduced gradient, which equals the KKT stationarity
    residual ||J^T r + C^T lambda|| of the free variables with least-squares multipliers;
    kkt_rel = max_i |g_i| / (||J_z[:, i]|| max(||r||, 1)) (a cosine, independent of units
    and of the data's size); step = ||dx||_inf in scaled units (1 = 1 um or 1 urad): the
    Gauss-Newton estimate of the distance to the minimiser.
``project<k>(x) -> x``
    the start point of phase k: auto-fixed variables set to zero, basic variables from
    the constraints.
``residual(x, p) -> r``
    model minus measured length (mm) of every reading, unweighted.
``constraints(x) -> g``
    C theta in scaled units (the datum constraints; zero at a feasible point).
``station_start(q, t, m) -> (S, rms)``
    start stations (4 x K: x, y, z, dead length, mm) from the nominal points: the linear
    solution of the squared range equations (paper 000, case B) refined by Gauss-Newton
    steps on the sqrt residual (the minimiser Python's ``calibrate_stations(method=
    "sqrt")`` finds); rms: geometric residual RMS per station, mm.
``budget_sigma(q, t, m, S) -> sigma``
    standard uncertainty (mm) of every reading from the exported budget, as
    :func:`volcal.analysis.identify.reading_sigma` (length sources in quadrature, axis
    repeatabilities projected on the beam direction; the derivative of the nominal point
    is exact here, a finite difference in Python).
``model(q, t, theta) -> (p, dp, dp_dtheta, dp_dq)``
    first-order tool point (mm), volumetric error (mm), and their Jacobians, q in file
    units (mm / deg); the Jacobians are returned transposed so that C reads them row-major
    (3 x n_theta and 3 x n_axes).
``error_values(q, theta) -> e``
    the error motions (mm / rad) at a pose, q in file units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
import pandas as pd
import scipy.linalg as sla

from volcal.analysis.identify import Identifier, reading_sigma
from volcal.base.exceptions import InputError
from volcal.measurement.budget import Budget
from volcal.measurement.instruments import get_instrument
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.problem.residuals import IdentificationProblem

#: Gauss-Newton steps of the station start computation (from the linear solution).
STATION_START_STEPS = 8


@dataclass
class Phase:
    """One solve of a strategy: which variables are fixed, which of them are set to zero,
    and the elimination of the constraints (see the module docstring)."""

    name: str
    fixed: np.ndarray  # (n_x,) bool
    zero: np.ndarray  # (n_x,) bool, fixed variables set to 0 before the phase
    # set by :func:`eliminate`
    basic: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # basic variables
    nonbasic: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # free non-basic
    E: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)  # dx = E dz
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)  # projection

    @property
    def n_z(self) -> int:
        return int(len(self.nonbasic))


def eliminate(phase: Phase, Cs: np.ndarray) -> Phase:
    """Fill in the elimination of the scaled constraints Cs x = 0 for a phase."""
    n = Cs.shape[1]
    fixed = phase.fixed
    free = np.flatnonzero(~fixed)
    fixed_idx = np.flatnonzero(fixed)
    A = Cs[:, free] if Cs.shape[0] else np.zeros((0, len(free)))
    A = A[np.linalg.norm(A, axis=1) > 0] if A.shape[0] else A
    rows = np.zeros(0, int)
    if A.shape[0]:
        # independent rows (a row whose free part is a combination of others is implied)
        _, R, piv = sla.qr(A.T, pivoting=True, mode="economic")
        d = np.abs(np.diag(R))
        r = int(np.sum(d > max(A.shape) * np.finfo(float).eps * d[0]))
        rows = np.sort(piv[:r])
    if len(rows):
        Cr = Cs[np.linalg.norm(Cs[:, free], axis=1) > 0][rows]
        A = Cr[:, free]
        _, _, piv = sla.qr(A, pivoting=True, mode="economic")
        basic_loc = np.sort(piv[: len(rows)])
        nonbasic_loc = np.setdiff1d(np.arange(len(free)), basic_loc)
        A_B, A_N = A[:, basic_loc], A[:, nonbasic_loc]
        T = -np.linalg.solve(A_B, A_N)
        F = -np.linalg.solve(A_B, Cr[:, fixed_idx])
        for M in (T, F):  # rounding noise in structurally zero entries
            if M.size:
                M[np.abs(M) < 1e-14 * max(1.0, np.abs(M).max())] = 0.0
    else:
        basic_loc = np.zeros(0, int)
        nonbasic_loc = np.arange(len(free))
        T = np.zeros((0, len(free)))
        F = np.zeros((0, len(fixed_idx)))
    basic, nonbasic = free[basic_loc], free[nonbasic_loc]
    E = np.zeros((n, len(nonbasic)))
    E[nonbasic, np.arange(len(nonbasic))] = 1.0
    E[basic, :] = T
    P = np.eye(n)
    P[basic, :] = 0.0
    P[np.ix_(basic, nonbasic)] = T
    P[np.ix_(basic, fixed_idx)] = F
    P = P @ np.diag((~phase.zero).astype(float))
    phase.basic, phase.nonbasic, phase.E, phase.P = basic, nonbasic, E, P
    if Cs.shape[0]:
        # every direction E z and every projected point satisfies the constraints
        err = max(np.abs(Cs @ E).max(initial=0.0), np.abs(Cs @ P).max(initial=0.0))
        if err > 1e-10 * max(1.0, np.abs(Cs).max()):
            raise RuntimeError(f"constraint elimination failed (residual {err:.2e})")
    return phase


def plan_phases(
    ider: Identifier,
    strategy: str,
    x0: np.ndarray,
    p: np.ndarray,
    user_fixed: np.ndarray,
    *,
    solve: bool,
) -> list[Phase]:
    """The phases of a strategy with the fixed sets :meth:`Identifier.run` uses: it is run
    here as is (with IPOPT when ``solve``, so that a two-phase analysis happens at the
    phase-1 solution exactly as in Python; without solving, at the start point, when the
    plan has no data)."""
    if strategy not in ("joint", "two-phase", "points-only"):
        raise InputError(
            f"strategy {strategy!r} cannot be exported; exportable strategies: "
            "joint, two-phase, points-only"
        )
    is_st, is_th, is_fr = ider.is_station, ider.is_theta, ider.is_frame
    _, _, fixed, _ = ider.run(strategy, x0, p, user_fixed=user_fixed, solve=solve)
    phases: list[Phase] = []
    if strategy == "two-phase":
        # phase 1: stations only, error parameters and frame held at zero
        phases.append(Phase("stations", user_fixed | is_th | is_fr, is_th | is_fr))
    # the final phase: variables held by the analysis start at zero (stations keep theirs)
    phases.append(
        Phase("joint" if strategy == "joint" else "errors", fixed, fixed & ~user_fixed & ~is_st)
    )
    return phases


# ---------------------------------------------------------------------------------------
# CasADi functions


def _dm(M: np.ndarray) -> ca.DM:
    """A sparse DM holding the nonzeros of M."""
    M = np.asarray(M, float)
    if M.ndim == 1:
        M = M[:, None]
    r, c = np.nonzero(M)
    o = np.lexsort((r, c))  # the nonzeros of a DM are stored column by column
    r, c = r[o], c[o]
    return ca.DM(
        ca.Sparsity.triplet(M.shape[0], M.shape[1], r.tolist(), c.tolist()), M[r, c].tolist()
    )


def _dense(f: ca.Function) -> ca.Function:
    """The same function with every output dense: generated C writes the nonzeros of an
    output only, packed, so a structurally sparse output would not be a plain array."""
    if all(f.sparsity_out(i).is_dense() for i in range(f.n_out())):
        return f
    sym: Any = ca.SX if f.is_a("SXFunction") else ca.MX
    args: Any = [sym.sym(f.name_in(i), f.sparsity_in(i)) for i in range(f.n_in())]
    outs = [ca.densify(o) for o in f.call(args)]  # list in, list out
    opts = {"cse": True} if sym is ca.SX else {}
    return ca.Function(f.name(), args, outs, f.name_in(), f.name_out(), opts)


def theta_block(pr: IdentificationProblem, phase: Phase) -> np.ndarray:
    """The theta rows of E restricted to the theta columns of z: (n_theta, n_a)."""
    nt = pr.n_theta
    cols = np.flatnonzero(phase.nonbasic < nt)
    if np.any(np.abs(phase.E[nt:, cols]) > 0) or np.any(np.abs(phase.E[:nt, len(cols) :]) > 0):
        raise RuntimeError("constraints couple error parameters with instrument variables")
    return phase.E[:nt, cols]


def local_free(pr: IdentificationProblem, phase: Phase) -> np.ndarray:
    """Indices into the local normal system [theta_z (n_a), stations (4K), frame (6)] of the
    free (reduced) variables z, in z order."""
    nt = pr.n_theta
    n_a = int(np.sum(phase.nonbasic < nt))
    inst = phase.nonbasic[phase.nonbasic >= nt] - nt
    return np.concatenate([np.arange(n_a), n_a + inst]).astype(int)


def rows_function(pr: IdentificationProblem, phase: Phase, name: str) -> ca.Function:
    """Weighted residuals and Jacobian rows of every reading in the local coordinates of a
    phase: rw (N), A (n_a x N: theta part, through the elimination), B (4 x N: the
    reading's station), G (6 x N: frame).  The normal equations are summed from these in
    the C driver (a symmetric rank-N update is far faster there than a generic sparse
    product), then solved by :func:`solve_function`."""
    m, em, ins, lay = pr.machine, pr.error_model, pr.instrument, pr.layout
    nt, nps, ng, K, N = (
        pr.n_theta,
        ins.n_station_params,
        ins.n_global_params,
        lay.n_stations,
        lay.n_readings,
    )
    Et = theta_block(pr, phase) * pr.scale[:nt, None]
    qs, ts, ths = ca.SX.sym("q", m.n_axes), ca.SX.sym("t", 3), ca.SX.sym("theta", nt)
    ss, gs, ms, ws = ca.SX.sym("s", nps), ca.SX.sym("g", ng), ca.SX.sym("m"), ca.SX.sym("w")
    # the reading model of IdentificationProblem, in physical units
    e = em.values_function()(qs, ths)
    point = m["tool_point_exact" if pr.exact else "tool_point"](qs, ts, e)[0]
    val = ins.reading(point, ss, gs)
    row = ca.jacobian(val, ca.vertcat(ths, ss, gs)).T
    sc_s = ca.DM(pr.scale[nt : nt + nps])
    sc_g = ca.DM(pr.scale[nt + nps * K :])
    one = ca.Function(
        "row1",
        [qs, ts, ths, ss, gs, ms, ws],
        [
            ws * (val - ms),
            ws * ca.mtimes(_dm(Et).T, row[:nt]),
            ws * row[nt : nt + nps] * sc_s,
            ws * row[nt + nps :] * sc_g,
        ],
        {"cse": True},
    )
    xs = ca.MX.sym("x", pr.n_x)
    p = ca.MX.sym("p", pr.nlp["p"].shape[0])
    xp = xs * ca.DM(pr.scale)
    th, sp, g = xp[:nt], xp[nt : nt + nps * K], xp[nt + nps * K :]
    n_ax = m.n_axes
    Q = ca.reshape(p[: n_ax * N], n_ax, N)
    T = ca.reshape(p[n_ax * N : (n_ax + 3) * N], 3, N)
    meas, w = p[(n_ax + 3) * N : (n_ax + 4) * N], p[(n_ax + 4) * N :]
    sel = ca.DM(ca.Sparsity.triplet(K, N, [int(i) for i in lay.station_index], list(range(N))), 1.0)
    SN = ca.densify(ca.mtimes(ca.reshape(sp, nps, K), sel))
    rw, A, B, G = one.map(N)(Q, T, th, SN, g, meas.T, w.T)
    return _dense(ca.Function(name, [xs, p], [rw.T, A, B, G], ["x", "p"], ["rw", "A", "B", "G"]))


def solve_function(
    pr: IdentificationProblem, phase: Phase, name: str, *, linsol: str = "ldl"
) -> ca.Function:
    """Gauss-Newton step of a phase from the local normal equations (H full symmetric,
    column-major, g) and |r|: (dx, gdx, kkt, kkt_rel, step) as described in the module
    docstring."""
    idx = local_free(pr, phase)
    n_h = theta_block(pr, phase).shape[1] + pr.n_x - pr.n_theta
    H, g, rn = ca.MX.sym("H", n_h, n_h), ca.MX.sym("g", n_h), ca.MX.sym("rnorm")
    E = _dm(phase.E)
    if len(idx):
        Hr, gr = H[idx.tolist(), idx.tolist()], g[idx.tolist()]
        dz = -ca.solve(Hr, gr, linsol)
        dx = ca.mtimes(E, dz)
        cn = ca.sqrt(ca.fmax(ca.diag(Hr), 1e-300))
        kkt = ca.mmax(ca.fabs(gr))
        kkt_rel = ca.mmax(ca.fabs(gr) / cn) / ca.fmax(rn, 1.0)
        step = ca.mmax(ca.fabs(dx))
        gdx = ca.dot(gr, dz)
    else:
        dx, kkt, kkt_rel, step, gdx = ca.MX(pr.n_x, 1), ca.MX(0), ca.MX(0), ca.MX(0), ca.MX(0)
    return _dense(
        ca.Function(
            name,
            [H, g, rn],
            [dx, gdx, kkt, kkt_rel, step],
            ["H", "g", "rnorm"],
            ["dx", "gdx", "kkt", "kkt_rel", "step"],
        )
    )


def step_reference(pr: IdentificationProblem, phase: Phase, x: np.ndarray, p: np.ndarray):
    """The step of a phase evaluated in Python from problem.jacobian (for tests): (dx, f,
    kkt, kkt_rel, step) with x scaled."""
    r, J = pr.jacobian(x, p)
    r, J = np.asarray(r).ravel(), np.asarray(ca.densify(J))
    Jz = J @ phase.E
    g = Jz.T @ r
    dz = -np.linalg.solve(Jz.T @ Jz, g)
    dx = phase.E @ dz
    rel = np.abs(g) / np.maximum(np.linalg.norm(Jz, axis=0), 1e-300) / max(np.linalg.norm(r), 1.0)
    return dx, 0.5 * r @ r, np.abs(g).max(), rel.max(), np.abs(dx).max()


def project_function(pr: IdentificationProblem, phase: Phase, name: str) -> ca.Function:
    xs = ca.MX.sym("x", pr.n_x)
    return _dense(ca.Function(name, [xs], [ca.mtimes(_dm(phase.P), xs)], ["x"], ["x_out"]))


def residual_function(pr: IdentificationProblem, name: str) -> ca.Function:
    """Model minus measured length, mm, unweighted (weights replaced by ones)."""
    N = pr.layout.n_readings
    xs = ca.MX.sym("x", pr.n_x)
    p = ca.MX.sym("p", pr.nlp["p"].shape[0])
    p1 = ca.vertcat(p[: p.shape[0] - N], ca.DM.ones(N))
    return _dense(ca.Function(name, [xs, p], [pr.residual(xs, p1)], ["x", "p"], ["r"]))


def constraints_function(pr: IdentificationProblem, name: str) -> ca.Function:
    xs = ca.MX.sym("x", pr.n_x)
    Cs = np.zeros((pr.C.shape[0], pr.n_x))
    Cs[:, : pr.n_theta] = pr.C * pr.scale[None, : pr.n_theta]
    g = ca.mtimes(_dm(Cs), xs) if Cs.shape[0] else ca.MX(1, 1)
    return _dense(ca.Function(name, [xs], [g], ["x"], ["g"]))


def scaled_constraints(pr: IdentificationProblem) -> np.ndarray:
    Cs = np.zeros((pr.C.shape[0], pr.n_x))
    Cs[:, : pr.n_theta] = pr.C * pr.scale[None, : pr.n_theta]
    return Cs


def station_start_function(
    machine: Machine,
    station_index: np.ndarray,
    n_stations: int,
    name: str,
    steps: int = STATION_START_STEPS,
) -> ca.Function:
    """Start stations from the nominal points (see the module docstring).

    Written as per-reading SX functions mapped over all readings and summed per station
    with a constant selection matrix, so that the generated C stays small."""
    N, n_ax, K = len(station_index), machine.n_axes, n_stations
    q, t, m = ca.MX.sym("q", n_ax * N), ca.MX.sym("t", 3 * N), ca.MX.sym("m", N)
    sel = ca.DM(
        ca.Sparsity.triplet(N, K, list(range(N)), [int(i) for i in station_index]), 1.0
    )  # reading -> station (N x K)
    counts = np.bincount(station_index, minlength=K).astype(float)
    P = machine["nominal"].map(N)(ca.reshape(q, n_ax, N), ca.reshape(t, 3, N))  # 3 x N
    c = ca.mtimes(P, sel) / ca.repmat(ca.DM(counts).T, 3, 1)  # 3 x K
    Pc = P - ca.mtimes(c, sel.T)
    # case B (paper 000): 2 Pc.Q + 2 l d - C = |Pc|^2 - l^2; normal equations per station
    ps, ls = ca.SX.sym("P", 3), ca.SX.sym("l")
    a = ca.vertcat(2 * ps, 2 * ls, -1.0)
    b = ca.sumsqr(ps) - ls * ls
    lin = ca.Function("lin", [ps, ls], [ca.vertcat(ca.vec(ca.mtimes(a, a.T)), a * b)])
    Ms = ca.SX.sym("M", 30)
    M, v = ca.reshape(Ms[:25], 5, 5), Ms[25:]
    dsc = 1.0 / ca.sqrt(ca.diag(M))  # unit-diagonal scaling
    y: Any = dsc * ca.solve(M * ca.mtimes(dsc, dsc.T), dsc * v)
    lin_solve = ca.Function("lin_solve", [Ms], [y[:4]], {"cse": True})
    y = lin_solve.map(K)(ca.mtimes(lin.map(N)(Pc, m.T), sel))  # 4 x K
    u: Any = ca.vertcat(y[:3, :] + c, y[3, :])
    # Gauss-Newton on the sqrt residual ||P - Q|| - d - l: the tracker's own reading (its
    # frame motion zero), so the C solver computes the reading the identification fits
    tracker = get_instrument("tracker")
    us = ca.SX.sym("u", 4)
    rr = tracker.reading(ps, us, ca.SX.zeros(tracker.n_global_params)) - ls
    row = ca.jacobian(rr, us).T
    gn = ca.Function(
        "gn", [ps, ls, us], [ca.vertcat(ca.vec(ca.mtimes(row, row.T)), row * rr), rr * rr]
    )
    Hs = ca.SX.sym("H", 20)
    gn_solve = ca.Function(
        "gn_solve", [Hs], [ca.solve(ca.reshape(Hs[:16], 4, 4), Hs[16:])], {"cse": True}
    )
    gnN = gn.map(N)
    for _ in range(steps):
        vals, _ = gnN(P, m.T, ca.mtimes(u, sel.T))
        u = u - gn_solve.map(K)(ca.mtimes(vals, sel))
    _, r2 = gnN(P, m.T, ca.mtimes(u, sel.T))
    rms = ca.sqrt(ca.mtimes(r2, sel) / ca.DM(counts).T).T
    return _dense(ca.Function(name, [q, t, m], [u, rms], ["q", "t", "m"], ["S", "rms"]))


def budget_sigma_function(
    machine: Machine, budget: Budget, station_index: np.ndarray, n_stations: int, name: str
) -> ca.Function:
    """sigma (mm) of every reading from the budget and the start stations."""
    N, n_ax = len(station_index), machine.n_axes
    qs, ts, Ls, Ss = ca.SX.sym("q", n_ax), ca.SX.sym("t", 3), ca.SX.sym("L"), ca.SX.sym("S", 3)
    p0 = machine["nominal"](qs, ts)
    u = p0 - Ss
    u = u / ca.sqrt(ca.sumsqr(u))
    var: Any = 0
    for s in budget.length_sources:
        div = float(s.k or 1.0) if s.distribution == "normal" else np.sqrt(3.0)
        var = var + ((s.magnitude + s.per_metre * ca.fabs(Ls) / 1000.0) * s.scale / div) ** 2
    dpdq = ca.jacobian(p0, qs)
    for k, a in enumerate(machine.spec.axes):
        sig = budget.axis_sigma(a.name)
        if sig:
            var = var + (ca.dot(u, dpdq[:, k]) * sig) ** 2
    one = ca.Function("sigma1", [qs, ts, Ls, Ss], [ca.sqrt(var)], {"cse": True})
    q, t, m = ca.MX.sym("q", n_ax * N), ca.MX.sym("t", 3 * N), ca.MX.sym("m", N)
    S = ca.MX.sym("S", 4, n_stations)
    sel = ca.DM(
        ca.Sparsity.triplet(n_stations, N, [int(i) for i in station_index], list(range(N))), 1.0
    )
    SN = ca.mtimes(S[:3, :], sel)
    sigma_all = one.map(N)(ca.reshape(q, n_ax, N), ca.reshape(t, 3, N), m.T, SN)
    return _dense(ca.Function(name, [q, t, m, S], [sigma_all.T], ["q", "t", "m", "S"], ["sigma"]))


def _deg_factor(machine: Machine) -> np.ndarray:
    return np.array([np.pi / 180.0 if a.is_rotary else 1.0 for a in machine.spec.axes])


def model_function(
    machine: Machine, em: ErrorModel, name: str, *, exact: bool = False
) -> ca.Function:
    """Tool point, volumetric error and Jacobians at one pose (q in file units)."""
    qf, t, th = ca.SX.sym("q", machine.n_axes), ca.SX.sym("t", 3), ca.SX.sym("theta", em.n_params)
    q = qf * ca.DM(_deg_factor(machine))
    e = em.values_function()(q, th)
    p, dp, _ = machine["tool_point_exact" if exact else "tool_point"](q, t, e)
    return _dense(
        ca.Function(
            name,
            [qf, t, th],
            [p, dp, ca.jacobian(dp, th).T, ca.jacobian(p, qf).T],
            ["q", "t", "theta"],
            ["p", "dp", "dp_dtheta", "dp_dq"],
            {"cse": True},
        )
    )


def error_values_function(machine: Machine, em: ErrorModel, name: str) -> ca.Function:
    qf, th = ca.SX.sym("q", machine.n_axes), ca.SX.sym("theta", em.n_params)
    e = em.values_function()(qf * ca.DM(_deg_factor(machine)), th)
    return _dense(ca.Function(name, [qf, th], [e], ["q", "theta"], ["e"], {"cse": True}))


def analysis_sigma(machine: Machine, budget: Budget, meas, st0: np.ndarray) -> np.ndarray:
    """sigma used for the export-time analysis: the table's where given, else the budget's
    (as :func:`volcal.analysis.identify.identify` weights the readings)."""
    sigma = np.array(meas.sigma, float)
    bad = ~np.isfinite(sigma)
    if bad.any():
        sigma[bad] = reading_sigma(machine, budget, meas, st0)[bad]
    return sigma


def stations_frame(ids, st: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "station": list(ids),
            "x_mm": st[:, 0],
            "y_mm": st[:, 1],
            "z_mm": st[:, 2],
            "dead_length_mm": st[:, 3],
        }
    )
