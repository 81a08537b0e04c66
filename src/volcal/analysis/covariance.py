"""Linearised covariance of constrained least squares (KKT / Fisher information).

For whitened residuals r(x) with Jacobian J at the solution and equality constraints
C x = 0, the covariance of the estimate is Z (Z^T J^T J Z)^-1 Z^T with Z an orthonormal
basis of null(C): the Fisher information restricted to the directions the constraints
leave free.  Multiplying by the residual variance factor s^2 = ||r||^2 / (m - p) gives the
a-posteriori covariance for budgets that are only known up to a factor.
"""

from __future__ import annotations

import numpy as np

from volcal.base.linalg import null_space, scale_columns


def constrained_covariance(
    J: np.ndarray,
    C: np.ndarray | None = None,
    *,
    fixed: np.ndarray | None = None,
    n_rows: int | None = None,
) -> np.ndarray:
    """(n, n) covariance of x; rows/columns of fixed variables are NaN.  J may be the
    Jacobian's R factor (``J = Q R``), ``n_rows`` then the Jacobian's number of rows (for
    the pseudo-inverse's tolerance)."""
    J = np.asarray(J, float)
    n = J.shape[1]
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    # columns scaled to unit norm for a well-conditioned inverse, undone afterwards
    free, _, d, Jf = scale_columns(J, fixed)
    Z = _datum_basis(C, free, d)
    # pseudo-inverse via SVD: exact for full rank, and never explodes on a near-null direction
    from volcal.analysis.identifiability import _r_factor

    m = Jf.shape[0] if n_rows is None else int(n_rows)
    R = _r_factor(Jf) @ Z  # factorises the scaled copy in place
    _, s, Vt = np.linalg.svd(R, full_matrices=False)
    keep = s > max(m, len(free)) * np.finfo(float).eps * (s[0] if len(s) else 0)
    Minv = (Vt[keep].T / s[keep] ** 2) @ Vt[keep]
    cov_s = Z @ Minv @ Z.T
    return _unscaled(cov_s, n, free, d)


#: the largest ratio of the extreme eigenvalues of the reduced Gauss-Newton matrix
#: (columns scaled) from which :func:`gram_covariance` inverts it; beyond it the caller
#: takes the R factor.  The Gram's rounding moves the covariance by about n eps times
#: that ratio relative (a 111-variable fit with the ratio at 1e6: 2.5e-8), the R factor's
#: by about n eps times its square root
GRAM_MAX_CONDITION = 1e6


def gram_covariance(
    H: np.ndarray,
    C: np.ndarray | None = None,
    *,
    fixed: np.ndarray | None = None,
    max_condition: float = GRAM_MAX_CONDITION,
) -> np.ndarray | None:
    """:func:`constrained_covariance` from the Gauss-Newton matrix H = J^T J (n, n) that
    a solver already holds at the point, instead of J or its R factor: the same
    Z (Z^T H Z)^-1 Z^T on columns scaled to unit norm, by an eigendecomposition of the
    reduced matrix.  Forming H squared J's conditioning, so this is done only while the
    reduced matrix is well conditioned (its eigenvalues within ``max_condition`` of each
    other); otherwise None, and the caller takes the R factor, whose pseudo-inverse also
    decides a rank.  Rows/columns of fixed variables are NaN."""
    H = np.asarray(H, float)
    n = H.shape[1]
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    Hf = H[np.ix_(free, free)]
    # the column norms of J are the square roots of H's diagonal
    norms = np.sqrt(np.clip(np.diag(Hf), 0.0, None))
    d = 1.0 / np.where(norms == 0, 1.0, norms)
    Hs = Hf * d[:, None] * d[None, :]
    Z = _datum_basis(C, free, d)
    M = Z.T @ Hs @ Z
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    if len(lam) and not (np.isfinite(lam).all() and lam[0] * max_condition > lam[-1]):
        return None
    cov_s = Z @ ((V / lam) @ V.T) @ Z.T
    return _unscaled(cov_s, n, free, d)


def _datum_basis(C: np.ndarray | None, free: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Orthonormal basis Z of the scaled free variables that the datum conditions C
    (rows over all variables) leave free: the null space of C's free columns scaled by d
    (rows without a free entry dropped); the identity without conditions."""
    if C is not None and len(C):
        Cf = np.asarray(C, float)[:, free] * d
        Cf = Cf[np.linalg.norm(Cf, axis=1) > 0]
        if Cf.shape[0]:
            return null_space(Cf)
    return np.eye(len(free))


def _unscaled(cov_s: np.ndarray, n: int, free: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(n, n) covariance from the scaled free variables' ``cov_s``; fixed ones NaN."""
    cov = np.full((n, n), np.nan)
    cov[np.ix_(free, free)] = cov_s * d[:, None] * d[None, :]
    return cov
