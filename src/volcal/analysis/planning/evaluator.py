"""The predicted uncertainty of a plan, from the identification's own Jacobian.

A :class:`PlanEvaluator` is built once for a machine, an error model, a set of *candidate*
poses, the tool offsets and the number of stations.  Its layout is the full sequential
experiment: every station reads every (candidate pose, tool offset).  A plan is then

* the station positions (K, 3) mm, and
* the selection of candidate poses actually measured (a boolean mask): the readings of
  unselected poses get weight 0, so the same CasADi Jacobian serves every subset.

The Jacobian is :attr:`volcal.problem.residuals.IdentificationProblem.jacobian`, the one the
identification solves with, evaluated at zero errors and the nominal lengths, weighted by
the budget's reading uncertainties.  The datum and the held pivots are chosen once at a
reference design (:meth:`PlanEvaluator.freeze`) as ``identify`` chooses them, so that every
candidate is judged in the same parameterisation.

Criteria (all from the covariance Z (Z^T J^T J Z)^-1 Z^T of the free variables under the
datum, in the solver's scaled units: um for lengths, urad for angles):

* ``"I"`` (default): RMS over the evaluation poses of the total standard uncertainty of the
  volumetric error, um, modulo the rigid motion between stations and machine that no
  multilateration sees (I-optimality: the prediction variance integrated over the
  workspace; independent of the datum);
* ``"A"``: RMS standard uncertainty of the error parameters (scaled units);
* ``"D"``: geometric mean of the standard deviations of the free parameters along the
  principal directions, exp(-log det(M) / (2 r));
* ``"E"``: the standard deviation along the worst-determined direction, 1/sqrt(lambda_min);
* ``"MC"``: paper 004's fitness, the RMS error of the identified volumetric error over
  simulated measurements of the design, each solved linearised (:meth:`Scorer.monte_carlo_rmse`);
* ``"MC-nonlinear"``: the same with every simulated measurement identified by Gauss-Newton
  iterations on the nonlinear residual, as the paper's fitness does (slow: a solve per
  trial).

A design that loses rank (a direction the reference design determined becomes invisible)
scores ``inf``.  :meth:`PlanEvaluator.symbolic_criterion` gives the same criterion as a
CasADi Function of the station coordinates for gradient-based placement.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import scipy.linalg as sla

from volcal.analysis.identifiability import rigid_columns
from volcal.analysis.identify import (
    Identifier,
    axis_sensitivity,
    combined_variance,
    declared_poses,
    field_jacobian,
)
from volcal.measurement.budget import Budget, load_budget
from volcal.measurement.instruments import get_instrument
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.problem.residuals import IdentificationProblem, Layout, NumpyCall, dense_mtimes

__all__ = ["PlanEvaluator", "Scorer", "CRITERIA", "Frozen"]

#: criterion names (see the module docstring)
CRITERIA = ("I", "A", "D", "E", "MC", "MC-nonlinear")


@dataclass
class Frozen:
    """The parameterisation every candidate is judged in: the held variables (user-fixed
    and the reference design's pivots), the datum in force, the orthonormal basis Z of the
    free directions it leaves, and the reference rank."""

    fixed: np.ndarray
    free: np.ndarray
    Z: np.ndarray
    rank: int
    datum_active: np.ndarray
    unidentifiable: list[str]


def _linsol() -> str:
    """CasADi's LAPACK LU where the build has it (M^-1 of the criterion graph), else its own
    sparse QR.  Chosen once."""
    global _LINSOL
    if _LINSOL is None:
        _LINSOL = "qr"
        try:
            m = ca.MX.sym("m", 2, 2)
            ca.Function("t", [m], [ca.solve(m, ca.DM.eye(2), "lapacklu")])
            _LINSOL = "lapacklu"
        except Exception:  # plugin not in this build
            pass
    return _LINSOL


_LINSOL: str | None = None


class PlanEvaluator:
    """Criteria of plans over a candidate pose set (see the module docstring).

    machine, error_model: the model; poses: candidate poses (Np, n_axes) in internal units
    (mm, rad); tools: tool offsets (T, 3) mm; n_stations: K; budget: reading uncertainties;
    eval_poses (internal units) and eval_tools (mm): where the volumetric uncertainty is
    predicted (default: a Halton sample of the travel at every planned tool offset);
    dead_length_mm: the stations' dead length used for the nominal readings."""

    def __init__(
        self,
        machine: Machine,
        error_model: ErrorModel,
        poses: np.ndarray,
        tools: np.ndarray,
        n_stations: int,
        budget: Budget | str = "paper002",
        *,
        eval_poses: np.ndarray | None = None,
        eval_tools: np.ndarray | None = None,
        dead_length_mm: float = 0.0,
    ):
        self.machine, self.error_model = machine, error_model
        self.poses = np.atleast_2d(np.asarray(poses, float))
        self.tools = np.atleast_2d(np.asarray(tools, float))
        self.n_stations = K = int(n_stations)
        self.budget = budget if isinstance(budget, Budget) else load_budget(budget)
        self.dead_length_mm = float(dead_length_mm)
        Np, T = len(self.poses), len(self.tools)
        # reading order: station-major, then tool, then pose (the order they are measured)
        st = np.repeat(np.arange(K), T * Np)
        ti = np.tile(np.repeat(np.arange(T), Np), K)
        pi = np.tile(np.arange(Np), T * K)
        self.station_of, self.tool_of, self.pose_of = st, ti, pi
        self.q = self.poses[pi]
        self.t = self.tools[ti]
        ids = tuple(f"S{k + 1}" for k in range(K))
        self.layout = Layout(st, K, ids, ti * Np + pi)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.identifier = Identifier(machine, error_model, self.layout, solver="gauss-newton")
        self.problem = pr = self.identifier.problem
        self.instrument = get_instrument("tracker")
        # geometry that does not depend on the stations: nominal points, d(point)/d(axis)
        # for the reading uncertainties, and the reflector axis turned with the tool
        self.points, self.dpdq = axis_sensitivity(machine, self.q, self.t)
        # the volumetric error's derivative at the evaluation poses, in scaled variables
        if eval_poses is None:
            eval_poses = declared_poses(machine.spec, 128)
        if eval_tools is None:
            eval_tools = np.unique(self.tools, axis=0)
        eq = np.repeat(np.asarray(eval_poses, float), len(eval_tools), axis=0)
        et = np.tile(np.asarray(eval_tools, float), (len(eval_poses), 1))
        self.eval_q, self.eval_t = eq, et
        p_eval, _, G = field_jacobian(machine, error_model, np.zeros(error_model.n_params), eq, et)
        self.eval_points = p_eval  # nominal points (n_eval, 3) mm
        self.G_eval = G  # (n_eval, 3, n_theta) mm per mm or rad
        Gs = np.zeros((3 * len(eq), pr.n_x))
        Gs[:, : pr.n_theta] = G.reshape(-1, pr.n_theta) * pr.scale[None, : pr.n_theta]
        self._G_scaled = Gs * 1e3  # um per scaled unit
        self.n_eval = len(eq)
        self.frozen: Frozen | None = None
        #: the picklable numeric core; its parameterisation is set by freeze()
        self.scorer = Scorer(self)

    # ---- the data vector (the scorer's, so both sides compute them one way) -----------
    def x(self, stations: np.ndarray) -> np.ndarray:
        """Physical unknowns at zero errors with the stations (K, 3) mm."""
        S = np.column_stack(
            [
                np.asarray(stations, float).reshape(-1, 3),
                np.full(self.n_stations, self.dead_length_mm),
            ]
        )
        return self.problem.pack_x(np.zeros(self.problem.n_theta), S)

    def p(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """The data vector: nominal readings, weights 1/sigma on selected poses, else 0."""
        return self.scorer.p(stations, selected)

    def sigma(self, stations: np.ndarray) -> np.ndarray:
        """Standard uncertainty (mm) of every reading from the budget at these stations."""
        return self.scorer.sigma(stations)

    # ---- the parameterisation ----------------------------------------------------------
    def freeze(self, stations: np.ndarray, selected: np.ndarray | None = None) -> Frozen:
        """Choose the datum and the held pivots at a reference design, as ``identify`` does
        (:meth:`volcal.analysis.identify.Identifier.select_datum`, then the pivots of the
        null directions left); every later evaluation uses them."""
        ider, pr = self.identifier, self.problem
        x, p = self.x(stations), self.p(stations, selected)
        user_fixed = ider.station_fixed(np.zeros(self.n_stations, bool))
        ider.select_datum(x, p, user_fixed)
        ident = ider.analyse(x, p, user_fixed)
        fixed = user_fixed.copy()
        fixed[list(ident.pivots)] = True
        free = np.flatnonzero(~fixed)
        C = ider._scaled_constraints()[:, free]
        C = C[np.linalg.norm(C, axis=1) > 0]
        Z = sla.null_space(C) if len(C) else np.eye(len(free))
        names = [pr.names[i] for i in np.flatnonzero(ident.unidentifiable)]
        self.frozen = Frozen(fixed, free, Z, Z.shape[1], pr.datum_active.copy(), names)
        # the volumetric error is judged modulo the rigid motion no multilateration sees
        # (project it out at the evaluation points): the criterion is then the same
        # whatever datum fixes that motion
        B = self._G_scaled[:, free] @ Z  # (3 n_eval, r)
        R = rigid_columns(self.eval_points - self.eval_points.mean(0))
        R = R / np.linalg.norm(R, axis=0)
        self._B = B - R @ np.linalg.lstsq(R, B, rcond=None)[0]
        self._theta_rows = np.flatnonzero(free < pr.n_theta)
        self.scorer.set_frozen(free, Z, self._B, self._theta_rows)
        return self.frozen

    def information(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """Z^T J^T J Z (r, r) of a design, in the frozen parameterisation."""
        return self.scorer.information(stations, selected)

    def criterion(
        self, stations: np.ndarray, selected: np.ndarray | None = None, criterion: str = "I"
    ) -> float:
        """The criterion of a design (stations (K, 3) mm, selected poses)."""
        return self.scorer.value(self.information(stations, selected), criterion)

    def covariance(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """Covariance of x (physical units; held variables NaN) of a design."""
        fz = self.frozen
        assert fz is not None
        M = self.information(stations, selected)
        Minv = np.linalg.pinv(M, hermitian=True)
        cs = fz.Z @ Minv @ fz.Z.T
        n = self.problem.n_x
        cov = np.full((n, n), np.nan)
        cov[np.ix_(fz.free, fz.free)] = cs
        s = self.problem.scale
        return cov * s[:, None] * s[None, :]

    def volumetric_u(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """Standard uncertainty (n_eval, 3) um of the volumetric error at the evaluation
        poses."""
        fz = self.frozen
        assert fz is not None
        M = self.information(stations, selected)
        L = np.linalg.cholesky(M)
        X = sla.solve_triangular(L, self._B.T, lower=True)  # (r, 3 n_eval)
        return np.sqrt(np.sum(X * X, axis=0)).reshape(-1, 3)

    # ---- symbolic (gradient-based placement) ---------------------------------------------
    def symbolic_criterion(
        self, criterion: str = "I", selected: np.ndarray | None = None
    ) -> ca.Function:
        """``f(s, w) -> criterion^2`` as a CasADi Function of the station coordinates s
        (3K, mm) and the weights w of the selected readings (1/mm) (see
        :meth:`_criterion_graph`)."""
        return self.criterion_functions(criterion, selected)[0]

    def criterion_functions(
        self, criterion: str = "I", selected: np.ndarray | None = None
    ) -> tuple[ca.Function, ca.Function]:
        """:meth:`symbolic_criterion` and ``(s, w) -> (criterion^2, its gradient wrt s
        (3K,), per mm)`` from one graph.  The gradient is written out (see
        :meth:`_criterion_graph`) for IPOPT's ``grad_f``: it equals AD of the first (a
        test checks it) at about half the cost."""
        s, w, f, g = self._criterion_graph(criterion, selected)
        return (
            ca.Function("plan_criterion", [s, w], [f], ["s", "w"], ["f"]),
            ca.Function("plan_criterion_grad", [s, w], [f, g], ["s", "w"], ["f", "grad_s"]),
        )

    def _criterion_graph(
        self, criterion: str = "I", selected: np.ndarray | None = None
    ) -> tuple[ca.MX, ca.MX, ca.MX, ca.MX]:
        """(s, w, f, df/ds): the criterion^2 f as a CasADi expression of the station
        coordinates s (3K, mm) and the weights w of the selected readings (1/mm), for
        gradient-based placement, and its gradient wrt s.

        Only the stations move, so only the instrument's derivatives change: each row of
        the Jacobian is w d(reading)/d(point) G(pose) for the error parameters and
        w d(reading)/d(station) for the station's own columns, with G = d(point)/d(theta)
        of the machine at zero errors (numeric, from the same chain as the problem's) and
        the instrument's derivatives from its one reading expression (AD).  The rows are
        those of the problem's Jacobian (a test checks them against it), on the selected
        readings only, so the derivatives wrt s stay cheap."""
        fz = self.frozen
        assert fz is not None, "call freeze() first"
        pr, ins = self.problem, self.instrument
        K, nt = self.n_stations, pr.n_theta
        keep = np.ones(len(self.pose_of), bool)
        if selected is not None:
            keep = np.asarray(selected, bool)[self.pose_of]
        rows = np.flatnonzero(keep)
        N = len(rows)
        if not hasattr(self, "_G_read"):
            _, _, G = field_jacobian(self.machine, self.error_model, np.zeros(nt), self.q, self.t)
            self._G_read = G * pr.scale[None, None, :nt]  # (N_all, 3, nt) per scaled unit
        G = self._G_read[rows]
        # d(reading)/d(point), d(reading)/d(station) of the instrument, mapped over readings
        ps, ss = ca.SX.sym("p", 3), ca.SX.sym("s", ins.n_station_params)
        gs = ca.SX.sym("g", ins.n_global_params)
        v = ins.reading(ps, ss, gs)
        f_d = ca.Function("d_reading", [ps, ss, gs], [ca.jacobian(v, ps), ca.jacobian(v, ss)])
        nps = ins.n_station_params
        st = self.station_of[rows]
        # the weighted derivatives V (3 + n_ps, N) as a function of (s, w) in SX: a few
        # scalar operations per reading, evaluated without the MX graph's per-node copies
        # of (3 + n_ps) x N matrices (a third of the criterion's time), and their
        # transposed directional derivative (for the gradient) in SX as well
        s_x, w_x = ca.SX.sym("s", 3 * K), ca.SX.sym("w", N)
        St = ca.vertcat(ca.reshape(s_x, 3, K), ca.DM(np.full((1, K), self.dead_length_mm)))
        sel = ca.DM(ca.Sparsity.triplet(K, N, st.tolist(), list(range(N))), 1.0)
        dp, ds = f_d.map(N)(ca.DM(self.points[rows].T), ca.mtimes(St, sel), 0)
        # the map lays the (1, 3) and (1, n_ps) row Jacobians side by side
        V_x = ca.vertcat(ca.reshape(dp, 3, N), ca.reshape(ds, nps, N))
        V_x = V_x * ca.repmat(w_x.T, 3 + nps, 1)
        dV_x = ca.SX.sym("dV", V_x.shape)
        f_V = ca.Function("plan_derivatives", [s_x, w_x], [V_x])
        f_Vt = ca.Function(
            "plan_derivatives_t", [s_x, w_x, dV_x], [ca.jtimes(V_x, s_x, dV_x, True)]
        )
        s = ca.MX.sym("s", 3 * K)
        w = ca.MX.sym("w", N)
        V = f_V(s, w)  # (3 + n_ps, N)
        # A = J[:, free] Z without forming J: the theta columns of a row are
        # w (dp_x G_x + dp_y G_y + dp_z G_z) and a free station parameter j of the row's
        # station adds w ds_j times its row of Z, so A = sum_b diag(w v_b) H_b over the
        # 3 + n_ps rows v_b of (dp; ds), with every H_b (N, r) fixed (numeric): G_c
        # Z_theta, and for ds_j the Z row of parameter j of each reading's station.  One
        # term per instrument derivative (not per station and parameter): the fewest
        # N x r operations, whose adjoints dominate the gradient's cost.
        ZZ = np.zeros((pr.n_x, fz.Z.shape[1]))
        ZZ[fz.free] = fz.Z
        r = ZZ.shape[1]
        H = [G[:, c, :] @ ZZ[:nt] for c in range(3)]
        for j in range(nps):
            i = nt + nps * st + j  # parameter j of each reading's station
            H.append(ZZ[i] * pr.scale[i][:, None])
        used = [b for b, Hb in enumerate(H) if np.any(Hb)]  # all zero: held, or unmoved
        used = self._merge_proportional(f_V, N, H, used)
        # each H_b converted to a CasADi matrix once (about 7 ms for 960 x 70), one node
        # used by A and by the gradient
        H_dm = {b: ca.MX(ca.DM(H[b])) for b in used}
        A: ca.MX = ca.MX(N, r)
        for b in used:
            A = A + ca.repmat(V[b, :].T, 1, r) * H_dm[b]
        M = dense_mtimes(A.T, A)
        # f and the r x r matrix Q with df = -<A Q, dA> (times 2): I and A are
        # trace(M^-1 W) / n, so Q = M^-1 W M^-1 / n; D is det(M)^(-1/r), Q = f M^-1 / r.
        # M^-1 from one LU (LAPACK) and r x r products: two solves through CasADi's own
        # sparse QR took as long as forming M
        Minv = ca.solve(M, ca.DM.eye(r), _linsol())
        if criterion in ("I", "A"):
            if criterion == "I":
                # trace(B M^-1 B^T) = trace(M^-1 B^T B): an r x r right-hand side
                W, n = self._B.T @ self._B, self.n_eval
            else:
                Zt = fz.Z[self._theta_rows]
                W, n = Zt.T @ Zt, max(len(self._theta_rows), 1)
            X = dense_mtimes(Minv, ca.DM(W))
            f = ca.trace(X) / n
            Q = dense_mtimes(X, Minv) / n
        elif criterion == "D":
            f = ca.exp(-ca.log(ca.det(M)) / M.shape[0])
            Q = f * Minv / M.shape[0]
        else:
            raise ValueError(f"criterion {criterion!r} has no smooth form; use I, A or D")
        # the gradient written out rather than left to reverse AD: df/dA = -2 A Q, then
        # df/dv_b per reading = row sums of df/dA * H_b, and the instrument's small
        # derivative map takes it to s.  Two products of N x r by r x r (M and A Q) through
        # the dense kernel, where reverse AD of A^T A takes two more through CasADi's
        # reference loops: about half the cost of an iteration.
        GA = -2.0 * dense_mtimes(A, Q)
        dV = ca.MX(3 + nps, N)
        for b in used:
            dV[b, :] = ca.sum2(GA * H_dm[b]).T
        self._sym_rows = rows
        return s, w, f, f_Vt(s, w, dV)

    def _merge_proportional(
        self, f_V: ca.Function, N: int, H: list[np.ndarray], used: list[int]
    ) -> list[int]:
        """Fold a derivative row v_b that is a fixed multiple c of an earlier one v_a into
        it (H_a += c H_b, b dropped): the tracker's d(reading)/d(station) is minus
        d(reading)/d(point), which halves the N x r terms of A and of the gradient.  The
        proportion is read off the instrument's own derivatives at two sets of stations
        drawn around the points (seeded), exact to rounding or not taken."""
        rng = np.random.default_rng(0)
        c0, ext = self.points.mean(0), np.ptp(self.points, axis=0) + 1.0
        K = self.n_stations
        Vs = [
            np.asarray(f_V((c0 + ext * rng.uniform(-1.5, 1.5, (K, 3))).ravel(), np.ones(N)))
            for _ in range(2)
        ]
        keep: list[int] = []
        for b in used:
            for a in keep:
                va, vb = np.concatenate([V[a] for V in Vs]), np.concatenate([V[b] for V in Vs])
                big = np.abs(va) > 1e-3 * np.abs(va).max()
                if not big.any():
                    continue
                c = float(np.median(vb[big] / va[big]))
                if np.all(np.abs(vb - c * va) <= 1e-12 * (np.abs(vb) + np.abs(c * va) + 1e-300)):
                    H[a] = H[a] + c * H[b]
                    break
            else:
                keep.append(b)
        return keep

    def weights(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """1/sigma (1/mm) of the selected readings (the ``w`` of :meth:`symbolic_criterion`)."""
        w = 1.0 / self.sigma(stations)
        if selected is not None:
            w = w[np.asarray(selected, bool)[self.pose_of]]
        return w

    def describe(self) -> dict[str, Any]:
        return {
            "candidate_poses": len(self.poses),
            "tools": len(self.tools),
            "stations": self.n_stations,
            "readings_if_all_selected": self.layout.n_readings,
            "evaluation_points": self.n_eval,
        }


class Scorer:
    """The numeric core of :class:`PlanEvaluator`: everything a criterion
    evaluation needs and nothing else, picklable (the Jacobian Function travels in
    CasADi's serialised form), so worker processes and Dask workers evaluate candidates
    with exactly the code of this process.  ``run_chunk((start, designs))`` scores a list
    of designs (stations (K, 3) mm, selected mask or None)."""

    def __init__(self, ev: PlanEvaluator, criterion: str = "I"):
        pr = ev.problem
        self.criterion_name = criterion
        self.jac = pr.jacobian
        self.scale = pr.scale.copy()
        self.n_theta, self.n_x = pr.n_theta, pr.n_x
        self.n_stations, self.dead_length_mm = ev.n_stations, ev.dead_length_mm
        self.n_station_params = ev.instrument.n_station_params
        self.n_global = pr.n_x - pr.n_theta - self.n_station_params * ev.n_stations
        self.points, self.dpdq = ev.points, ev.dpdq
        self.station_of, self.pose_of = ev.station_of, ev.pose_of
        self.q, self.t = ev.q, ev.t
        self.budget = ev.budget
        self.axis_names = list(ev.machine.axis_names)
        self.n_eval = ev.n_eval
        # the parameterisation, set by PlanEvaluator.freeze (set_frozen)
        self.free: np.ndarray = np.zeros(0, int)
        self.Z: np.ndarray = np.zeros((0, 0))
        self.B: np.ndarray = np.zeros((0, 0))
        self.B_r: np.ndarray = np.zeros((0, 0))
        self.theta_rows: np.ndarray = np.zeros(0, int)
        self._call: NumpyCall | None = None
        self._info: dict[tuple[bytes, bytes | None], np.ndarray] = {}

    def set_frozen(
        self, free: np.ndarray, Z: np.ndarray, B: np.ndarray, theta_rows: np.ndarray
    ) -> None:
        """The free variables, the basis of the directions the datum leaves, the scaled
        volumetric map B (3 n_eval, r) and the rows of Z that are error parameters."""
        self.free, self.Z, self.B, self.theta_rows = free, Z, B, theta_rows
        self._info = {}  # computed in another parameterisation
        # the I-criterion needs only B^T B = R^T R: ||L^-1 B^T||_F = ||L^-1 R^T||_F with R
        # (at most r x r) from a QR of B, a right-hand side of r columns, not 3 n_eval
        self.B_r = sla.qr(B, mode="r", check_finite=False)[0][: B.shape[1]] if B.size else B

    def _frozen(self) -> None:
        if not len(self.free):
            raise RuntimeError("call PlanEvaluator.freeze() first")

    def __getstate__(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["jac"] = self.jac.serialize()
        d["_call"] = None
        d["_info"] = {}
        return d

    def __setstate__(self, d: dict[str, Any]) -> None:
        d["jac"] = ca.Function.deserialize(d["jac"])
        self.__dict__.update(d)

    def x_scaled(self, stations: np.ndarray) -> np.ndarray:
        S = np.column_stack(
            [
                np.asarray(stations, float).reshape(-1, 3),
                np.full(self.n_stations, self.dead_length_mm),
            ]
        )
        x = np.concatenate([np.zeros(self.n_theta), S.ravel(), np.zeros(self.n_global)])
        return x / self.scale

    def lengths(self, stations: np.ndarray) -> np.ndarray:
        S = np.asarray(stations, float).reshape(-1, 3)[self.station_of]
        return np.linalg.norm(self.points - S, axis=1) + self.dead_length_mm

    def sigma(self, stations: np.ndarray) -> np.ndarray:
        """Standard uncertainty (mm) of every reading from the budget at these stations."""
        S = np.asarray(stations, float).reshape(-1, 3)[self.station_of]
        d = self.points - S
        grad = d / np.linalg.norm(d, axis=1, keepdims=True)
        var = combined_variance(
            self.axis_names, self.budget, self.lengths(stations), grad, self.dpdq
        )
        return np.sqrt(var)

    def p(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """The data vector (the layout of ``IdentificationProblem.pack_data``): poses, tool
        offsets, nominal readings, weights 1/sigma on selected poses and 0 elsewhere."""
        w = 1.0 / self.sigma(stations)
        if selected is not None:
            w = w * np.asarray(selected, bool)[self.pose_of]
        return IdentificationProblem.pack_data(self.q, self.t, self.lengths(stations), w)

    def jacobian(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        if self._call is None:
            self._call = NumpyCall(self.jac)
        return self._call(self.x_scaled(stations), self.p(stations, selected))[1]

    def reduced_jacobian(
        self, stations: np.ndarray, selected: np.ndarray | None = None
    ) -> np.ndarray:
        """J[:, free] Z: the whitened Jacobian in the frozen parameterisation (N, r)."""
        self._frozen()
        return self.jacobian(stations, selected)[:, self.free] @ self.Z

    def information(self, stations: np.ndarray, selected: np.ndarray | None = None) -> np.ndarray:
        """Z^T J^T J Z (r, r) of a design.  The last few are kept: a plan's design is
        scored before and after each search and again for each prediction written (each
        a Jacobian of every candidate reading); the same numbers, computed once."""
        key = (
            np.asarray(stations, float).tobytes(),
            None if selected is None else np.asarray(selected, bool).tobytes(),
        )
        M = self._info.get(key)
        if M is None:
            A = self.reduced_jacobian(stations, selected)
            M = A.T @ A
            if len(self._info) >= 4:
                self._info.pop(next(iter(self._info)))
            self._info[key] = M
        return M.copy()

    @staticmethod
    def _factor(M: np.ndarray) -> np.ndarray | None:
        """Cholesky factor of M, or None when the design lost a direction the reference
        design determined (not positive definite, or numerically so)."""
        try:
            L = np.linalg.cholesky(M)
        except np.linalg.LinAlgError:
            return None
        d = np.diag(L)
        return L if d.min() > 1e-7 * d.max() else None

    def value(self, M: np.ndarray, criterion: str | None = None) -> float:
        """The criterion of an information matrix M (r, r) (module docstring)."""
        criterion = criterion or self.criterion_name
        if criterion.startswith("MC"):  # its expectation: the exchange and the checks use I
            criterion = "I"
        L = self._factor(M)
        if L is None:
            return float("inf")
        d = np.diag(L)
        if criterion == "I":
            X = sla.solve_triangular(L, self.B_r.T, lower=True)
            return float(np.sqrt(np.sum(X * X) / self.n_eval))
        if criterion == "A":
            X = sla.solve_triangular(L, self.Z[self.theta_rows].T, lower=True)
            return float(np.sqrt(np.sum(X * X) / max(len(self.theta_rows), 1)))
        if criterion == "D":
            return float(np.exp(-np.sum(np.log(d)) / len(d)))
        if criterion == "E":
            return float(1.0 / np.sqrt(np.linalg.eigvalsh(M)[0]))
        raise ValueError(f"unknown criterion {criterion!r}; expected one of {CRITERIA}")

    def score(self, stations: np.ndarray, selected: np.ndarray | None = None) -> float:
        if self.criterion_name == "MC":
            return self.monte_carlo_rmse(stations, selected)
        if self.criterion_name == "MC-nonlinear":
            return self.monte_carlo_rmse(stations, selected, nonlinear=True)
        return self.value(self.information(stations, selected))

    #: simulated measurements per design of the MC criterion, and their seed (the same
    #: draws for every design: common random numbers make designs comparable)
    mc_trials: int = 100
    mc_seed: int = 4

    def monte_carlo_rmse(
        self, stations: np.ndarray, selected: np.ndarray | None = None, *, nonlinear: bool = False
    ) -> float:
        """Paper 004's fitness: the RMS error (um) of the identified volumetric error over
        the evaluation poses and ``mc_trials`` simulated measurements of the design, modulo
        the rigid motion no multilateration sees.  Each trial draws the whitened reading
        errors (standard normal) and solves the linearised least-squares problem of the
        design with its Jacobian, so it converges to the I-criterion as the trials grow."""
        A = self.reduced_jacobian(stations, selected)
        L = self._factor(A.T @ A)
        if L is None:
            return float("inf")
        rng = np.random.default_rng(self.mc_seed)
        E = rng.standard_normal((A.shape[0], self.mc_trials))
        if nonlinear:
            delta = self._nonlinear_trials(stations, selected, E)
        else:
            delta = sla.cho_solve((L, True), A.T @ E)  # (r, trials) estimation errors
        err = self.B @ delta  # (3 n_eval, trials) um
        return float(np.sqrt(np.mean(err * err) * 3.0))

    def _nonlinear_trials(
        self, stations: np.ndarray, selected: np.ndarray | None, E: np.ndarray
    ) -> np.ndarray:
        """Estimation errors (r, trials) in the reduced coordinates when every trial is
        identified as paper 004 does: the nominal readings plus sigma times the draws E,
        solved by Gauss-Newton iterations (at most 4, from the truth) of the full nonlinear
        residual with the problem's Jacobian Function."""
        if self._call is None:
            self._call = NumpyCall(self.jac)
        x0 = self.x_scaled(stations)
        p = self.p(stations, selected)
        n = len(self.station_of)
        w = p[-n:]
        sigma = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)
        base = p.copy()
        out = np.zeros((self.Z.shape[1], E.shape[1]))
        for k in range(E.shape[1]):
            pk = base.copy()
            pk[-2 * n : -n] += sigma * E[:, k]  # noisy readings (mm)
            y = np.zeros(self.Z.shape[1])
            for _ in range(4):
                x = x0.copy()
                x[self.free] += self.Z @ y
                r, J = self._call(x, pk)
                A = J[:, self.free] @ self.Z
                step = np.linalg.lstsq(A, -r.ravel(), rcond=None)[0]
                y += step
                if np.linalg.norm(step) <= 1e-10 * (1.0 + np.linalg.norm(y)):
                    break
            out[:, k] = y
        return out

    def run_chunk(self, chunk: tuple[int, list]) -> list[float]:
        _, designs = chunk
        return [self.score(S, sel) for S, sel in designs]
