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
1 urad).  Every batch operation is a dense matrix product over the trials.

:meth:`StructuredLSQ.linear_map` gives the linearised mode: one factorisation, the
estimate's change as ``K @ dm`` for a matrix of reading changes (many right-hand sides).

The exact (non-truncated) machine model is not linear in theta; for it use the IPOPT path
(:func:`volcal.analysis.uncertainty.montecarlo.ipopt_resolve`), which is general and slow.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

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
    machine, error_model, q: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """P0 (N, 3) and G (N, 3, n_theta) with P = P0 + G theta (first-order model, exact)."""
    p0, _, Je = machine.evaluate(q, t, np.zeros(machine.n_errors))
    B = error_model.basis(q)
    G = np.einsum("nik,nkp->nip", Je, B)
    return p0, G


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
        P0, G = _point_model(m_, problem.error_model, q, t)
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
        )
        J0 = self.jacobian(self.x_hat)
        A = J0[:, free] @ Z
        self.R = np.asarray(np.linalg.qr(A, mode="r"))
        self._J0 = J0
        if check:
            import casadi  # noqa: F401  (only to fail clearly if unavailable)

            xs = problem.to_scaled(self.x_hat)
            r_ca, J_ca = (v.full() for v in problem.jacobian(xs, p))
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
        d = dict(self.__dict__)
        # large and rebuilt on demand
        for k in ("_J0", "_ind", "_w2"):
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

    def _geometry(self, X: np.ndarray):
        """Per reading (B, N, 3) beam vector D = P - Q_eff, lengths L (B, N), stations."""
        th, S, g = self._split(X)
        B = X.shape[0]
        N = self.n_readings
        P = self.P0[None] + (th @ self.G.reshape(3 * N, -1).T).reshape(B, N, 3)
        Qs = S[:, :, :3]
        Qeff = Qs + g[:, None, :3] + np.cross(g[:, None, 3:6], Qs)
        D = P - Qeff[:, self.station_index, :]
        L = np.sqrt(np.einsum("bni,bni->bn", D, D))
        return D, L, S

    def residuals(self, X: np.ndarray, M: np.ndarray) -> np.ndarray:
        """Whitened residuals (B, N) at physical X (B, n) for readings M (B, N)."""
        D, L, S = self._geometry(np.atleast_2d(X))
        return self.w * (L - S[:, self.station_index, 3] - M)

    def _gradient_t(self, X: np.ndarray, MT: np.ndarray) -> np.ndarray:
        """J^T r (B, n) wrt the physical variables at X (B, n) for readings MT (N, B).

        Trial-last layout: every array is (readings, ..., trials), so that the model is two
        dense products with G and a few passes over contiguous memory."""
        B = X.shape[0]
        N, nt, K = self.n_readings, self.n_theta, self.n_stations
        G2 = self.G.reshape(3 * N, nt)
        th = X[:, :nt]
        S = X[:, nt : nt + 4 * K].reshape(B, K, 4).transpose(1, 2, 0)  # (K, 4, B)
        gl = X[:, nt + 4 * K :]  # (B, 6)
        P = (G2 @ th.T).reshape(N, 3, B)
        P += self.P0[:, :, None]
        Qs = S[:, :3, :]  # (K, 3, B)
        frame = bool(np.any(gl))
        if frame:
            om = gl[:, 3:6].T  # (3, B)
            Qeff = Qs + gl[:, :3].T[None] + np.cross(om[None], Qs, axis=1)
        else:
            Qeff = Qs
        idx = self.station_index
        P -= Qeff[idx]  # D, (N, 3, B)
        D = P
        L = np.sqrt(D[:, 0] ** 2 + D[:, 1] ** 2 + D[:, 2] ** 2)  # (N, B)
        r = L - S[idx, 3, :]
        r -= MT
        wr = r * self.w2[:, None]  # w * (w * raw)
        coef = wr / L
        D *= coef[:, None, :]  # V = r U, (N, 3, B)
        V = D
        g = np.empty((B, self.n))
        g[:, :nt] = (G2.T @ V.reshape(3 * N, B)).T
        Ind = self._indicator()
        VS = -(Ind @ V.reshape(N, 3 * B)).reshape(K, 3, B)
        wrS = -(Ind @ wr)  # (K, B)
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

    @property
    def w2(self) -> np.ndarray:
        w2 = getattr(self, "_w2", None)
        if w2 is None:
            w2 = self._w2 = self.w**2
        return w2

    def gradient(self, X: np.ndarray, M: np.ndarray) -> np.ndarray:
        """J^T r (B, n) with respect to the *scaled* variables."""
        g, _ = self._gradient(X, M)
        return g * self.scale

    def _indicator(self) -> np.ndarray:
        ind = getattr(self, "_ind", None)
        if ind is None or ind.shape != (self.n_stations, self.n_readings):
            ind = np.zeros((self.n_stations, self.n_readings))
            ind[self.station_index, np.arange(self.n_readings)] = 1.0
            self._ind = ind
        return ind

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Jacobian (N, n) of the whitened residuals wrt the scaled variables at x."""
        x = np.asarray(x, float)[None, :]
        D, L, S = self._geometry(x)
        U = (D / L[:, :, None])[0] * self.w[:, None]  # (N, 3)
        N, nt, K = self.n_readings, self.n_theta, self.n_stations
        J = np.zeros((N, self.n))
        J[:, :nt] = np.einsum("ni,nip->np", U, self.G)
        _, S_, gl = self._split(x)
        om = gl[0, 3:6]
        # Q_eff = S + t + om x S:  dr/dS = -U^T (I + [om]x) = -(U + U x om)^T,
        # dr/dt = -U^T, dr/dom = U^T [S]x = (U x S)^T
        dS = -(U + np.cross(U, om))
        cols = nt + 4 * self.station_index
        rows = np.arange(N)
        for k in range(3):
            J[rows, cols + k] = dS[:, k]
        J[rows, cols + 3] = -self.w
        J[:, nt + 4 * K : nt + 4 * K + 3] = -U
        J[:, nt + 4 * K + 3 :] = -np.cross(S_[0, self.station_index, :3], U)
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
        for _ in range(max_iter):
            idx = np.flatnonzero(active)
            if not idx.size:
                break
            g = self._gradient_t(X[idx], MT if idx.size == B else np.ascontiguousarray(MT[:, idx]))
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
