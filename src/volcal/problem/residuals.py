"""The identification as one NLP: variables, whitened residuals, datum constraints.

Variables  x = [theta (error parameters), station parameters (per station, stacked),
               global instrument parameters].
Parameters p = the data: axis positions q (n_axes x N), tool offsets t (3 x N), readings m
               (N), weights w = 1/sigma (N; 0 drops a reading, used by outlier rejection).
Residuals  r = w * (model(q, t, theta, station) - m), one per reading, from a single SX
           function replicated over the readings with ``Function.map``.
Constraints g = C theta, one row per *candidate* datum condition (see :mod:`volcal.model.datum`);
           the rows in force (``datum_active``) are bounded to 0, the others are free, so
           choosing the datum for a data set never rebuilds the solver.

The structure (how many readings, which station each belongs to) is fixed when the
problem is built; the numbers are parameters, so the solver built from it serves every
data set of that layout (Monte Carlo, studies, repeated identifications) without rebuild.
Fixing a variable is done with equal bounds, again without rebuild.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

from volcal.base.linalg import unique_rows
from volcal.base.units import solver_scale
from volcal.measurement.instruments import Instrument
from volcal.model.datum import candidate_conditions
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.model.numpy_call import NumpyCall  # noqa: F401  (its home before model/)


def _dense_kernel() -> str:
    """The BLAS plugin CasADi uses for dense products (``mtimes(.., blas)``, CasADi >= 3.8):
    the OpenBLAS bundled with CasADi ("classic") where the build has it, else BLASFEO, else
    the reference triple loop.  Chosen once.  On one thread the OpenBLAS kernel took 2.2-6x
    less time than BLASFEO on the shapes volcal multiplies (78 x 7500 by 7500 x 90: 9.5 vs
    21 ms; 70 x 960 by 960 x 70: 0.76 vs 1.8 ms; 960 x 70 by 70 x 70: 0.76 vs 4.8 ms, where
    BLASFEO was slower than the reference loop); it runs under the thread limits of
    :mod:`volcal.base.threads`."""
    global _BLAS
    if _BLAS is None:
        _BLAS = "reference"
        for name in ("classic", "blasfeo"):
            try:
                a = ca.DM.ones(2, 2)
                ca.mtimes(a, a, name)
                _BLAS = name
                break
            except Exception:  # plugin not in this build (or an older CasADi)
                continue
    return _BLAS


_BLAS: str | None = None


def dense_mtimes(a, b):
    """a @ b for dense MX operands through CasADi's fastest available BLAS plugin."""
    kernel = _dense_kernel()
    return ca.mtimes(a, b) if kernel == "reference" else ca.mtimes(a, b, kernel)


@dataclass(frozen=True)
class Layout:
    """Structure of a data set: the station (0..n_stations-1) of every reading and, where
    several readings share one commanded pose and tool offset (every station of a
    sequential measurement sees the same poses), the pose (0..n_poses-1) of every reading.
    Without ``pose_index`` every reading is its own pose."""

    station_index: np.ndarray
    n_stations: int
    station_ids: tuple[str, ...] | None = None
    pose_index: np.ndarray | None = None

    @property
    def n_readings(self) -> int:
        return int(len(self.station_index))

    @property
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(pose of every reading, first reading of every pose)."""
        if self.pose_index is None:
            idx = np.arange(self.n_readings)
            return idx, idx
        idx = np.asarray(self.pose_index, int)
        first = np.full(idx.max() + 1, -1)
        first[idx[::-1]] = np.arange(len(idx))[::-1]
        return idx, first

    @classmethod
    def from_measurements(cls, meas) -> Layout:
        """The layout of validated measurements
        (:class:`volcal.measurement.tables.Measurements`), with readings of identical
        commanded pose and tool offset grouped."""
        return cls(
            np.asarray(meas.station_index, int),
            len(meas.station_ids),
            tuple(meas.station_ids),
            cls.group_poses(meas.q_internal, meas.tool),
        )

    @staticmethod
    def group_poses(q: np.ndarray, tool: np.ndarray) -> np.ndarray:
        """Pose index of every reading: readings with identical axis positions and tool
        offset share a pose."""
        return unique_rows(np.hstack([np.asarray(q, float), np.asarray(tool, float)]))[1]


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
    conditions: list = field(init=False, repr=False)
    C_all: np.ndarray = field(init=False, repr=False)
    datum_active: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        m, em, ins, lay = self.machine, self.error_model, self.instrument, self.layout
        n_ax = m.n_axes
        n_ps, n_st, n_g = ins.n_station_params, lay.n_stations, ins.n_global_params
        self.n_theta = em.n_params
        self.n_x = em.n_params + n_ps * n_st + n_g

        # Variables are scaled so that a unit step is a typical uncertainty (1 um, 1 urad,
        # 1 um for stations): IPOPT then sees a Hessian whose conditioning reflects the
        # geometry of the experiment, not the choice of units.
        self.scale = np.concatenate(
            [
                solver_scale(em.param_units),
                np.full(n_ps * n_st, 1e-3),
                solver_scale(ins.global_param_units),
            ]
        )

        # Two SX functions of the *scaled* variables.  Per pose: the actual tool point and
        # its derivative wrt theta (the chain and the error functions, the expensive part,
        # evaluated once per pose whatever the number of stations).  Per reading: the
        # weighted residual of the instrument for that point, with its derivatives.  The
        # Jacobian is then assembled explicitly instead of by AD through the maps.
        nt = em.n_params
        sc = self.scale
        qs, ts, ths = ca.SX.sym("q", n_ax), ca.SX.sym("t", 3), ca.SX.sym("theta", nt)
        e = em.values_function()(qs, ths * ca.DM(sc[:nt]))
        point = m["tool_point_exact" if self.exact else "tool_point"](qs, ts, e)[0]
        # d(point)/d(theta) transposed (nt x 3): mapped over the poses it gives
        # [G_0^T | G_1^T | ...] = G_stack^T, so G_stack is one transpose (no index list)
        f_pose = ca.Function(
            "pose",
            [qs, ts, ths],
            [point, ca.jacobian(point, ths).T],
            ["q", "t", "theta"],
            ["p", "dp_dtheta_T"],
            {"cse": True},
        )
        # the point alone: the objective and the residuals need no derivative (an MX call
        # evaluates every output of the function it calls)
        f_point = ca.Function(
            "point", [qs, ts, ths], [point], ["q", "t", "theta"], ["p"], {"cse": True}
        )
        ps, ss, gs = ca.SX.sym("p", 3), ca.SX.sym("s", n_ps), ca.SX.sym("g", n_g)
        ms, ws = ca.SX.sym("m"), ca.SX.sym("w")
        s_phys = ss * ca.DM(sc[nt : nt + n_ps])
        g_phys = gs * ca.DM(sc[nt + n_ps * n_st :]) if n_g else gs
        res = ws * (ins.reading(ps, s_phys, g_phys) - ms)
        row = ca.jacobian(res, ca.vertcat(ps, ss, gs)).T
        f_read = ca.Function(
            "reading",
            [ps, ss, gs, ms, ws],
            [res, row],
            ["p", "s", "g", "m", "w"],
            ["r", "dr_dpsg"],
            {"cse": True},
        )
        f_res = ca.Function(
            "reading_value",
            [ps, ss, gs, ms, ws],
            [res],
            ["p", "s", "g", "m", "w"],
            ["r"],
            {"cse": True},
        )

        #: the per-pose and per-reading functions, shared by the whole-graph NLP (built
        #: on first use, :attr:`nlp`) and the chunked evaluator (:attr:`chunked`)
        self.f_pose, self.f_point, self.f_read, self.f_res = f_pose, f_point, f_read, f_res

        self.conditions = candidate_conditions(em, em.datum)
        self.C_all = (
            np.array([c.row for c in self.conditions]) if self.conditions else np.zeros((0, nt))
        )
        # until a datum is selected for the data at hand, every candidate is in force
        self.datum_active = np.ones(len(self.conditions), bool)

        self.names = list(em.param_names)
        self.units = list(em.param_units)
        for k in range(n_st):
            sid = lay.station_ids[k] if lay.station_ids else f"station{k}"
            self.names += [f"{sid}.{nm}" for nm in ins.station_param_names]
            self.units += ["mm"] * n_ps
        self.names += list(ins.global_param_names)
        self.units += list(ins.global_param_units)

    # ---- the whole-graph NLP (built on first use) -----------------------------------------
    def release_graph(self) -> None:
        """Free the graph of every reading (:attr:`_graph`, :attr:`jacobian`): built again,
        the same, if asked for again."""
        self.__dict__.pop("_graph", None)
        self.__dict__.pop("jacobian", None)

    @cached_property
    def _graph(self) -> dict:
        """The CasADi graph of every reading: the NLP for IPOPT and the whole-problem
        Functions.  Its sparsity and index lists are per reading (about 3.4 kB a reading
        in CasADi's objects: 0.7 GB at 2 x 10^5 readings), so it is built only when one of
        them is asked for (IPOPT, code generation, the planning criteria); the
        Gauss-Newton solver and the analyses evaluate the same residuals, J^T r, J^T J and
        R factor in fixed-size chunks of poses (:attr:`chunked`) without it."""
        m, em, ins, lay = self.machine, self.error_model, self.instrument, self.layout
        n_ax, N = m.n_axes, lay.n_readings
        n_ps, n_st, n_g = ins.n_station_params, lay.n_stations, ins.n_global_params
        nt = em.n_params
        f_pose, f_point, f_read, f_res = self.f_pose, self.f_point, self.f_read, self.f_res
        out: dict = {}
        # all readings in MX (x is the scaled variable vector)
        xs = ca.MX.sym("x", self.n_x)
        th = xs[:nt]
        sp = xs[nt : nt + n_ps * n_st]
        g = xs[nt + n_ps * n_st :]
        Q, T = ca.MX.sym("q", n_ax, N), ca.MX.sym("t", 3, N)
        meas, w = ca.MX.sym("m", N), ca.MX.sym("w", N)
        p = ca.vertcat(ca.vec(Q), ca.vec(T), meas, w)
        st_idx = np.asarray(lay.station_index, int)
        pose_idx, first = lay.poses
        Np = len(first)
        sel = ca.DM(ca.Sparsity.triplet(n_st, N, [int(i) for i in st_idx], list(range(N))), 1.0)
        S = ca.mtimes(ca.reshape(sp, n_ps, n_st), sel)
        P, GT = f_pose.map(Np)(Q[:, first.tolist()], T[:, first.tolist()], th)
        Pr = P[:, pose_idx.tolist()]  # the point of every reading
        r_row, rows = f_read.map(N)(Pr, S, g, meas.T, w.T)
        r = r_row.T
        # the same residuals without derivatives, for the objective and ``residual``
        P_val = f_point.map(Np)(Q[:, first.tolist()], T[:, first.tolist()], th)
        r_val = f_res.map(N)(P_val[:, pose_idx.tolist()], S, g, meas.T, w.T).T

        # J = [D G_stack | station columns | global columns]: D (N x 3 Np) holds each
        # reading's d(r)/d(point) in the columns of its pose, G_stack (3 Np x nt) the
        # poses' d(point)/d(theta).
        ar = np.arange(N)
        cols = (3 * pose_idx[:, None] + np.arange(3)[None, :]).ravel()
        D = ca.MX(
            ca.Sparsity.triplet(N, 3 * Np, np.repeat(ar, 3).tolist(), cols.tolist()),
            ca.vec(rows[:3, :])[
                self._csc_order(N, 3 * Np, np.repeat(ar, 3), cols, np.arange(3 * N))
            ],
        )
        Gs = GT.T  # G_stack (3 n_poses, nt), shared with the Hessian
        # station and global columns: one nonzero per row per variable
        rr = np.concatenate([ar] * (n_ps + n_g))
        cc = np.concatenate(
            [nt + n_ps * st_idx + k for k in range(n_ps)]
            + [np.full(N, nt + n_ps * n_st + j) for j in range(n_g)]
        )
        src = np.concatenate([(3 + v) + ar * (3 + n_ps + n_g) for v in range(n_ps + n_g)])
        J_rest = ca.MX(
            ca.Sparsity.triplet(N, self.n_x, rr.tolist(), cc.tolist()),
            ca.vec(rows)[self._csc_order(N, self.n_x, rr, cc, src)],
        )
        Jr = J_rest[:, nt:]
        out["residual"] = ca.Function("residual", [xs, p], [r_val], ["x", "p"], ["r"])
        # The whole Jacobian J = [D G_stack | J_rest] is built only when asked for
        # (:attr:`jacobian`): its sparsity pattern alone holds N n_theta indices (50 MB at
        # 3 x 10^4 readings, several times over through its products and transpose).  The
        # solvers and the analyses use its factors: J^T r and J^T J below, and the dense J
        # assembled in numpy from the factors (:class:`DenseJacobian`).
        out["_jacobian_graph"] = (xs, p, r, D, Gs, Jr)
        out["jacobian_parts"] = ca.Function(
            "jacobian_parts",
            [xs, p],
            [r, ca.densify(Gs), rows],
            ["x", "p"],
            ["r", "G", "rows"],
        )

        Cs = self.C_all * self.scale[None, :nt]
        gvec = ca.mtimes(ca.DM(Cs), xs[: em.n_params]) if self.C_all.shape[0] else ca.MX(0, 1)
        out["nlp"] = {"x": xs, "p": p, "f": 0.5 * ca.sumsqr(r_val), "g": gvec}
        # gradient of 0.5 ||r||^2 from the explicit Jacobian: J^T r, instead of reverse AD
        # through the map (which cost half of a small solve), through J's factors:
        # J^T r = [G_stack^T (D^T r); J_rest^T r]
        Dt = D.T
        Jt_r = ca.vertcat(ca.mtimes(GT, ca.mtimes(Dt, r)), ca.mtimes(Jr.T, r))
        out["grad_f"] = ca.Function(
            "nlp_grad_f",
            [xs, p],
            [0.5 * ca.sumsqr(r), Jt_r],
            ["x", "p"],
            ["f", "grad_f_x"],
        )
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", gvec.shape[0])
        # Gauss-Newton Hessian of the Lagrangian (constraints are linear: no curvature),
        # H = J^T J assembled from the structure of J instead of a generic sparse product
        # (20-30x slower here): with D the readings' d(r)/d(point) and G_stack the poses'
        # d(point)/d(theta),
        #   [H_tt | H_tr] = G_stack^T [(D^T D) G_stack | D^T J_rest]   (D^T D block-diagonal,
        #                   3x3 per pose): one dense product through CasADi's BLAS plugin
        #   H_rr = J_rest^T J_rest             one nonzero per row per variable
        # so the flops are 3 n_poses n_theta^2 (not N n_theta^2), all in CasADi: the
        # Function can be expanded, serialised and code-generated.
        right = ca.densify(ca.horzcat(ca.mtimes(ca.mtimes(Dt, D), Gs), ca.mtimes(Dt, Jr)))
        H_top = dense_mtimes(GT, right)  # [H_tt | H_tr] in one product
        H_tt, H_tr = H_top[:, :nt], H_top[:, nt:]
        H_rr = ca.mtimes(Jr.T, Jr)
        H = ca.blockcat([[H_tt, H_tr], [H_tr.T, H_rr]])
        out["hess_lag"] = ca.Function(
            "nlp_hess_l",
            [xs, p, lam_f, lam_g],
            [ca.triu(lam_f * ca.densify(H))],
            ["x", "p", "lam_f", "lam_g"],
            ["triu_hess_gamma_x_x"],
        )
        #: H = J^T J alone (for the Gauss-Newton solver and the analyses)
        out["gram"] = ca.Function(
            "gram", [xs, p], [r, Jt_r, ca.densify(H)], ["x", "p"], ["r", "g", "H"]
        )
        return out

    @property
    def residual(self) -> ca.Function:
        """``(x, p) -> r``: the whitened residuals (whole graph, built on first use)."""
        return self._graph["residual"]

    @property
    def jacobian_parts(self) -> ca.Function:
        """``(x, p) -> (r, G, rows)``: J's factors (whole graph, built on first use)."""
        return self._graph["jacobian_parts"]

    @property
    def nlp(self) -> dict:
        """The NLP {x, p, f, g} for ``nlpsol`` (whole graph, built on first use)."""
        return self._graph["nlp"]

    @property
    def grad_f(self) -> ca.Function:
        """``(x, p) -> (f, J^T r)`` (whole graph, built on first use)."""
        return self._graph["grad_f"]

    @property
    def hess_lag(self) -> ca.Function:
        """IPOPT's Gauss-Newton Hessian of the Lagrangian (whole graph, on first use)."""
        return self._graph["hess_lag"]

    @property
    def gram(self) -> ca.Function:
        """``(x, p) -> (r, J^T r, J^T J)`` (whole graph, built on first use)."""
        return self._graph["gram"]

    @property
    def n_p(self) -> int:
        """Length of the data vector p (:meth:`pack_data`)."""
        return (self.machine.n_axes + 5) * self.layout.n_readings

    @cached_property
    def chunked(self):
        """The residuals, J^T r, J^T J and R factor evaluated in fixed-size chunks of poses
        (:class:`volcal.problem.chunked.ChunkedEvaluator`), without the whole graph."""
        from volcal.problem.chunked import ChunkedEvaluator

        return ChunkedEvaluator(self)

    @cached_property
    def jacobian(self) -> ca.Function:
        """``(x, p) -> (r, J)``: the whitened residuals and their Jacobian wrt the scaled
        variables, as one CasADi Function (for code generation and symbolic use, e.g. the
        planning criteria); built on first use.  Numerically, :class:`DenseJacobian` gives
        the same J from :attr:`jacobian_parts` at a fraction of the memory."""
        xs, p, r, D, Gs, Jr = self._graph["_jacobian_graph"]
        J = ca.horzcat(ca.mtimes(D, Gs), Jr)
        return ca.Function("jacobian", [xs, p], [r, J], ["x", "p"], ["r", "J"])

    def fingerprint(self) -> str:
        """A hash of the problem's structure: unknowns (names), the datum candidates, the
        layout (station and pose of every reading), the instrument and the model variant.
        A saved solver state applies to a rebuilt problem only when the fingerprints
        agree."""
        import hashlib

        h = hashlib.sha256()
        for part in (
            self.machine.spec.name,
            self.instrument.name,
            str(self.exact),
            "|".join(self.names),
        ):
            h.update(part.encode())
        h.update(np.ascontiguousarray(self.C_all, float).tobytes())
        h.update(np.ascontiguousarray(self.layout.station_index, np.int64).tobytes())
        h.update(np.ascontiguousarray(self.layout.poses[0], np.int64).tobytes())
        return h.hexdigest()[:16]

    # ---- the datum in force ------------------------------------------------------------
    @property
    def C(self) -> np.ndarray:
        """The datum conditions in force, (c, n_theta) on theta (mm, rad)."""
        return self.C_all[self.datum_active]

    @property
    def constraint_labels(self) -> list[str]:
        return [c.label for c, a in zip(self.conditions, self.datum_active) if a]

    def set_datum(self, active: np.ndarray) -> None:
        """Put the candidate conditions where ``active`` is True in force (no rebuild)."""
        active = np.asarray(active, bool)
        if active.shape != (len(self.conditions),):
            raise ValueError(f"expected {len(self.conditions)} datum flags, got {active.shape}")
        self.datum_active = active.copy()

    def g_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lbg, ubg) of the NLP: 0 for conditions in force, unbounded for the others."""
        lb = np.where(self.datum_active, 0.0, -np.inf)
        ub = np.where(self.datum_active, 0.0, np.inf)
        return lb, ub

    # ---- graph helpers ----------------------------------------------------------------
    @staticmethod
    def _csc_order(
        nrow: int, ncol: int, rr: np.ndarray, cc: np.ndarray, src: np.ndarray
    ) -> list[int]:
        """Indices into a nonzero source vector, in the column-major order CasADi stores a
        matrix built from triplets (rr, cc) whose values sit at positions src."""
        order = np.lexsort((rr, cc))
        return np.asarray(src)[order].tolist()

    # ---- packing ------------------------------------------------------------------------
    @staticmethod
    def pack_data(q: np.ndarray, t: np.ndarray, m: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Parameter vector p from q (N, n_axes), t (N, 3), readings m (N,), weights w (N,)."""
        return np.concatenate(
            [
                np.asarray(q, float).ravel(),
                np.asarray(t, float).ravel(),
                np.asarray(m, float),
                np.asarray(w, float),
            ]
        )

    def pack_x(self, theta: np.ndarray, stations: np.ndarray, glob: np.ndarray | None = None):
        """x from theta (n_theta,), stations (n_stations, n_station_params), globals."""
        glob = np.zeros(self.instrument.n_global_params) if glob is None else glob
        return np.concatenate([theta, np.asarray(stations, float).ravel(), glob])

    def unpack_x(self, x: np.ndarray):
        """(theta, stations (n_stations, n_station_params), globals) from x."""
        x = np.asarray(x, float).ravel()
        nt, nps, ns = self.n_theta, self.instrument.n_station_params, self.layout.n_stations
        return x[:nt], x[nt : nt + nps * ns].reshape(ns, nps), x[nt + nps * ns :]

    def to_scaled(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, float) / self.scale

    def from_scaled(self, xs: np.ndarray) -> np.ndarray:
        return np.asarray(xs, float).ravel() * self.scale

    def theta_slice(self) -> slice:
        return slice(0, self.n_theta)

    def station_slice(self) -> slice:
        nps, ns = self.instrument.n_station_params, self.layout.n_stations
        return slice(self.n_theta, self.n_theta + nps * ns)


class DenseJacobian:
    """``(x_scaled, p) -> (r, J)`` as numpy arrays: the problem's whitened residuals (N,)
    and dense Jacobian (N, n_x) wrt the scaled variables, assembled from
    :attr:`IdentificationProblem.jacobian_parts` (the poses' d(point)/d(theta), each
    reading's d(r)/d(point, station, globals)).  The same numbers as
    ``problem.jacobian`` without its sparsity pattern of N n_theta indices.  Not
    thread-safe: one object per thread."""

    def __init__(self, problem: IdentificationProblem) -> None:
        self._call = NumpyCall(problem.jacobian_parts)
        lay = problem.layout
        self._pose = np.asarray(lay.poses[0], np.intp)
        st = np.asarray(lay.station_index, np.intp)
        self._station, self._n_st = st, lay.n_stations
        self._nt, self._n_x = problem.n_theta, problem.n_x
        n_ps = problem.instrument.n_station_params
        n_st = lay.n_stations
        self._n_ps = n_ps
        # column of every station / global derivative row, per reading
        self._rest_cols = [problem.n_theta + n_ps * st + k for k in range(n_ps)] + [
            np.full(len(st), problem.n_theta + n_ps * n_st + j)
            for j in range(problem.instrument.n_global_params)
        ]

    def __call__(self, xs: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, G, rows = self._call(xs, p)
        Gp = G.reshape(-1, 3, self._nt)  # (n_poses, 3, nt): row 3 k + c of G_stack
        return np.asarray(r).ravel(), self._block(Gp, rows, slice(0, len(self._pose)))

    def _block(self, Gp: np.ndarray, rows: np.ndarray, sl: slice) -> np.ndarray:
        """The rows ``sl`` of J from the poses' G (n_poses, 3, nt) and the readings' rows."""
        nt = self._nt
        pose = self._pose[sl]
        J = np.zeros((len(pose), self._n_x))
        Jt = J[:, :nt]
        for c in range(3):  # J_theta = sum_c d(r)/d(p_c) * d(p_c)/d(theta) of its pose
            Jt += rows[c][sl, None] * Gp[pose, c, :]
        ar = np.arange(len(pose))
        for k, cols in enumerate(self._rest_cols):
            J[ar, cols[sl]] = rows[3 + k][sl]
        return J

    def r_factor(
        self, xs: np.ndarray, p: np.ndarray, block_rows: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(r, R)``: the whitened residuals (N,) and the R factor (n_x, n_x) of the dense
        Jacobian (``J = Q R``), assembled and factorised in blocks of ``block_rows``
        readings (default: about 16 MB of J per block) so that J itself is never held
        (:class:`volcal.base.linalg.StackedQR`).  Everything the analyses take from J
        (column norms, singular values, null space, covariance) follows from R.

        A reading's row is zero in the columns of every other station, so the readings
        are factorised station by station on their nonzero columns only (error
        parameters, their station's, the globals) and the stations' triangles then
        together: an orthogonal reduction as well (the same R up to row signs and
        rounding), with (n_theta + n_station_params + n_globals)^2 flops per reading
        instead of n_x^2."""
        from volcal.base.linalg import StackedQR

        r, G, rows = self._call(xs, p)
        nt = self._nt
        Gp = G.reshape(-1, 3, nt)
        n_rest = len(self._rest_cols)
        width = nt + n_rest  # the nonzero columns of a reading
        step = int(block_rows or max(2048, (1 << 21) // max(width, 1)))
        order = np.argsort(self._station, kind="stable")
        st_sorted = self._station[order]
        pose, rows = self._pose[order], np.asarray(rows)[:, order]
        n_st = int(self._n_st)
        bounds = np.searchsorted(st_sorted, np.arange(n_st + 1))
        top = StackedQR(self._n_x)
        for k in range(n_st):
            acc = StackedQR(width, expected_rows=len(order))
            for start in range(int(bounds[k]), int(bounds[k + 1]), step):
                sl = slice(start, min(start + step, int(bounds[k + 1])))
                Jb = np.zeros((sl.stop - sl.start, width))
                Jt = Jb[:, :nt]
                for c in range(3):
                    Jt += rows[c][sl, None] * Gp[pose[sl], c, :]
                Jb[:, nt:] = rows[3 : 3 + n_rest, sl].T
                acc.add(Jb)
            if acc.rows:
                cols = np.concatenate(
                    [
                        np.arange(nt),
                        nt + self._n_ps * k + np.arange(self._n_ps),
                        nt + self._n_ps * n_st + np.arange(n_rest - self._n_ps),
                    ]
                )
                Rk = np.zeros((width, self._n_x))
                Rk[:, cols] = acc.R
                top.add(Rk)
        return np.asarray(r).ravel(), top.R
