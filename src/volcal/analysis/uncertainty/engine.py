"""Fast re-solves of one identification problem for many data sets (Monte Carlo).

An IPOPT solve of the bundled example (3,576 readings, 105 unknowns) costs ~0.5 s; ten
thousand of them would take over an hour.  Near its solution the problem is almost
linear, and its structure makes every evaluation cheap:

* with the first-order machine model the tool point is *exactly* linear in the error
  parameters, ``P_i = P0_i + G_i theta`` (``G_i = dP/de (q_i, t_i) B(q_i)``, 3 x n_theta,
  computed once from the machine's CasADi function);
* the reading of sequential multilateration is ``||P_i - Q_eff(s)|| - d_s`` with the
  station ``s`` moved by the (small) frame motion: ``Q_eff = S + t_g + w_g x S``.

:class:`StructuredLSQ` holds these arrays (numpy only: it pickles, and a worker process
never imports CasADi) and solves the *same* nonlinear least-squares problem as the
:class:`~volcal.analysis.identify.Identifier` - same whitened residuals, same datum constraints,
same held variables - for a batch of reading vectors at once:

    x <- x - Z (R^T R)^-1 Z^T J(x)^T r(x)

with ``Z`` an orthonormal basis of the null space of the constraints on the free (scaled)
variables and ``R`` the triangular factor of ``J0 Z``, J0 the Jacobian at the nominal
solution, factorised once.  The gradient ``J(x)^T r(x)`` is exact at every iterate, so the
fixed point is the exact stationary point of the constrained nonlinear problem, not of its
linearisation; the fixed matrix only sets the (linear, here ~1e-5 per iteration) rate.
Iterations stop once the largest step is below ``tol`` (scaled units: 1 = 1 um or
1 urad).  Every batch operation is a dense matrix product over the trials: the tool
points are computed once per distinct pose (every station sees the same poses) and the
readings station by station, in arrays that stay in the cache; the first iteration, at
x_hat, where the residuals are linear in the readings, is one product with a matrix
computed once (see :meth:`StructuredLSQ._first_gradient`).

The readings, their residuals and the Jacobian are the instrument's own reading Function
(:attr:`Instrument.reading_function`) replayed by numpy over all readings at once
(:class:`volcal.model.numpy_tape.NumpyTape`, its derivatives by the tape's reverse sweep):
one definition of the reading.  Only the batched gradient of the iterations
(:meth:`StructuredLSQ._gradient_t`, most of a Monte Carlo run's time) writes the tracker's
reading out in numpy, in place and station by station: evaluating the Function there, mapped
by CasADi (serial: 12-20x this time; just-in-time compiled C: ~4x) or replayed by the tape
(~2.5x: twice the arrays, out of the processor's cache), costs more than the 10 % a Monte
Carlo run may lose (benchmarks/bench_montecarlo.py).  It is compared with the problem's
CasADi functions each time an engine is built (``check``).

:meth:`StructuredLSQ.linear_map` gives the linearised mode: one factorisation, the
estimate's change as ``K @ dm`` for a matrix of reading changes (many right-hand sides).

The exact (non-truncated) machine model is not linear in theta; for it use the IPOPT path
(:func:`volcal.analysis.uncertainty.montecarlo.ipopt_resolve`), which is general and slow.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

from volcal.model.numpy_tape import NumpyTape

__all__ = ["StructuredLSQ", "VolumetricMap", "unpack_data", "BatchSolution"]


def unpack_data(
    n_axes: int, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(q (N, n_axes), t (N, 3), m (N,), w (N,)) from a parameter vector of
    :meth:`volcal.problem.residuals.IdentificationProblem.pack_data`."""
    p = np.asarray(p, float).ravel()
    N = p.size // (n_axes + 5)
    if N * (n_axes + 5) != p.size:
        raise ValueError(
            f"data vector of length {p.size} does not split into readings of {n_axes} axes"
        )
    q = p[: N * n_axes].reshape(N, n_axes)
    t = p[N * n_axes : N * (n_axes + 3)].reshape(N, 3)
    m = p[N * (n_axes + 3) : N * (n_axes + 4)]
    w = p[N * (n_axes + 4) :]
    return q, t, m, w


def _point_model(
    machine, error_model, q: np.ndarray, t: np.ndarray, pose_index: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """P0 (N, 3) and G (N, 3, n_theta) with P = P0 + G theta (first-order model, exact).
    With ``pose_index`` (N,) the model is evaluated once per distinct pose (readings of
    one pose share q and t; the pose's first reading stands for it): the same numbers,
    one evaluation per pose instead of one per reading."""
    if pose_index is not None:
        idx = np.asarray(pose_index, int)
        first = np.full(int(idx.max()) + 1 if idx.size else 0, -1)
        first[idx[::-1]] = np.arange(idx.size)[::-1]
        p0, G = _point_model(machine, error_model, np.asarray(q)[first], np.asarray(t)[first])
        return p0[idx], G[idx]
    p0, _, Je = machine.evaluate(q, t, np.zeros(machine.n_errors))
    return p0, error_model.apply_basis(Je, q)


@dataclass
class VolumetricMap:
    """Volumetric error (first-order model) at fixed poses as a linear map of theta:
    ``dp = G theta`` (mm), G of shape (M, 3, n_theta).  ``q`` (M, n_axes; mm, rad),
    ``tool`` (M, 3) mm, ``points`` (M, 3) nominal tool points (mm)."""

    q: np.ndarray
    tool: np.ndarray
    G: np.ndarray
    points: np.ndarray

    @classmethod
    def build(
        cls, machine, error_model, q: np.ndarray, tool: np.ndarray | None = None
    ) -> VolumetricMap:
        q = np.atleast_2d(np.asarray(q, float))
        tool = (
            np.zeros((len(q), 3))
            if tool is None
            else np.array(np.broadcast_to(np.asarray(tool, float), (len(q), 3)))
        )
        p0, G = _point_model(machine, error_model, q, tool)
        return cls(q, tool, G, p0)

    @property
    def n_points(self) -> int:
        return int(self.G.shape[0])

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        """(M, 3) for theta (n_theta,) or (B, M, 3) for theta (B, n_theta); mm."""
        th = np.asarray(theta, float)
        G2 = self.G.reshape(-1, self.G.shape[2])
        if th.ndim == 1:
            return (G2 @ th).reshape(-1, 3)
        return (th @ G2.T).reshape(th.shape[0], -1, 3)


@dataclass
class BatchSolution:
    """Solutions of a batch: ``x`` (B, n) physical units, ``iterations`` (B,),
    ``step`` (B,) the last step (scaled units), ``converged`` (B,)."""

    x: np.ndarray
    iterations: np.ndarray
    step: np.ndarray
    converged: np.ndarray


@dataclass
class _Station:
    """The readings of one station in the order of their tool points: ``rows`` (n_k,)
    reading indices, ``points`` (n_k,) their points (ascending) or None when the station
    saw every point once (then point j is row j), ``w2`` (n_k, 1) the squared weights and
    ``repeated`` whether a point occurs twice."""

    rows: np.ndarray
    points: np.ndarray | None
    w2: np.ndarray
    repeated: bool


@dataclass
class _Blocks:
    """The readings of a :class:`StructuredLSQ` arranged for the batched gradient: the
    distinct tool points, component-major (P0 (3, U, 1); G2 (3 U, n_theta), rows x of
    every point, then y, then z), the stations (:class:`_Station`) and work arrays reused
    between calls of one batch size (per thread; fresh megabyte-sized temporaries cost
    more than the arithmetic on them)."""

    P0: np.ndarray
    G2: np.ndarray
    stations: list[_Station]
    work: dict = field(default_factory=dict)

    @classmethod
    def build(cls, eng: StructuredLSQ) -> _Blocks:
        N, nt = eng.n_readings, eng.n_theta
        if eng.point_index is not None:
            pt = np.asarray(eng.point_index, int)
        else:  # readings with bit-identical P0 and G share a point
            key = np.concatenate([eng.P0, eng.G.reshape(N, -1)], axis=1)
            pt = np.unique(key, axis=0, return_inverse=True)[1].ravel()
        U = int(pt.max()) + 1 if N else 0
        first = np.full(U, -1)
        first[pt[::-1]] = np.arange(N)[::-1]
        P0 = np.ascontiguousarray(eng.P0[first].T[:, :, None])
        G2 = np.ascontiguousarray(eng.G[first].transpose(1, 0, 2).reshape(3 * U, nt))
        w2 = eng.w**2
        stations = []
        for k in range(eng.n_stations):
            idx = np.flatnonzero(eng.station_index == k)
            idx = idx[np.argsort(pt[idx], kind="stable")]
            pts = pt[idx]
            every = pts.size == U and bool(np.all(pts == np.arange(U)))
            repeated = bool(pts.size > 1 and np.any(pts[1:] == pts[:-1]))
            stations.append(_Station(idx, None if every else pts, w2[idx][:, None], repeated))
        return cls(P0, G2, stations)

    def buffers(self, B: int) -> dict[str, np.ndarray]:
        """Work arrays for a batch of B trials (per thread: two threads may solve at
        once; the last size kept)."""
        import threading

        w = self.work.setdefault(threading.get_ident(), {})
        if w.get("B") != B:
            U = self.P0.shape[1]
            n = max([s.rows.size for s in self.stations] + [0])
            w.clear()
            w.update(
                B=B,
                P=np.empty((3, U, B)),
                VP=np.empty((3, U, B)),
                D=np.empty((3, n, B)),
                L=np.empty((n, B)),
                r=np.empty((n, B)),
                t=np.empty((n, B)),
            )
        return w


@dataclass
class StructuredLSQ:
    """The identification problem of a sequential multilateration data set, in arrays
    (see the module docstring).  Build it with :meth:`build`.

    Variables are those of :class:`volcal.problem.residuals.IdentificationProblem`: theta
    (n_theta), 4 per station (x, y, z, dead length; mm), 6 frame parameters
    (tx, ty, tz mm; rx, ry, rz rad).  ``x_hat`` is the nominal solution, ``fixed`` the
    held variables, ``scale`` the problem's variable scaling.
    """

    P0: np.ndarray  # (N, 3)
    G: np.ndarray  # (N, 3, n_theta)
    w: np.ndarray  # (N,)
    m: np.ndarray  # (N,) nominal readings
    station_index: np.ndarray  # (N,)
    n_stations: int
    x_hat: np.ndarray  # (n,)
    fixed: np.ndarray  # (n,) bool
    scale: np.ndarray  # (n,)
    Z: np.ndarray  # (n_free, n_z)
    R: np.ndarray  # (n_z, n_z) upper triangular, J0 Z = Q R
    names: list[str] = field(default_factory=list)
    #: (N,) the distinct tool point (pose and tool offset) of every reading; None: found
    #: from P0 and G
    point_index: np.ndarray | None = None
    #: the instrument's reading (value only) as a numpy tape: the readings, residuals and
    #: Jacobian evaluate it
    reading: NumpyTape | None = field(default=None, repr=False)
    _J0: np.ndarray | None = field(default=None, repr=False)

    # ---- construction -------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        problem,
        x_hat: np.ndarray,
        p: np.ndarray,
        fixed: np.ndarray,
        *,
        constrained: bool = True,
        check: bool = True,
    ) -> StructuredLSQ:
        """From an :class:`~volcal.problem.residuals.IdentificationProblem`, its solution x_hat
        (physical), the data vector p and the held variables.  With ``check`` the
        residuals and gradient are compared with the problem's CasADi functions (relative
        1e-9), which guards this re-implementation against any change of the model."""
        if getattr(problem, "exact", False):
            raise ValueError(
                "the structured solver needs the first-order machine model "
                "(linear in theta); use the IPOPT path for exact=True"
            )
        ins = problem.instrument
        if ins.n_station_params != 4 or ins.n_global_params != 6:
            raise ValueError(
                f"the structured solver knows sequential multilateration only, "
                f"not {type(ins).__name__}"
            )
        m_ = problem.machine
        q, t, meas, w = unpack_data(m_.n_axes, p)
        pose_index = getattr(problem.layout, "pose_index", None)
        P0, G = _point_model(m_, problem.error_model, q, t, pose_index)
        n, nt = problem.n_x, problem.n_theta
        fixed = np.asarray(fixed, bool).copy()
        free = ~fixed
        C = np.zeros((problem.C.shape[0], n))
        if constrained and problem.C.shape[0]:
            C[:, :nt] = problem.C * problem.scale[None, :nt]
        Cf = C[:, free]
        Cf = Cf[np.linalg.norm(Cf, axis=1) > 0]
        Z = sla.null_space(Cf) if Cf.shape[0] else np.eye(int(free.sum()))
        self = cls(
            P0=P0,
            G=G,
            w=np.array(w),
            m=np.array(meas),
            station_index=np.asarray(problem.layout.station_index, int),
            n_stations=int(problem.layout.n_stations),
            x_hat=np.array(x_hat, float),
            fixed=fixed,
            scale=np.array(problem.scale, float),
            Z=Z,
            R=np.zeros((0, 0)),
            names=list(problem.names),
            point_index=None if pose_index is None else np.asarray(pose_index, int),
            reading=reading_tape(ins),
        )
        J0 = self.jacobian(self.x_hat)
        A = J0[:, free] @ Z
        self.R = np.asarray(np.linalg.qr(A, mode="r"))
        self._J0 = J0
        if check:
            from volcal.problem.residuals import DenseJacobian

            # the problem's own Jacobian (from its CasADi factors; equal to
            # ``problem.jacobian``, tests/test_solvers.py) against this engine's
            xs = problem.to_scaled(self.x_hat)
            r_ca, J_ca = DenseJacobian(problem)(xs, p)
            r_me = self.residuals(self.x_hat[None, :], meas[None, :])[0]
            g_ca = J_ca.T @ r_ca.ravel()
            g_me = self.gradient(self.x_hat[None, :], meas[None, :])[0]
            er = np.max(np.abs(r_me - r_ca.ravel())) / max(1.0, np.max(np.abs(r_ca)))
            eJ = np.max(np.abs(J0 - J_ca)) / max(1.0, np.max(np.abs(J_ca)))
            eg = np.max(np.abs(g_me - g_ca)) / max(1.0, np.max(np.abs(J_ca)) * np.sqrt(len(meas)))
            if max(er, eJ, eg) > 1e-9:
                raise AssertionError(
                    f"structured model differs from the CasADi problem: "
                    f"residuals {er:.2e}, Jacobian {eJ:.2e}, gradient {eg:.2e}"
                )
        return self

    def __getstate__(self):
        d = dict(self.__dict__)  # the reading tape is plain numpy: it pickles
        # large and rebuilt on demand
        for k in ("_J0", "_blocks", "_at_hat"):
            d.pop(k, None)
        d["_J0"] = None
        return d

    # ---- sizes ------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return int(self.x_hat.size)

    @property
    def n_theta(self) -> int:
        return int(self.G.shape[2])

    @property
    def n_readings(self) -> int:
        return int(self.w.size)

    @property
    def free(self) -> np.ndarray:
        return ~self.fixed

    # ---- model ------------------------------------------------------------------------------
    def _split(self, X: np.ndarray):
        nt, K = self.n_theta, self.n_stations
        th = X[:, :nt]
        S = X[:, nt : nt + 4 * K].reshape(-1, K, 4)
        g = X[:, nt + 4 * K :]
        return th, S, g

    def _tape(self) -> NumpyTape:
        if self.reading is None:
            raise ValueError("an engine without its reading tape (StructuredLSQ.build sets it)")
        return self.reading

    def _inputs(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reading tape's inputs at physical X (B, n), per nonzero: tool points
        (3, N, B), every reading's station (4, N, B), frame (6, 1, B)."""
        th, S, g = self._split(X)
        B, N = X.shape[0], self.n_readings
        P = self.P0.T[:, :, None] + (self.G.reshape(3 * N, -1) @ th.T).reshape(N, 3, B).transpose(
            1, 0, 2
        )
        return P, S[:, self.station_index, :].transpose(2, 1, 0), g.T[:, None, :]

    def readings(self, X: np.ndarray) -> np.ndarray:
        """The instrument's readings (B, N), mm, at physical X (B, n)."""
        ((v,),) = self._tape()(*self._inputs(np.atleast_2d(X)))
        return np.array(np.broadcast_to(v, (self.n_readings, np.atleast_2d(X).shape[0])).T)

    def reading_derivatives(
        self, x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At one physical x (n,): the readings (N,) and their derivatives with respect to
        the tool point (N, 3), the reading's station (N, 4) and the frame (N, 6), from the
        reading tape's reverse sweep (the frame given per reading so that its derivative
        stays per reading)."""
        P, S, g = self._inputs(np.asarray(x, float)[None, :])
        N = self.n_readings
        g = np.broadcast_to(g, (g.shape[0], N, 1))
        ((v,),), d = self._tape().vjp((P, S, g), np.ones((N, 1)))

        def cols(parts):
            return np.column_stack([np.broadcast_to(c, (N, 1))[:, 0] for c in parts])

        return np.array(np.broadcast_to(v, (N, 1))[:, 0]), cols(d[0]), cols(d[1]), cols(d[2])

    def beam(self) -> tuple[np.ndarray, np.ndarray]:
        """At x_hat: the unit beam vectors (N, 3) (the reading's derivative with respect to
        the tool point) and the distances (N,) mm (reading + dead length)."""
        v, dp, _, _ = self.reading_derivatives(self.x_hat)
        _, S, _ = self._split(self.x_hat[None, :])
        return dp, v + S[0, self.station_index, 3]

    def residuals(self, X: np.ndarray, M: np.ndarray) -> np.ndarray:
        """Whitened residuals (B, N) at physical X (B, n) for readings M (B, N)."""
        return self.w * (self.readings(X) - M)

    def _structure(self) -> _Blocks:
        """The readings grouped for the batched gradient (built once, not pickled)."""
        blk = getattr(self, "_blocks", None)
        if blk is None:
            blk = self._blocks = _Blocks.build(self)
        return blk

    def _gradient_t(self, X: np.ndarray, MT: np.ndarray) -> np.ndarray:
        """J^T r (B, n) wrt the physical variables at X (B, n) for readings MT (N, B).

        Trial-last layout: every array is (component, points or readings, trials).  The
        tool points are computed once per distinct pose (every station sees the same
        points: one product with the poses' G), then station by station, in the order of
        the points (arrays that stay in the cache, no gather where a station saw every
        point), the beam vectors, residuals and their contributions, which are summed per
        point for the one product with G^T."""
        blk = self._structure()
        B = X.shape[0]
        nt, K = self.n_theta, self.n_stations
        U = blk.P0.shape[1]
        buf = blk.buffers(B)
        th = X[:, :nt]
        S = X[:, nt : nt + 4 * K].reshape(B, K, 4).transpose(1, 2, 0)  # (K, 4, B)
        gl = X[:, nt + 4 * K :]  # (B, 6)
        P = buf["P"]
        np.matmul(blk.G2, th.T, out=P.reshape(3 * U, B))
        P += blk.P0
        Qs = S[:, :3, :]  # (K, 3, B)
        frame = bool(np.any(gl))
        if frame:
            om = gl[:, 3:6].T  # (3, B)
            Qeff = Qs + gl[:, :3].T[None] + np.cross(om[None], Qs, axis=1)
        else:
            Qeff = Qs
        VP = buf["VP"]  # contributions summed per point
        VP.fill(0.0)
        VS = np.empty((K, 3, B))
        wrS = np.empty((K, B))
        for k, st in enumerate(blk.stations):
            n = st.rows.size
            D, L, r, t = buf["D"][:, :n], buf["L"][:n], buf["r"][:n], buf["t"][:n]
            if st.points is None:  # D = P - Q_eff, the beam vectors
                np.subtract(P, Qeff[k][:, None, :], out=D)
            else:
                np.take(P, st.points, axis=1, out=D, mode="clip")
                D -= Qeff[k][:, None, :]
            np.multiply(D[0], D[0], out=L)
            np.multiply(D[1], D[1], out=t)
            L += t
            np.multiply(D[2], D[2], out=t)
            L += t
            np.sqrt(L, out=L)
            np.subtract(L, S[k, 3][None, :], out=r)
            np.take(MT, st.rows, axis=0, out=t, mode="clip")
            r -= t
            r *= st.w2  # w * (w * raw)
            np.divide(r, L, out=L)
            D *= L[None]  # V = r U
            if st.points is None:
                VP += D
            elif not st.repeated:
                VP[:, st.points] += D
            else:
                np.add.at(VP.transpose(1, 0, 2), st.points, D.transpose(1, 0, 2))
            D.sum(axis=1, out=VS[k])
            r.sum(axis=0, out=wrS[k])
        np.negative(VS, out=VS)
        np.negative(wrS, out=wrS)
        g = np.empty((B, self.n))
        g[:, :nt] = (blk.G2.T @ VP.reshape(3 * U, B)).T
        if frame:
            gS = VS - np.cross(om[None], VS, axis=1)
        else:
            gS = VS
        gsta = np.concatenate([gS, wrS[:, None, :]], axis=1)  # (K, 4, B)
        g[:, nt : nt + 4 * K] = gsta.transpose(2, 0, 1).reshape(B, 4 * K)
        g[:, nt + 4 * K : nt + 4 * K + 3] = VS.sum(axis=0).T
        g[:, nt + 4 * K + 3 :] = np.cross(Qs, VS, axis=1).sum(axis=0).T
        return g

    def _gradient(self, X, M):
        X = np.atleast_2d(X)
        return self._gradient_t(X, np.ascontiguousarray(np.atleast_2d(M).T)), None

    def gradient(self, X: np.ndarray, M: np.ndarray) -> np.ndarray:
        """J^T r (B, n) with respect to the *scaled* variables."""
        g, _ = self._gradient(X, M)
        return g * self.scale

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Jacobian (N, n) of the whitened residuals wrt the scaled variables at x."""
        _, dp, ds, dg = self.reading_derivatives(x)
        N, nt, K = self.n_readings, self.n_theta, self.n_stations
        w = self.w[:, None]
        J = np.zeros((N, self.n))
        J[:, :nt] = np.einsum("ni,nip->np", dp * w, self.G)
        rows = np.arange(N)[:, None]
        J[rows, nt + 4 * self.station_index[:, None] + np.arange(4)] = ds * w
        J[:, nt + 4 * K :] = dg * w
        return J * self.scale

    # ---- solving ------------------------------------------------------------------------------
    def _step(self, g_scaled_free: np.ndarray) -> np.ndarray:
        """(B, n_free) scaled step for gradients (B, n_free)."""
        b = g_scaled_free @ self.Z  # (B, n_z)
        y = sla.solve_triangular(self.R, sla.solve_triangular(self.R, b.T, trans="T"))
        return -(self.Z @ y).T

    def solve(
        self,
        M: np.ndarray,
        X0: np.ndarray | None = None,
        *,
        tol: float = 1e-9,
        stall_tol: float = 1e-7,
        max_iter: int = 50,
    ) -> BatchSolution:
        """Exact constrained nonlinear least-squares solutions for readings M (B, N),
        starting from X0 (B, n; default x_hat; fixed variables keep their X0 values).

        A trial has converged when its largest step (scaled units: um, urad) is below
        ``tol``, or - on ill-conditioned problems, where rounding keeps the steps at a few
        1e-9 - when a step below ``stall_tol`` is no smaller than 0.3 times the previous
        one (the iteration has reached rounding level; linear convergence would shrink it
        further)."""
        M = np.atleast_2d(np.asarray(M, float))
        B = M.shape[0]
        X = np.tile(self.x_hat, (B, 1)) if X0 is None else np.array(X0, float)
        free = self.free
        sc = self.scale[free]
        MT = np.ascontiguousarray(M.T)
        active = np.ones(B, bool)
        done = np.zeros(B, bool)
        it = np.zeros(B, int)
        last = np.full(B, np.inf)
        for n_it in range(max_iter):
            idx = np.flatnonzero(active)
            if not idx.size:
                break
            MTa = MT if idx.size == B else np.ascontiguousarray(MT[:, idx])
            g = self._first_gradient(X, MT) if n_it == 0 else self._gradient_t(X[idx], MTa)
            dxs = self._step((g * self.scale)[:, free])
            X[np.ix_(idx, np.flatnonzero(free))] += dxs * sc
            size = np.max(np.abs(dxs), axis=1)
            stalled = (size < stall_tol) & (size > 0.3 * last[idx])
            last[idx] = size
            it[idx] += 1
            ok = (size < tol) | stalled
            done[idx[ok]] = True
            active[idx[ok]] = False
        return BatchSolution(X, it, last, done)

    def prepare(self) -> None:
        """Build the cached arrays of :meth:`solve` now (the grouping of the readings and
        the first iteration's linear map)."""
        self._structure()
        self._hat_arrays()

    def _hat_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(g_hat, A) of :meth:`_first_gradient`, computed once."""
        cached = getattr(self, "_at_hat", None)
        if cached is None:
            J0 = self._J0 if self._J0 is not None else self.jacobian(self.x_hat)
            A = np.ascontiguousarray(((J0 / self.scale[None, :]) * self.w[:, None]).T)
            g_hat = self._gradient_t(self.x_hat[None, :], self.m[:, None])[0]
            cached = self._at_hat = (g_hat, A)
        return cached

    def _first_gradient(self, X: np.ndarray, MT: np.ndarray) -> np.ndarray:
        """The gradient of the first iteration.  At x_hat the residuals are linear in the
        readings (r = w (L(x_hat) - d - m')), so there J^T r = g_hat - A (m' - m) with
        g_hat the gradient at x_hat for the nominal readings m and A = J^T diag(w), both
        computed once: one product instead of the model.  Trials that start elsewhere (held
        variables drawn) take the full gradient."""
        hat = np.all(X == self.x_hat[None, :], axis=1)
        if not hat.any():
            return self._gradient_t(X, MT)
        g_hat, A = self._hat_arrays()
        if hat.all():
            dMT = MT - self.m[:, None]
            return g_hat[None, :] - (A @ dMT).T
        g = np.empty((X.shape[0], self.n))
        g[hat] = self._first_gradient(X[hat], np.ascontiguousarray(MT[:, hat]))
        g[~hat] = self._gradient_t(X[~hat], np.ascontiguousarray(MT[:, ~hat]))
        return g

    def linear_map(self) -> tuple[np.ndarray, np.ndarray]:
        """Linearised mode: (K_m, K_x) with dx = K_m dm + K_x dx_fixed (physical units,
        rows: all variables; K_m (n, N) for reading changes dm (mm), K_x (n, n_fixed) for
        changes of the held variables)."""
        J0 = self._J0 if self._J0 is not None else self.jacobian(self.x_hat)
        free = self.free
        # dx_free(scaled) = -Z H^-1 Z^T J_f^T (dr), dr = -w dm  or  J_fixed dxs_fixed
        A = J0[:, free] @ self.Z
        Y = sla.solve_triangular(self.R, sla.solve_triangular(self.R, A.T, trans="T"))
        P = self.Z @ Y  # (n_free, N): H^-1 J^T
        Km = np.zeros((self.n, self.n_readings))
        Km[free] = (P * self.w[None, :]) * self.scale[free][:, None]
        Kx = np.zeros((self.n, int(self.fixed.sum())))
        Jx = J0[:, self.fixed] / self.scale[self.fixed]  # per physical unit
        Kx[free] = -(P @ Jx) * self.scale[free][:, None]
        Kx[np.flatnonzero(self.fixed), np.arange(int(self.fixed.sum()))] = 1.0
        return Km, Kx

    def covariance(self, sigma_m: np.ndarray | None = None) -> np.ndarray:
        """Linearised covariance (n, n, physical) for independent reading errors of
        standard deviations sigma_m (default 1/w: the weights' own)."""
        Km, _ = self.linear_map()
        s = 1.0 / self.w if sigma_m is None else np.asarray(sigma_m, float)
        A = Km * s[None, :]
        return A @ A.T


def reading_tape(instrument) -> NumpyTape:
    """The instrument's reading (its :attr:`reading_function`'s value, the same expression)
    as a numpy tape."""
    import casadi as ca

    f = instrument.reading_function
    p = ca.SX.sym("p", 3)
    s = ca.SX.sym("s", instrument.n_station_params)
    g = ca.SX.sym("g", instrument.n_global_params)
    v = f(p, s, g)[0]
    return NumpyTape(ca.Function(f"{instrument.name}_value", [p, s, g], [v], {"cse": True}))
