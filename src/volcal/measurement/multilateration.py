"""Per-station and per-point solvers of the classic multilateration pipeline.

Units: every position, length and residual is in mm; condition numbers are plain numbers.

Model of one reading (the same for a laser tracker station and a laser of a multi-laser
instrument)::

    ||P - Q|| = d + l

with ``Q`` the station (tracker) position, ``P`` the reflector position, ``d`` the station's
dead length and ``l`` the measured (relative) length. Paper 000 (Holub et al. 2022) writes the
right-hand side ``L_k + P_i(k)``, paper 002 (Liu et al. 2023) ``l + l_j``.

Two families of small problems are solved here, each in a batch (all stations, or all
points, at once) with numpy: a batched Levenberg-Marquardt iteration on stacked 3x3 / 4x4
normal equations, or batched closed-form linear systems.

1. :func:`calibrate_station` / :func:`calibrate_stations`: station position ``Q`` and dead
   length ``d`` from readings on known (nominal) points.
2. :func:`multilaterate`: point positions ``P`` from readings of stations with known ``Q`` and
   ``d``.

Methods (names as in the papers):

``"sqrt"``
    Paper 000 Case A, eq. (7) / (15): least squares on ``||P - Q|| - (d + l)``.
``"squared"``
    Paper 000 eq. (8): least squares on ``||P - Q||^2 - (d + l)^2`` (an unequally weighted
    version of ``"sqrt"``: each residual is about ``2 (d + l)`` times the sqrt residual).
``"linear"``
    Paper 000 Case B, eq. (9)-(11) (stations) and (16)-(17) (points): the squared equations are
    linear in ``(Q, d, C)`` with ``C = |Q|^2 - d^2`` (stations) or in ``(P, C)`` with
    ``C = |P|^2`` (points) when ``C`` is treated as an independent unknown; the normal
    equations ``A x = b`` are solved. Its condition numbers are reported.
``"linear_taylor"``
    ``"linear"`` followed by paper 000's first-order Taylor refinement, eq. (12)-(14): one
    linearised step of the sqrt residual for the position only (3x3 system, the dead length
    of Case B is kept).
``"paper002"`` (stations only)
    Paper 002 eq. (12)-(20): the squared equations minus the first one, ``G L = h`` with
    ``L = (x, y, z, d)``, solved by linear least squares. Needs no initial guess; it is the
    default start value of ``"sqrt"`` and ``"squared"``.
``"sphere"`` (points only)
    Closed-form intersection of three spheres; the root is chosen with ``side``.

Contract of every result: ``converged`` is False exactly when the positions are NaN, and
``status`` says why (too few readings, singular or coplanar geometry, no convergence, ...).
Shapes that are plainly wrong raise :class:`volcal.base.exceptions.InputError`.

``residual_rms`` is always the RMS of the geometric (sqrt) residual ``||P - Q|| - (d + l)`` in
mm, whatever the method, so that methods can be compared.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from volcal.base.exceptions import InputError

__all__ = [
    "STATION_METHODS",
    "POINT_METHODS",
    "StationCalibration",
    "StationCalibrations",
    "Multilateration",
    "calibrate_station",
    "calibrate_stations",
    "multilaterate",
    "condition_numbers",
]

STATION_METHODS = ("sqrt", "squared", "linear", "linear_taylor", "paper002")
POINT_METHODS = ("sqrt", "squared", "linear", "linear_taylor", "sphere")

#: A problem whose normal matrix, after scaling to unit diagonal, has a 2-norm condition number
#: above this is reported as singular (its solution would carry no reliable digit).
SINGULAR_CONDITION = 1e12
#: Anchors (points for a station, stations for a point) whose centred coordinates have a
#: singular value below this fraction of the largest are coplanar (or collinear).
GEOMETRY_TOL = 1e-9

_EPS = np.finfo(float).eps


# --------------------------------------------------------------------------------------------
# result objects
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StationCalibration:
    """Calibration of one station.

    Attributes
    ----------
    position : (3,) station position Q, mm (NaN when not converged).
    dead_length : dead length d, mm (the given value when it was not estimated; NaN when not
        converged).
    residual_rms : RMS of ``||P - Q|| - (d + l)`` over the readings, mm.
    iterations : iterations of the iterative solver (0 for the linear methods, 1 for
        ``"linear_taylor"``'s refinement step).
    condition : 2-norm condition number (sigma_max / sigma_min by SVD) of the system matrix the
        method solves: Case B's 5x5 (4x4 without dead length) normal matrix ``A`` for
        ``"linear"`` and ``"linear_taylor"``, ``G^T G`` for ``"paper002"``, the Gauss-Newton
        matrix ``J^T W J`` at the solution for ``"sqrt"`` and ``"squared"``.
    condition_lower_bound : paper 000 Theorem 1 lower bound of ``condition`` from the row and
        column 2-norms: max norm / min norm.
    condition_scaled : condition number of the same matrix after scaling the unknowns so
        that the matrix has a unit diagonal (``D A D``, ``D = diag(A)^-1/2``; the same as
        scaling the columns of the design matrix to unit norm).
    condition_taylor : condition number of the 3x3 Taylor system (eq. 14), NaN unless
        ``method="linear_taylor"``.
    converged : False when the result is unusable; then position and dead_length are NaN.
    status : what happened, in words.
    method : the method used.
    n_readings : readings used (NaN lengths are dropped).
    """

    position: np.ndarray
    dead_length: float
    residual_rms: float
    iterations: int
    condition: float
    condition_lower_bound: float
    condition_scaled: float
    condition_taylor: float
    converged: bool
    status: str
    method: str
    n_readings: int


@dataclass(frozen=True)
class StationCalibrations:
    """Calibration of several stations (arrays over stations, in the order of ``stations``).

    Fields as in :class:`StationCalibration`, stacked: positions (K, 3) mm, dead_lengths (K,)
    mm, residual_rms (K,) mm, iterations (K,), condition* (K,), converged (K,) bool,
    status (K,) str. ``stations`` holds the station ids (sorted unique values of the
    ``station_index`` given).
    """

    stations: np.ndarray
    positions: np.ndarray
    dead_lengths: np.ndarray
    residual_rms: np.ndarray
    iterations: np.ndarray
    condition: np.ndarray
    condition_lower_bound: np.ndarray
    condition_scaled: np.ndarray
    condition_taylor: np.ndarray
    converged: np.ndarray
    status: np.ndarray
    method: str
    n_readings: np.ndarray

    def __len__(self) -> int:
        return len(self.stations)

    def __getitem__(self, k: int) -> StationCalibration:
        """The k-th station (position in ``stations``, not its id) as a StationCalibration."""
        return StationCalibration(
            position=self.positions[k].copy(),
            dead_length=float(self.dead_lengths[k]),
            residual_rms=float(self.residual_rms[k]),
            iterations=int(self.iterations[k]),
            condition=float(self.condition[k]),
            condition_lower_bound=float(self.condition_lower_bound[k]),
            condition_scaled=float(self.condition_scaled[k]),
            condition_taylor=float(self.condition_taylor[k]),
            converged=bool(self.converged[k]),
            status=str(self.status[k]),
            method=self.method,
            n_readings=int(self.n_readings[k]),
        )

    def to_frame(self):
        """pandas DataFrame with columns station, x, y, z, dead_length (mm), residual_rms_um,
        converged, status (the ``stations.csv`` layout plus diagnostics)."""
        import pandas as pd

        return pd.DataFrame(
            {
                "station": self.stations,
                "x": self.positions[:, 0],
                "y": self.positions[:, 1],
                "z": self.positions[:, 2],
                "dead_length": self.dead_lengths,
                "residual_rms_um": 1e3 * self.residual_rms,
                "converged": self.converged,
                "status": self.status,
            }
        )


@dataclass(frozen=True)
class Multilateration:
    """Point positions from known stations (arrays over points).

    Attributes
    ----------
    points : (N, 3) point positions, mm (NaN where not converged).
    residual_rms : (N,) RMS of ``||P - Q_k|| - (d_k + l_k)`` over the stations read, mm.
    condition : (N,) 2-norm condition number of the system matrix of the method: the 4x4
        normal matrix ``A`` of eq. (17) for ``"linear"`` / ``"linear_taylor"``, ``J^T W J``
        at the solution (3x3) for ``"sqrt"``, ``"squared"`` and ``"sphere"``.
    condition_lower_bound : (N,) Theorem 1 lower bound of ``condition``.
    condition_scaled : (N,) condition number after scaling to unit diagonal.
    condition_taylor : (N,) condition number of the 3x3 Taylor system, NaN unless
        ``"linear_taylor"``.
    converged : (N,) bool; False exactly where ``points`` is NaN.
    iterations : (N,) iterations of the iterative solver.
    n_stations : (N,) readings used per point.
    point_status : (N,) str, per point.
    status : one-line summary over all points.
    method : the method used.
    stations_used : (N, 3) int indices of the stations used by ``"sphere"`` (-1 if none),
        None for other methods.
    """

    points: np.ndarray
    residual_rms: np.ndarray
    condition: np.ndarray
    condition_lower_bound: np.ndarray
    condition_scaled: np.ndarray
    condition_taylor: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    n_stations: np.ndarray
    point_status: np.ndarray
    status: str
    method: str
    stations_used: np.ndarray | None = field(default=None)


# --------------------------------------------------------------------------------------------
# small batched helpers
# --------------------------------------------------------------------------------------------
def condition_numbers(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Condition numbers of a stack of square matrices ``A`` (..., n, n).

    Returns ``(cond, lower_bound, cond_scaled)``:

    - ``cond``: sigma_max / sigma_min from the singular values (inf when singular);
    - ``lower_bound``: paper 000 Theorem 1, ``sigma_max >= max(max_i ||a_i.||, max_j ||a_.j||)``
      and ``sigma_min <= min(min_i ||a_i.||, min_j ||a_.j||)``, hence
      ``cond >= max norm / min norm``;
    - ``cond_scaled``: cond of ``D A D`` with ``D = diag(|A_jj|)^-1/2`` (unknowns scaled so
      that the matrix has a unit diagonal).
    """
    A = np.asarray(A, dtype=float)
    symmetric = np.array_equal(A, np.swapaxes(A, -1, -2))

    def singular_values(M):
        if symmetric:  # |eigenvalues| are the singular values; eigvalsh is ~2x faster
            return np.sort(np.abs(np.linalg.eigvalsh(M)), axis=-1)[..., ::-1]
        return np.linalg.svd(M, compute_uv=False)

    with np.errstate(divide="ignore", invalid="ignore"):
        s = singular_values(A)
        cond = np.where(s[..., -1] > 0, s[..., 0] / s[..., -1], np.inf)
        norms = np.concatenate([np.linalg.norm(A, axis=-1), np.linalg.norm(A, axis=-2)], axis=-1)
        lower = norms.max(axis=-1) / norms.min(axis=-1)
        dg = np.abs(np.diagonal(A, axis1=-2, axis2=-1))
        D = np.where(dg > 0, 1.0 / np.sqrt(dg), 1.0)
        As = A * D[..., :, None] * D[..., None, :]
        ss = singular_values(As)
        cond_s = np.where(ss[..., -1] > 0, ss[..., 0] / ss[..., -1], np.inf)
    cond = np.where(np.isfinite(cond), cond, np.inf)
    cond_s = np.where(np.isfinite(cond_s), cond_s, np.inf)
    return cond, lower, cond_s


def _scaled_solve(A: np.ndarray, b: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Solve the stacked systems A x = b (B, n, n), (B, n) where ``ok``; NaN elsewhere.

    The unknowns are scaled to a unit diagonal first (``D A D y = D b``, ``x = D y``), which
    changes nothing in exact arithmetic.
    """
    B, n = b.shape
    x = np.full((B, n), np.nan)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return x
    Ai, bi = A[idx], b[idx]
    dg = np.abs(np.diagonal(Ai, axis1=-2, axis2=-1))
    D = np.where(dg > 0, 1.0 / np.sqrt(np.where(dg > 0, dg, 1.0)), 1.0)
    As = Ai * D[:, :, None] * D[:, None, :]
    try:
        y = np.linalg.solve(As, (D * bi)[..., None])[..., 0]
    except np.linalg.LinAlgError:  # an exactly singular one slipped through: one by one
        y = np.full_like(bi, np.nan)
        for j in range(len(idx)):
            try:
                y[j] = np.linalg.solve(As[j], D[j] * bi[j])
            except np.linalg.LinAlgError:
                pass
    x[idx] = D * y
    return x


def _taylor_step(
    diff: np.ndarray, w: np.ndarray, target: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One weighted Gauss-Newton (Taylor) step of a batch of range problems: for each
    problem b the unknown X_b with ranges ||X_b - A_bm|| ~ target_bm (weights w_bm, 0 drops a
    range), linearised at the current X_b where diff = X_b - A_bm (B, M, 3).  Returns (the
    step (B, 3), the condition numbers of the normal matrices (B,), which steps are usable:
    a normal matrix that is not singular)."""
    t = np.linalg.norm(diff, axis=-1)
    a = diff / np.where(t > 0, t, 1.0)[..., None] * w[..., None]
    res = (target - t) * w
    At = np.einsum("bmi,bmj->bij", a, a)
    bt = np.einsum("bmi,bm->bi", a, res)
    ct, _, cts = condition_numbers(At)
    good = np.isfinite(cts) & (cts < SINGULAR_CONDITION)
    return _scaled_solve(At, bt, good), ct, good


def _geometry(anchors: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Rank (0-3) of the affine hull of the masked anchors (B, M, 3): 3 = spans space,
    2 = coplanar, 1 = collinear, 0 = one point (or none)."""
    w = mask.astype(float)
    cnt = w.sum(axis=1)
    c = (anchors * w[..., None]).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    X = (anchors - c[:, None, :]) * w[..., None]
    s = np.linalg.svd(X, compute_uv=False)  # (B, 3) (M >= 3 rows assumed by callers)
    if s.shape[-1] < 3:
        s = np.concatenate([s, np.zeros(s.shape[:-1] + (3 - s.shape[-1],))], axis=-1)
    top = s[:, :1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(top > 0, s / np.where(top > 0, top, 1.0), 0.0)
    return (rel > GEOMETRY_TOL).sum(axis=1)


def _plane(anchors: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (B, 3) and unit normal (B, 3) of the best-fit plane of the masked anchors."""
    w = mask.astype(float)
    c = (anchors * w[..., None]).sum(axis=1) / np.maximum(w.sum(axis=1), 1)[:, None]
    X = (anchors - c[:, None, :]) * w[..., None]
    _, _, vt = np.linalg.svd(X, full_matrices=True)
    return c, vt[:, -1, :]


def _taylor_refine(
    x: np.ndarray,
    idx: np.ndarray,
    diff: np.ndarray,
    w: np.ndarray,
    ranges: np.ndarray,
    cond_t: np.ndarray,
    iters: np.ndarray,
    conv: np.ndarray,
    status: np.ndarray,
) -> None:
    """One Taylor step (:func:`_taylor_step`) from the linear solutions ``x[idx]`` (mm), in
    place: ``diff`` (n, K, 3) mm from the anchors to them, ``w`` (n, K) weights, ``ranges``
    (n, K) mm the distances they must have.  Records the step's condition in ``cond_t``
    and one iteration; a singular step un-converges its entry."""
    dx, ct, gt = _taylor_step(diff, w, ranges)
    cond_t[idx] = ct
    x[idx[gt]] = x[idx[gt]] + dx[gt]
    iters[idx[gt]] = 1
    conv[idx[~gt]] = False
    for j in np.flatnonzero(~gt):
        status[idx[j]] = f"Taylor system singular (condition {ct[j]:.3g})"
    for k in idx[gt]:
        status[k] = "solved (linear normal equations + one Taylor step)"


def _reject_misfits(
    conv: np.ndarray,
    status: np.ndarray,
    rms: np.ndarray,
    max_residual_rms: float | None,
    what: str,
) -> None:
    """Un-converge (in place) every solution whose geometric residual RMS ``rms`` (mm)
    exceeds ``max_residual_rms`` (mm; None: no limit), saying so in ``status``: a local
    minimum or inconsistent ``what``."""
    if max_residual_rms is None:
        return
    for k in np.flatnonzero(conv & ~(rms <= max_residual_rms)):
        conv[k] = False
        status[k] = (
            f"residual RMS {rms[k]:.3g} mm > max_residual_rms = "
            f"{max_residual_rms:g} mm (local minimum or inconsistent {what})"
        )


def _geometric_rms(
    X: np.ndarray, anchors: np.ndarray, ranges: np.ndarray, mask: np.ndarray
) -> np.ndarray:
    """RMS over masked readings of ``||X - anchor|| - range`` (B,), mm."""
    t = np.linalg.norm(X[:, None, :] - anchors, axis=-1)
    r = np.where(mask, t - ranges, 0.0)
    n = mask.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt((r**2).sum(axis=1) / n)


# --------------------------------------------------------------------------------------------
# batched Levenberg-Marquardt on range residuals
# --------------------------------------------------------------------------------------------
class _RangeProblem:
    """B independent problems: unknown X (3,) and optionally an offset o (dead length).

    Reading i of problem b: range_bi = base_bi + o_b (offset only when estimated);
    residual (kind "sqrt") ||X_b - a_bi|| - range_bi or (kind "squared")
    ||X_b - a_bi||^2 - range_bi^2, multiplied by the weight w_bi (0 for missing readings).
    """

    def __init__(self, anchors, base, weights, kind, estimate_offset):
        self.a, self.base, self.w = anchors, base, weights
        self.kind, self.est = kind, estimate_offset
        self.p = 4 if estimate_offset else 3

    def ranges(self, x, idx):
        base = self.base[idx]
        return base + x[:, 3:4] if self.est else base

    def eval(self, x, idx):
        """Weighted residuals r (b, M), Jacobian J (b, M, p) and the rounding level of the
        cost sum(r^2) (b,), from |r_i| and the size of the terms that cancel in r_i."""
        a, w = self.a[idx], self.w[idx]
        rho = self.ranges(x, idx)
        diff = x[:, None, :3] - a  # (b, M, 3)
        if self.kind == "sqrt":
            t = np.linalg.norm(diff, axis=-1)
            tt = np.where(t > 0, t, 1.0)
            r = (t - rho) * w
            mag = (t + np.abs(rho)) * np.abs(w)
            Jx = diff / tt[..., None]
            Jo = -np.ones_like(t)
        else:
            t2 = (diff**2).sum(axis=-1)
            r = (t2 - rho**2) * w
            mag = (t2 + rho**2) * np.abs(w)
            Jx = 2.0 * diff
            Jo = -2.0 * rho
        J = Jx * w[..., None]
        if self.est:
            J = np.concatenate([J, (Jo * w)[..., None]], axis=-1)
        dr = 4 * _EPS * mag
        noise = (2 * np.abs(r) * dr + dr**2).sum(axis=1)
        return r, J, noise


def _solve_stack(H: np.ndarray, g: np.ndarray) -> np.ndarray:
    """x with H x = g for stacked small systems; pseudo-inverse where H is exactly singular."""
    try:
        return np.linalg.solve(H, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.einsum("bij,bj->bi", np.linalg.pinv(H), g)


def _lm(problem: _RangeProblem, x0: np.ndarray, max_iter: int, xtol: float):
    """Batched Levenberg-Marquardt (Marquardt diagonal scaling) from x0 (B, p).

    Converged when the undamped Gauss-Newton step from the current iterate is shorter than
    ``xtol * (|x| + s)``, ``s`` = 1 mm + the mean |range| of the problem (so that a point at
    the origin converges too); testing the undamped step keeps a heavily damped (short) step
    from passing for convergence.
    Returns x, converged (B,), iterations (steps applied or tried, the final Gauss-Newton
    step included; B,), reason (B,) str.
    """
    B, p = x0.shape
    x = x0.astype(float).copy()
    lam = np.full(B, 1e-6)
    iters = np.zeros(B, dtype=int)
    conv = np.zeros(B, dtype=bool)
    done = ~np.all(np.isfinite(x), axis=1)
    reason = np.full(B, "", dtype=object)
    reason[done] = "no finite start value"
    all_idx = np.arange(B)
    r, J, noise = problem.eval(x, all_idx)
    cost = (r**2).sum(axis=1)
    eye = np.eye(p)
    m = problem.w != 0
    scale = np.abs(np.where(m, problem.base, 0.0)).sum(axis=1) / np.maximum(m.sum(axis=1), 1)
    scale = scale + 1.0  # mm
    for it in range(max_iter + 1):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        Ja, ra = J[act], r[act]
        JaT = np.swapaxes(Ja, 1, 2)
        H = JaT @ Ja
        g = (JaT @ ra[..., None])[..., 0]
        xa = x[act]
        gn = -_solve_stack(H, g)
        small = np.all(np.isfinite(gn), axis=1) & (
            np.linalg.norm(gn, axis=1) <= xtol * (np.linalg.norm(xa, axis=1) + scale[act])
        )
        fin = act[small]
        conv[fin] = True
        done[fin] = True
        reason[fin] = "converged"
        x[fin] = xa[small] + gn[small]  # the last (tiny) Gauss-Newton step, applied as is
        iters[fin] += 1
        if it == max_iter:
            break
        keep = ~small
        act, H, g, xa = act[keep], H[keep], g[keep], xa[keep]
        if act.size == 0:
            break
        dg = np.diagonal(H, axis1=1, axis2=2)
        dg = np.maximum(dg, 1e-12 * np.maximum(dg.max(axis=1, keepdims=True), 1e-300))
        step = -_solve_stack(H + lam[act, None, None] * dg[:, :, None] * eye, g)
        xn = xa + step
        rn, Jn, nn = problem.eval(xn, act)
        cn = (rn**2).sum(axis=1)
        # accept unless the cost rose by more than its rounding level (below that level the
        # cost cannot rank two iterates; the step test above decides convergence)
        acc = (
            np.all(np.isfinite(xn), axis=1)
            & np.isfinite(cn)
            & (cn <= cost[act] + 2 * (noise[act] + nn))
        )
        ia = act[acc]
        x[ia], r[ia], J[ia], cost[ia], noise[ia] = xn[acc], rn[acc], Jn[acc], cn[acc], nn[acc]
        lam[ia] = np.maximum(lam[ia] / 10.0, 1e-12)
        lam[act[~acc]] *= 10.0
        iters[act] += 1
        stalled = act[lam[act] > 1e16]
        done[stalled] = True
        reason[stalled] = "stalled (damping grew without progress)"
    left = ~done
    reason[left] = f"no convergence in {max_iter} iterations"
    return x, conv, iters, reason


def _normal_conditions(problem: _RangeProblem, x: np.ndarray):
    """Condition numbers of J^T W J at x (B, p); NaN rows where x is not finite."""
    B = x.shape[0]
    out = [np.full(B, np.nan) for _ in range(3)]
    ok = np.all(np.isfinite(x), axis=1)
    idx = np.flatnonzero(ok)
    if idx.size:
        _, J, _ = problem.eval(x[idx], idx)
        H = np.einsum("bmi,bmj->bij", J, J)
        for o, v in zip(out, condition_numbers(H)):
            o[idx] = v
    return out


# --------------------------------------------------------------------------------------------
# input handling
# --------------------------------------------------------------------------------------------
def _as_array(a, name, shape_desc, ndim, last=None) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric {shape_desc}: {exc}") from None
    if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
        raise InputError(f"{name} must have shape {shape_desc}, got {arr.shape}")
    return arr


def _check_method(method, allowed):
    if method not in allowed:
        raise InputError(f"unknown method {method!r}; expected one of {', '.join(allowed)}")


# --------------------------------------------------------------------------------------------
# station calibration
# --------------------------------------------------------------------------------------------
def _station_case_b(P, l, mask, w, est, d_fixed):
    """Paper 000 Case B (eq. 9-11), batched over stations.

    With the dead length: for each reading -2 P.Q - 2 l d + C = l^2 - |P|^2, C = |Q|^2 - d^2;
    without: -2 P.Q + C = (d + l)^2 - |P|^2, C = |Q|^2. The normal matrix is
    A = 1/2 M^T W^2 M (M the rows above); it is the paper's A up to the sign of the C row and
    column, which changes neither singular values nor row / column norms.
    Returns x (K, 5 or 4) = (Q, [d], C), A (K, n, n), b (K, n).
    """
    ones = np.ones_like(l)
    if est:
        M = np.concatenate([-2 * P, (-2 * l)[..., None], ones[..., None]], axis=-1)
        rhs = l**2 - (P**2).sum(-1)
    else:
        rho = l + d_fixed[:, None]
        M = np.concatenate([-2 * P, ones[..., None]], axis=-1)
        rhs = rho**2 - (P**2).sum(-1)
    Mw = M * (w * mask)[..., None]
    rw = rhs * (w * mask)
    A = 0.5 * np.einsum("kmi,kmj->kij", Mw, Mw)
    b = 0.5 * np.einsum("kmi,km->ki", Mw, rw)
    return A, b


def _station_paper002(P, l, mask, est, d_fixed):
    """Paper 002 eq. (12)-(20): differences against each station's first reading.

    (P_j - P_1).Q + (l_j - l_1) d = 1/2 (|P_j|^2 - |P_1|^2 - l_j^2 + l_1^2)  (with d),
    (P_j - P_1).Q = 1/2 (|P_j|^2 - |P_1|^2 - rho_j^2 + rho_1^2)           (d known).
    Solved by least squares (normal equations G^T G L = G^T h, unknowns scaled).
    Returns A = G^T G (K, n, n), b = G^T h (K, n).
    """
    K = P.shape[0]
    first = np.argmax(mask, axis=1)
    P1 = P[np.arange(K), first]
    l1 = l[np.arange(K), first]
    Kj = (P**2).sum(-1)
    K1 = (P1**2).sum(-1)
    G = P - P1[:, None, :]
    if est:
        G = np.concatenate([G, (l - l1[:, None])[..., None]], axis=-1)
        h = 0.5 * (Kj - K1[:, None] - l**2 + (l1**2)[:, None])
    else:
        rho, rho1 = l + d_fixed[:, None], l1 + d_fixed
        h = 0.5 * (Kj - K1[:, None] - rho**2 + (rho1**2)[:, None])
    m = mask.copy()
    m[np.arange(K), first] = False
    G = G * m[..., None]
    h = h * m
    return np.einsum("kmi,kmj->kij", G, G), np.einsum("kmi,km->ki", G, h)


def _group(station_index, points, lengths, sigma):
    codes_src = np.asarray(station_index)
    if codes_src.ndim != 1:
        raise InputError(f"station_index must be 1-D, got shape {codes_src.shape}")
    N = len(codes_src)
    points = _as_array(points, "points", "(N, 3)", 2, 3)
    lengths = _as_array(lengths, "lengths", "(N,)", 1)
    if points.shape[0] != N or lengths.shape[0] != N:
        raise InputError(
            f"station_index, points and lengths must have the same length, got "
            f"{N}, {points.shape[0]}, {lengths.shape[0]}"
        )
    if sigma is None:
        sig = np.ones(N)
    else:
        sig = np.asarray(sigma, dtype=float)
        if sig.ndim > 1 or sig.size not in (1, N):
            raise InputError(f"sigma must be a scalar or have shape ({N},), got {sig.shape}")
        sig = np.broadcast_to(sig.reshape(-1), (N,))
        if np.any(~(sig > 0)):
            raise InputError("sigma must be positive (mm)")
    if not np.all(np.isfinite(points)):
        raise InputError("points must be finite (mm)")
    if codes_src.dtype == object and all(type(v) is str for v in codes_src.tolist()):
        # station ids as text (one per reading): np.unique's answer (the ids in sorted
        # order, each reading's index among them) from a set and a dict, without sorting
        # every reading's id (3 ms at 10^4 readings)
        names = sorted(set(codes_src.tolist()))
        at = {v: i for i, v in enumerate(names)}
        stations = np.empty(len(names), object)
        stations[:] = names
        codes = np.fromiter(map(at.__getitem__, codes_src.tolist()), np.intp, N)
    else:
        stations, codes = np.unique(codes_src, return_inverse=True)
    K = len(stations)
    valid = np.isfinite(lengths)
    order = np.argsort(codes, kind="stable")
    order = order[valid[order]]
    c = codes[order]
    counts = np.bincount(c, minlength=K)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    within = np.arange(len(order)) - starts[c]
    M = max(int(counts.max()) if K else 0, 1)
    P = np.zeros((K, M, 3))
    L = np.zeros((K, M))
    W = np.zeros((K, M))
    mask = np.zeros((K, M), dtype=bool)
    P[c, within] = points[order]
    L[c, within] = lengths[order]
    W[c, within] = 1.0 / sig[order]
    mask[c, within] = True
    return stations, P, L, W, mask, counts


def _initial_stations(initial, stations, K):
    """(K, 4) start values (x, y, z, d) with NaN where not given."""
    x0 = np.full((K, 4), np.nan)
    if initial is None:
        return x0
    if isinstance(initial, Mapping):
        pos = {s: i for i, s in enumerate(stations.tolist())}
        for key, val in initial.items():
            if key not in pos:
                raise InputError(f"initial: unknown station {key!r}")
            v = _as_array(val, f"initial[{key!r}]", "(3,) or (4,)", 1)
            if v.shape[0] not in (3, 4):
                raise InputError(f"initial[{key!r}] must have 3 or 4 values, got {v.shape[0]}")
            x0[pos[key], : v.shape[0]] = v
        return x0
    v = np.asarray(initial, dtype=float)
    if v.ndim == 1:
        v = v[None, :]
    if v.ndim != 2 or v.shape[0] != K or v.shape[1] not in (3, 4):
        raise InputError(
            f"initial must have shape ({K}, 3) or ({K}, 4) (x, y, z[, d] in mm), "
            f"got {np.shape(initial)}"
        )
    x0[:, : v.shape[1]] = v
    return x0


def calibrate_stations(
    station_index: Sequence[Any] | np.ndarray,
    points: np.ndarray,
    lengths: np.ndarray,
    method: str = "sqrt",
    *,
    sigma=None,
    initial=None,
    estimate_dead_length: bool = True,
    dead_length=0.0,
    max_iter: int = 100,
    xtol: float = 1e-12,
    max_residual_rms: float | None = 1.0,
) -> StationCalibrations:
    """Self-calibrate every station on known points, all stations in one batch.

    Parameters
    ----------
    station_index : (N,) station id of each reading (any sortable values).
    points : (N, 3) known (nominal) point of each reading, mm.
    lengths : (N,) measured length of each reading, mm (NaN readings are ignored).
    method : one of ``STATION_METHODS`` (see the module docstring).
    sigma : standard uncertainty of each reading, mm, scalar or (N,); readings are weighted
        by 1/sigma (all methods except ``"paper002"``, which is unweighted; for
        ``"squared"`` the weight multiplies the squared residual as in paper 000).
    initial : start values for ``"sqrt"`` / ``"squared"``: (K, 3) or (K, 4) array
        (x, y, z[, d] in mm, stations in sorted-id order) or a mapping id -> values. Missing
        start values come from ``"paper002"`` (no guess needed); a missing d starts at 0 or at
        ``dead_length``.
    estimate_dead_length : estimate d (4 unknowns per station); when False d is fixed to
        ``dead_length``.
    dead_length : scalar, (K,) array or mapping id -> value, mm; the fixed dead length when
        it is not estimated.
    max_iter, xtol : Levenberg-Marquardt limits; convergence when a step is shorter than
        ``xtol * (|x| + 1 mm + mean |length|)``.
    max_residual_rms : mm; a solution whose geometric residual RMS exceeds it is reported as
        failed (a local minimum or inconsistent data), None to disable.

    Returns
    -------
    StationCalibrations (positions NaN and converged False where a station failed).
    """
    _check_method(method, STATION_METHODS)
    stations, P, L, W, mask, counts = _group(station_index, points, lengths, sigma)
    K = len(stations)
    if K == 0:
        raise InputError("no readings")
    if isinstance(dead_length, Mapping):
        dfix = np.array([float(dead_length.get(s, 0.0)) for s in stations.tolist()])
    else:
        if np.size(dead_length) not in (1, K):
            raise InputError(f"dead_length must be a scalar or have {K} values")
        dfix = np.broadcast_to(np.asarray(dead_length, dtype=float), (K,)).copy()
    est = bool(estimate_dead_length)
    n_unknown = 4 if est else 3
    x0_given = _initial_stations(initial, stations, K)

    # requirements per method
    need = {
        "sqrt": n_unknown,
        "squared": n_unknown,
        "linear": n_unknown + 1,
        "linear_taylor": n_unknown + 1,
        "paper002": n_unknown + 1,
    }[method]
    status = np.full(K, "", dtype=object)
    few = counts < need
    for k in np.flatnonzero(few):
        status[k] = (
            f"too few readings: {counts[k]} < {need} needed by method {method!r}"
            f"{' with the dead length estimated' if est else ''}"
        )
    rank = np.zeros(K, dtype=int)
    rank[~few] = _geometry(P[~few], mask[~few]) if np.any(~few) else rank[~few]
    # Coplanar points: the squared equations are linear in (x, y, z, 1) so every linear method
    # is singular; the sqrt / squared cost has two mirror minima (accepted when a start value
    # picks one). Collinear points leave the station on a circle: singular for every method.
    bad_geo = (~few) & (rank < 2)
    for k in np.flatnonzero(bad_geo):
        status[k] = (
            "points collinear (or coincident): the station lies anywhere on a circle; "
            "not identifiable"
        )
    ok = ~few & ~bad_geo

    pos = np.full((K, 3), np.nan)
    dl = np.full(K, np.nan)
    iters = np.zeros(K, dtype=int)
    cond = np.full(K, np.nan)
    cond_lb = np.full(K, np.nan)
    cond_s = np.full(K, np.nan)
    cond_t = np.full(K, np.nan)
    conv = np.zeros(K, dtype=bool)

    def linear(kind):
        if kind == "paper002":
            A, b = _station_paper002(P, L, mask, est, dfix)
        else:
            A, b = _station_case_b(P, L, mask, W, est, dfix)
        c, lb, cs = condition_numbers(A)
        good = ok & np.isfinite(cs) & (cs < SINGULAR_CONDITION)
        x = _scaled_solve(A, b, good)
        return x, good, (c, lb, cs)

    if method in ("linear", "linear_taylor"):
        x, good, (c, lb, cs) = linear("linear")
        cond[:], cond_lb[:], cond_s[:] = c, lb, cs
        pos[good] = x[good, :3]
        dl[good] = x[good, 3] if est else dfix[good]
        for k in np.flatnonzero(ok & ~good):
            status[k] = f"Case B system singular (scaled condition {cs[k]:.3g})" + (
                "; points coplanar" if rank[k] == 2 else ""
            )
        conv = good.copy()
        for k in np.flatnonzero(good):
            status[k] = "solved (linear normal equations)"
        if method == "linear_taylor" and np.any(good):
            idx = np.flatnonzero(good)
            _taylor_refine(
                pos,
                idx,
                pos[idx][:, None, :] - P[idx],
                W[idx] * mask[idx],
                dl[idx][:, None] + L[idx],
                cond_t,
                iters,
                conv,
                status,
            )
    elif method == "paper002":
        x, good, (c, lb, cs) = linear("paper002")
        cond[:], cond_lb[:], cond_s[:] = c, lb, cs
        pos[good] = x[good, :3]
        dl[good] = x[good, 3] if est else dfix[good]
        conv = good.copy()
        for k in np.flatnonzero(ok & ~good):
            status[k] = f"paper 002 system singular (scaled condition {cs[k]:.3g})" + (
                "; points coplanar" if rank[k] == 2 else ""
            )
        for k in np.flatnonzero(good):
            status[k] = "solved (paper 002 linear least squares)"
    else:  # sqrt / squared
        x0 = x0_given.copy()
        if not est:
            x0[:, 3] = dfix
        elif np.any(np.isnan(x0[:, 3]) & np.isfinite(x0[:, 0])):
            fill = np.isnan(x0[:, 3]) & np.isfinite(x0[:, 0])
            x0[fill, 3] = dfix[fill]
        need_start = ok & np.isnan(x0[:, 0])
        if np.any(need_start):
            xs, good, _ = linear("paper002")
            use = need_start & good
            x0[use, :3] = xs[use, :3]
            if est:
                x0[use, 3] = xs[use, 3]
            for k in np.flatnonzero(need_start & ~good):
                status[k] = "no start value: the paper 002 linear start is singular" + (
                    " (points coplanar: two mirror solutions; pass initial=)"
                    if rank[k] == 2
                    else ""
                )
        run = ok & np.all(np.isfinite(x0[:, :3]), axis=1)
        idx = np.flatnonzero(run)
        if idx.size:
            base = L[idx] + (0.0 if est else dfix[idx][:, None])
            prob = _RangeProblem(P[idx], base, W[idx] * mask[idx], method, est)
            xs, cv, it, why = _lm(prob, x0[idx, :n_unknown], max_iter, xtol)
            c, lb, cs = _normal_conditions(prob, xs)
            cond[idx], cond_lb[idx], cond_s[idx] = c, lb, cs
            iters[idx] = it
            sing = ~(cs < SINGULAR_CONDITION)
            for jj, k in enumerate(idx):
                if cv[jj] and not sing[jj]:
                    conv[k] = True
                    pos[k] = xs[jj, :3]
                    dl[k] = xs[jj, 3] if est else dfix[k]
                    status[k] = "converged" + (
                        " (points coplanar: the mirror solution fits "
                        "equally well; kept the one nearest the start)"
                        if rank[k] == 2
                        else ""
                    )
                elif cv[jj]:
                    status[k] = (
                        f"singular at the solution (scaled condition {cs[jj]:.3g}); "
                        "the station is not identifiable from these points"
                    )
                else:
                    status[k] = str(why[jj])
    # geometric residual RMS (for every method)
    rng = L + np.where(np.isfinite(dl), dl, 0.0)[:, None]
    rms = _geometric_rms(pos, P, rng, mask)
    _reject_misfits(conv, status, rms, max_residual_rms, "data")
    pos[~conv] = np.nan
    dl[~conv] = np.nan
    return StationCalibrations(
        stations=stations,
        positions=pos,
        dead_lengths=dl,
        residual_rms=rms,
        iterations=iters,
        condition=cond,
        condition_lower_bound=cond_lb,
        condition_scaled=cond_s,
        condition_taylor=cond_t,
        converged=conv,
        status=status.astype(str),
        method=method,
        n_readings=counts,
    )


def calibrate_station(
    points: np.ndarray,
    lengths: np.ndarray,
    method: str = "sqrt",
    initial=None,
    estimate_dead_length: bool = True,
    *,
    sigma=None,
    dead_length: float = 0.0,
    max_iter: int = 100,
    xtol: float = 1e-12,
    max_residual_rms: float | None = 1.0,
) -> StationCalibration:
    """Self-calibrate one station on known points.

    Parameters
    ----------
    points : (N, 3) known (nominal) points, mm.
    lengths : (N,) measured lengths ``l_i = ||P_i - Q|| - d``, mm (NaN readings ignored).
    method : ``"sqrt"`` (default), ``"squared"``, ``"linear"``, ``"linear_taylor"`` or
        ``"paper002"``; see the module docstring.
    initial : start value (x, y, z) or (x, y, z, d), mm, for ``"sqrt"`` / ``"squared"``;
        None uses the paper 002 linear solution.
    estimate_dead_length : estimate d; when False it is fixed to ``dead_length`` (mm).
    sigma : scalar or (N,) standard uncertainty of the readings, mm (weights 1/sigma).
    dead_length, max_iter, xtol, max_residual_rms : as in :func:`calibrate_stations`.

    Returns
    -------
    StationCalibration; ``converged`` False (and NaN position) with a ``status`` when the
    readings are too few, the points collinear or coplanar without a start value, the
    system singular or the iteration did not converge.
    """
    points = _as_array(points, "points", "(N, 3)", 2, 3)
    lengths = _as_array(lengths, "lengths", "(N,)", 1)
    if initial is not None:
        initial = _as_array(initial, "initial", "(3,) or (4,)", 1)
        if initial.shape[0] not in (3, 4):
            raise InputError(
                f"initial must have 3 or 4 values (x, y, z[, d] in mm), got {initial.shape[0]}"
            )
        initial = initial[None, :]
    res = calibrate_stations(
        np.zeros(len(points), dtype=int),
        points,
        lengths,
        method,
        sigma=sigma,
        initial=initial,
        estimate_dead_length=estimate_dead_length,
        dead_length=dead_length,
        max_iter=max_iter,
        xtol=xtol,
        max_residual_rms=max_residual_rms,
    )
    return res[0]


# --------------------------------------------------------------------------------------------
# point multilateration
# --------------------------------------------------------------------------------------------
def _sphere(Q, rho, mask, side, side_type):
    """Closed-form intersection of the first three spheres of each point.

    Frame: origin Q1, ex toward Q2, ey in the plane of the three centres, ez = ex x ey.
    x = (r1^2 - r2^2 + D^2) / (2 D), y = (r1^2 - r3^2 + i^2 + j^2) / (2 j) - i x / j,
    z = +-sqrt(r1^2 - x^2 - y^2) (D = |Q2 - Q1|, i, j the coordinates of Q3).
    Returns P (N, 3), used (N, 3) station indices, z2 (N,) (mm^2), two roots (N, 2, 3),
    ok (N,), reason (N,), startable (N,): P is usable as a start value (when the spheres miss
    each other, z is clamped to 0: the point on the stations' plane).
    """
    N, K = mask.shape
    used = np.full((N, 3), -1, dtype=int)
    cnt = mask.sum(axis=1)
    ok = cnt >= 3
    # indices of the first three stations read by each point
    order = np.argsort(~mask, axis=1, kind="stable")[:, :3] if K >= 3 else None
    reason = np.full(N, "", dtype=object)
    reason[~ok] = "too few readings for sphere intersection (need 3)"
    P = np.full((N, 3), np.nan)
    roots = np.full((N, 2, 3), np.nan)
    z2 = np.full(N, np.nan)
    if order is None or not np.any(ok):
        return P, used, z2, roots, ok, reason, np.zeros(N, dtype=bool)
    idx = np.flatnonzero(ok)
    o = order[idx]
    used[idx] = o
    Qs = Q[o]  # (n, 3, 3)
    r = np.take_along_axis(rho[idx], o, axis=1)
    Q1, Q2, Q3 = Qs[:, 0], Qs[:, 1], Qs[:, 2]
    e21 = Q2 - Q1
    D = np.linalg.norm(e21, axis=1)
    ex = e21 / np.where(D > 0, D, 1.0)[:, None]
    v3 = Q3 - Q1
    i = np.einsum("ni,ni->n", ex, v3)
    w = v3 - i[:, None] * ex
    j = np.linalg.norm(w, axis=1)
    scale = np.maximum(D, 1e-300)
    degenerate = (D <= 0) | (j <= GEOMETRY_TOL * scale)
    jj = np.where(degenerate, 1.0, j)
    ey = w / jj[:, None]
    ez = np.cross(ex, ey)
    Dd = np.where(D > 0, D, 1.0)
    x = (r[:, 0] ** 2 - r[:, 1] ** 2 + D**2) / (2 * Dd)
    y = (r[:, 0] ** 2 - r[:, 2] ** 2 + i**2 + j**2) / (2 * jj) - i * x / jj
    zz = r[:, 0] ** 2 - x**2 - y**2
    z2[idx] = zz
    tol = 64 * _EPS * r[:, 0] ** 2  # rounding level of z^2
    noreal = zz < -tol
    z = np.sqrt(np.maximum(zz, 0.0))
    base = Q1 + x[:, None] * ex + y[:, None] * ey
    rp = base + z[:, None] * ez
    rm = base - z[:, None] * ez
    roots[idx, 0], roots[idx, 1] = rp, rm
    if side is not None:
        s = np.asarray(side, dtype=float)
        s = np.broadcast_to(s, (N, 3))[idx]
        ref = (
            np.einsum("ni,ni->n", s - Q1, ez)
            if side_type == "point"
            else np.einsum("ni,ni->n", s, ez)
        )
        pick_plus = ref >= 0
        choose = np.where(pick_plus[:, None], rp, rm)
        undecided = ref == 0
    else:
        # no side: decide with the remaining stations (if any), otherwise undecided
        undecided = np.ones(len(idx), dtype=bool)
        choose = rp
        extra = cnt[idx] > 3
        if np.any(extra):
            m = mask[idx].copy()
            np.put_along_axis(m, o, False, axis=1)
            rr = rho[idx]
            ep = np.where(m, np.linalg.norm(rp[:, None] - Q[None], axis=-1) - rr, 0.0)
            em = np.where(m, np.linalg.norm(rm[:, None] - Q[None], axis=-1) - rr, 0.0)
            cp, cm = (ep**2).sum(1), (em**2).sum(1)
            choose = np.where((cp <= cm)[:, None], rp, rm)
            undecided = ~extra
    P[idx] = choose
    startable = np.zeros(N, dtype=bool)  # usable as a start value (z clamped to 0 if needed)
    startable[idx] = ~degenerate & ~undecided
    bad = degenerate | noreal | undecided
    for jx in np.flatnonzero(bad):
        n = idx[jx]
        ok[n] = False
        if degenerate[jx]:
            reason[n] = "the three stations are collinear (or coincident): no unique intersection"
        elif noreal[jx]:
            reason[n] = f"the three spheres do not intersect (z^2 = {zz[jx]:.3g} mm^2 < 0)"
        else:
            reason[n] = (
                "two roots and nothing to choose between them: pass side= (a point, "
                "or a normal with side_type='normal')"
            )
    good = idx[~bad]
    reason[good] = "solved (sphere intersection)"
    more = good[cnt[good] > 3]
    if more.size:  # one message per (stations used, readings ignored) combination
        tail = "" if side is not None else " except to pick the root"
        keys = np.c_[used[more], cnt[more]]
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        for u, key in enumerate(uniq):
            reason[more[inv.ravel() == u]] = (
                f"solved (sphere intersection); used stations {tuple(int(v) for v in key[:3])} "
                f"only, the other {key[3] - 3} reading(s) ignored{tail}"
            )
    return P, used, z2, roots, ok, reason, startable


def multilaterate(
    stations: np.ndarray,
    dead_lengths: np.ndarray,
    lengths: np.ndarray,
    method: str = "sqrt",
    initial=None,
    *,
    sigma=None,
    side=None,
    side_type: str = "point",
    max_iter: int = 100,
    xtol: float = 1e-12,
    max_residual_rms: float | None = 1.0,
) -> Multilateration:
    """Positions of N points from K stations with known positions and dead lengths.

    Parameters
    ----------
    stations : (K, 3) station positions Q_k, mm.
    dead_lengths : (K,) dead lengths d_k, mm.
    lengths : (N, K) measured lengths, mm; NaN where station k did not read point i.
    method : ``"sqrt"`` (default, eq. 15), ``"squared"``, ``"linear"`` (eq. 16-17, unknowns
        (x, y, z, C = |P|^2)), ``"linear_taylor"`` (linear + one Taylor step of the sqrt
        residual) or ``"sphere"`` (closed-form intersection of the first three spheres read).
    initial : (N, 3) or (3,) start points for ``"sqrt"`` / ``"squared"``, mm; None starts
        from the ``"linear"`` solution (from ``"sphere"`` where that is singular and
        ``side`` is given).
    sigma : standard uncertainty of the readings, mm: scalar, (K,) or (N, K); weights 1/sigma.
    side : which of two mirror solutions to keep: for ``"sphere"`` (always two roots), and
        for ``"sqrt"`` / ``"squared"`` when the stations are coplanar. With
        ``side_type="point"`` a reference point (3,) or (N, 3) in mm (e.g. the nominal
        points); the root on the same side of the station plane is kept. With
        ``side_type="normal"`` a direction (3,) or (N, 3); the root ``P`` with
        ``(P - Q_1) . n > 0`` is kept (Q_1 the first station used).
    max_iter, xtol : Levenberg-Marquardt limits (converged when a step is shorter than
        ``xtol (|P| + 1 mm + mean range)``).
    max_residual_rms : mm; a point whose geometric residual RMS exceeds it is reported as
        failed (a local minimum of the sqrt / squared cost, or inconsistent readings), None
        to disable.

    Returns
    -------
    Multilateration; NaN points with converged False and a ``point_status`` where too few
    stations read the point, the stations are collinear (or coplanar for the linear methods,
    or coplanar without ``side`` / ``initial`` for sqrt / squared), a system is singular or
    the iteration did not converge.
    """
    _check_method(method, POINT_METHODS)
    if side_type not in ("point", "normal"):
        raise InputError(f"side_type must be 'point' or 'normal', got {side_type!r}")
    Q = _as_array(stations, "stations", "(K, 3)", 2, 3)
    K = Q.shape[0]
    dls = _as_array(np.atleast_1d(dead_lengths), "dead_lengths", f"({K},)", 1)
    if dls.shape[0] != K:
        raise InputError(f"dead_lengths must have {K} values (one per station), got {dls.shape[0]}")
    Lm = np.asarray(lengths, dtype=float)
    if Lm.ndim == 1 and Lm.shape[0] == K:
        Lm = Lm[None, :]
    if Lm.ndim != 2 or Lm.shape[1] != K:
        raise InputError(f"lengths must have shape (N, {K}) (NaN for missing), got {Lm.shape}")
    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(dls))):
        raise InputError("stations and dead_lengths must be finite (mm)")
    N = Lm.shape[0]
    mask = np.isfinite(Lm)
    if sigma is None:
        W = np.ones((N, K))
    else:
        s = np.asarray(sigma, dtype=float)
        try:
            s = np.broadcast_to(s, (N, K))
        except ValueError:
            raise InputError(
                f"sigma must be a scalar, ({K},) or ({N}, {K}), got {s.shape}"
            ) from None
        if np.any(~(s[mask] > 0)):
            raise InputError("sigma must be positive (mm)")
        W = np.where(mask, 1.0 / np.where(mask, s, 1.0), 0.0)
    W = W * mask
    rho = np.where(mask, Lm + dls[None, :], 0.0)
    if side is not None:
        side = np.asarray(side, dtype=float)
        if side.shape not in ((3,), (N, 3)):
            raise InputError(f"side must have shape (3,) or ({N}, 3), got {side.shape}")
    x_init = None
    if initial is not None:
        x_init = np.asarray(initial, dtype=float)
        try:
            x_init = np.broadcast_to(x_init, (N, 3)).copy()
        except ValueError:
            raise InputError(
                f"initial must have shape (3,) or ({N}, 3), got {x_init.shape}"
            ) from None

    cnt = mask.sum(axis=1)
    anchors = np.broadcast_to(Q, (N, K, 3))
    rank = np.zeros(N, dtype=int)
    has3 = cnt >= 3
    if np.any(has3):  # the geometry depends only on which stations read the point
        mk = mask[has3]
        if K <= 62:  # one integer code per pattern: much faster than np.unique(axis=0)
            codes = mk.astype(np.int64) @ (np.int64(1) << np.arange(K, dtype=np.int64))
            _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
            patterns = mk[first]
        else:
            patterns, inverse = np.unique(mk, axis=0, return_inverse=True)
        rank[has3] = _geometry(np.broadcast_to(Q, (len(patterns), K, 3)), patterns)[inverse.ravel()]

    pts = np.full((N, 3), np.nan)
    iters = np.zeros(N, dtype=int)
    cond = np.full(N, np.nan)
    cond_lb = np.full(N, np.nan)
    cond_s = np.full(N, np.nan)
    cond_t = np.full(N, np.nan)
    conv = np.zeros(N, dtype=bool)
    pstat = np.full(N, "", dtype=object)
    used = None

    def linear(sel):
        """Case B analogue for the points in sel: rows [-2 Q_k, 1], rhs rho^2 - |Q_k|^2."""
        Mrow = np.concatenate([-2 * Q, np.ones((K, 1))], axis=1)  # (K, 4)
        rhs = rho[sel] ** 2 - (Q**2).sum(1)[None, :]
        w2 = W[sel] ** 2
        A = 0.5 * np.einsum("nk,ki,kj->nij", w2, Mrow, Mrow)
        b = 0.5 * np.einsum("nk,ki,nk->ni", w2, Mrow, rhs)
        c, lb, cs = condition_numbers(A)
        good = np.isfinite(cs) & (cs < SINGULAR_CONDITION)
        x = _scaled_solve(A, b, good)
        return x[:, :3], good, (c, lb, cs)

    few_lin = cnt < 4
    collinear = has3 & (rank < 2)
    if method in ("linear", "linear_taylor"):
        sel = np.flatnonzero(~few_lin)
        if sel.size:
            x, good, (c, lb, cs) = linear(sel)
            cond[sel], cond_lb[sel], cond_s[sel] = c, lb, cs
            pts[sel[good]] = x[good]
            conv[sel[good]] = True
            for j in np.flatnonzero(~good):
                n = sel[j]
                pstat[n] = (
                    f"linear system singular (scaled condition {cs[j]:.3g})"
                    + ("; stations coplanar" if rank[n] == 2 else "")
                    + ("; stations collinear" if rank[n] < 2 else "")
                )
            pstat[sel[good]] = "solved (linear normal equations)"
        for n in np.flatnonzero(few_lin):
            pstat[n] = f"too few readings: {cnt[n]} < 4 needed by method {method!r}"
        if method == "linear_taylor" and np.any(conv):
            idx = np.flatnonzero(conv)
            _taylor_refine(
                pts,
                idx,
                pts[idx][:, None, :] - Q[None],
                W[idx],
                rho[idx],
                cond_t,
                iters,
                conv,
                pstat,
            )
    elif method == "sphere":
        P, used, z2, roots, ok, why, _ = _sphere(Q, rho, mask, side, side_type)
        pts[ok] = P[ok]
        conv = ok
        pstat[:] = why
        idx = np.flatnonzero(ok)
        if idx.size:
            prob = _RangeProblem(
                Q[used[idx]],
                np.take_along_axis(rho[idx], used[idx], 1),
                np.take_along_axis(W[idx], used[idx], 1),
                "sqrt",
                False,
            )
            c, lb, cs = _normal_conditions(prob, pts[idx])
            cond[idx], cond_lb[idx], cond_s[idx] = c, lb, cs
    else:  # sqrt / squared
        x0 = np.full((N, 3), np.nan) if x_init is None else x_init.copy()
        coplanar = has3 & (rank == 2)
        resolved_by = np.full(N, "", dtype=object)
        if x_init is None:
            sel = np.flatnonzero(~few_lin & ~coplanar & ~collinear)
            if sel.size:
                x, good, _ = linear(sel)
                x0[sel[good]] = x[good]
            need = np.flatnonzero(has3 & ~collinear & np.isnan(x0[:, 0]))
            if need.size and side is not None:
                Ps, _, _, _, _, _, oks = _sphere(
                    Q, rho[need], mask[need], side if side.ndim == 1 else side[need], side_type
                )
                x0[need[oks]] = Ps[oks]
        # too few / degenerate
        for n in np.flatnonzero(cnt < 3):
            pstat[n] = f"too few readings: {cnt[n]} < 3"
        for n in np.flatnonzero(collinear):
            pstat[n] = "stations collinear: the point lies anywhere on a circle; not identifiable"
        amb = coplanar & (side is None) & (x_init is None)
        for n in np.flatnonzero(amb):
            pstat[n] = (
                "stations coplanar: two mirror solutions; pass side= (or initial=) to choose one"
            )
        resolved_by[coplanar & (side is not None)] = "side"
        resolved_by[coplanar & (side is None) & (x_init is not None)] = "initial"
        run = (cnt >= 3) & ~collinear & ~amb & np.all(np.isfinite(x0), axis=1)
        for n in np.flatnonzero((cnt >= 3) & ~collinear & ~amb & ~run):
            pstat[n] = (
                "no start value (the linear start is singular and no sphere "
                "intersection was usable); pass initial="
            )
        idx = np.flatnonzero(run)
        if idx.size:
            prob = _RangeProblem(anchors[idx], rho[idx], W[idx], method, False)
            xs, cv, it, why = _lm(prob, x0[idx], max_iter, xtol)
            # mirror choice for coplanar stations given a side
            fix = np.flatnonzero(resolved_by[idx] == "side")
            if fix.size:
                c0, nrm = _plane(anchors[idx[fix]], mask[idx[fix]])
                s = side if side.ndim == 1 else side[idx[fix]]
                s = np.broadcast_to(s, (fix.size, 3))
                ref = (
                    np.einsum("ni,ni->n", s - c0, nrm)
                    if side_type == "point"
                    else np.einsum("ni,ni->n", s, nrm)
                )
                h = np.einsum("ni,ni->n", xs[fix] - c0, nrm)
                flip = np.sign(h) != np.sign(ref)
                xs[fix[flip]] -= 2 * h[flip, None] * nrm[flip]
            c, lb, cs = _normal_conditions(prob, xs)
            cond[idx], cond_lb[idx], cond_s[idx] = c, lb, cs
            iters[idx] = it
            sing = ~(cs < SINGULAR_CONDITION)
            good = cv & ~sing
            pts[idx[good]] = xs[good]
            conv[idx[good]] = True
            for j in np.flatnonzero(~good):
                pstat[idx[j]] = (
                    str(why[j])
                    if not cv[j]
                    else f"singular at the solution (scaled condition {cs[j]:.3g})"
                )
            ig = idx[good]
            pstat[ig] = "converged"
            pstat[ig[resolved_by[ig] == "side"]] = (
                "converged (stations coplanar: mirror root chosen by side)"
            )
            pstat[ig[resolved_by[ig] == "initial"]] = (
                "converged (stations coplanar: kept the mirror root nearest the initial point)"
            )
    rms = _geometric_rms(pts, anchors, rho, mask)
    _reject_misfits(conv, pstat, rms, max_residual_rms, "readings")
    pts[~conv] = np.nan
    rms[~conv] = np.nan
    n_ok = int(conv.sum())
    summary = f"{method}: {n_ok} of {N} points solved"
    if n_ok < N:
        msgs, counts = np.unique(pstat[~conv].astype(str), return_counts=True)
        top = sorted(zip(counts, msgs), reverse=True)[:3]
        summary += "; failures: " + "; ".join(f"{c} x {m}" for c, m in top)
    if method == "sphere" and np.any(cnt > 3):
        summary += "; sphere uses the first three stations read by each point (others ignored" + (
            ")" if side is not None else " except to choose the root)"
        )
    return Multilateration(
        points=pts,
        residual_rms=rms,
        condition=cond,
        condition_lower_bound=cond_lb,
        condition_scaled=cond_s,
        condition_taylor=cond_t,
        converged=conv,
        iterations=iters,
        n_stations=cnt,
        point_status=pstat.astype(str),
        status=summary,
        method=method,
        stations_used=used,
    )
