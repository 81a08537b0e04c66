"""Small numerical kernels shared by the layers (numpy only).

``volcal identify`` does its dense linear algebra through numpy's LAPACK, not
scipy.linalg: importing scipy (its array-API layer imports every lazy numpy submodule,
numpy.f2py and numpy.testing among them) took about 0.15 s of a 0.9 s run at 10^4
readings, more than all of the run's factorisations.  The kernels here are the scipy.linalg
calls the identification needed, on numpy: the same LAPACK routines (geqrf, gesdd,
potrf, getrf on a triangle, which is a back-substitution), the same tolerances, and
geqp3's column pivoting written out for the small matrices it is used on.  Only LAPACK's
triangular-pentagonal QR, worth its import on long streams of rows, still imports scipy."""

from __future__ import annotations

import numpy as np


def scale_columns(
    J: np.ndarray, fixed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The free columns of J scaled to unit norm: (free indices, their norms, d = 1 / norm,
    J[:, free] * d).

    Rank and null-space decisions are taken on the scaled matrix so that they do not depend
    on the units of the variables; a zero column keeps d = 1."""
    J = np.asarray(J, float)
    fixed = np.zeros(J.shape[1], bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    Jf = J[:, free]  # a copy: scaled in place (one tall array, not two)
    norms = np.linalg.norm(Jf, axis=0)
    d = 1.0 / np.where(norms == 0, 1.0, norms)
    Jf *= d
    return free, norms, d, Jf


def null_space(A: np.ndarray) -> np.ndarray:
    """Orthonormal basis (n, k) of the null space of A (m, n): the right singular vectors
    of singular values at most max(m, n) eps s_max (``scipy.linalg.null_space``'s
    tolerance, through the same LAPACK gesdd)."""
    A = np.asarray(A, float)
    m, n = A.shape
    if m == 0 or n == 0:
        return np.eye(n)
    _, s, vt = np.linalg.svd(A, full_matrices=True)
    tol = (s.max() if len(s) else 0.0) * max(m, n) * np.finfo(float).eps
    rank = int(np.sum(s > tol))
    return vt[rank:].T.copy()


def solve_triangular(T: np.ndarray, b: np.ndarray, *, lower: bool = False) -> np.ndarray:
    """T^-1 b for a triangular T (n, n) with a nonzero diagonal; b (n,) or (n, k).

    numpy has no triangular solve, but its LU (getrf with partial pivoting) of an upper
    triangle is the triangle itself (every column is zero below the diagonal, so no row is
    exchanged): ``np.linalg.solve`` is then a back-substitution.  A lower triangle is an
    upper one with rows and columns in reverse order."""
    T = np.asarray(T, float)
    b = np.asarray(b, float)
    if T.shape[0] == 0:
        return np.zeros_like(b)
    if lower:
        return np.linalg.solve(T[::-1, ::-1], b[::-1])[::-1]
    return np.linalg.solve(T, b)


def cholesky_upper(A: np.ndarray) -> np.ndarray:
    """The upper Cholesky factor U of a symmetric positive definite A (A = U^T U; its
    lower triangle read); raises ``numpy.linalg.LinAlgError`` when A is not positive
    definite."""
    return np.linalg.cholesky(np.asarray(A, float)).T


def cholesky_solve(U: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A^-1 b from A's upper Cholesky factor U (:func:`cholesky_upper`)."""
    return solve_triangular(U, solve_triangular(U.T, b, lower=True))


def pivot_order(A: np.ndarray) -> np.ndarray:
    """The column order (n,) of A's QR with column pivoting: LAPACK's ``geqp3`` choice
    (``scipy.linalg.qr(A, pivoting=True)[2]``), by its unblocked algorithm (``laqp2``,
    which geqp3 runs on matrices of fewer than 128 columns): at each step the column of
    the largest remaining norm (the first of equal ones, see below), a Householder
    reflection, and the remaining norms downdated, recomputed where the downdate has lost
    half its digits.  Only the first min(m, n) entries are chosen by norms; the others
    are where those exchanges left them.  For the small matrices the identifiability
    analysis pivots (k null directions x n variables) and the datum conditions of the
    correlation plot: no scipy import for them."""
    A = np.array(A, float)
    m, n = A.shape
    piv = np.arange(n)
    vn1 = np.linalg.norm(A, axis=0)
    vn2 = vn1.copy()
    tol3z = np.sqrt(np.finfo(float).eps)
    for i in range(min(m, n)):
        # the first of the columns of the largest norm, norms equal to 10 digits counting
        # as equal: LAPACK takes the first largest too (idamax), but equal columns there
        # come out of its blocked updates differing in the last bits, so which of two
        # copies it picks depends on where they sit in memory; here it is the first
        p = i + int(np.argmax(vn1[i:] >= vn1[i:].max() * (1.0 - 1e-10)))
        if p != i:
            A[:, [i, p]] = A[:, [p, i]]
            piv[[i, p]] = piv[[p, i]]
            vn1[p], vn2[p] = vn1[i], vn2[i]
        # Householder reflection of column i below the diagonal (larfg), applied to the rest
        x = A[i:, i]
        alpha, sigma = x[0], np.linalg.norm(x[1:])
        if sigma != 0.0:
            beta = -np.copysign(np.hypot(alpha, sigma), alpha)
            v = x.copy()
            v[0] = alpha - beta
            v /= v[0]
            tau = (beta - alpha) / beta
            A[i:, i + 1 :] -= tau * np.outer(v, v @ A[i:, i + 1 :])
            A[i, i] = beta
        for j in range(i + 1, n):
            if vn1[j] != 0.0:
                t = max(0.0, 1.0 - (abs(A[i, j]) / vn1[j]) ** 2)
                if t * (vn1[j] / vn2[j]) ** 2 <= tol3z:
                    vn1[j] = np.linalg.norm(A[i + 1 :, j]) if i + 1 < m else 0.0
                    vn2[j] = vn1[j]
                else:
                    vn1[j] *= np.sqrt(t)
    return piv


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of a 2-D float array in ascending lexicographic order and the
    index of each row among them: ``np.unique(a, axis=0, return_inverse=True)`` with a
    flat inverse, for finite values.  A lexsort of the columns and a comparison of
    neighbours, about ten times faster than np.unique on rows (which sorts records) at
    10^5 rows: the poses of a measurement are grouped this way several times per run."""
    a = np.asarray(a, float)
    n = a.shape[0]
    if n == 0 or a.ndim != 2 or a.shape[1] == 0:
        uniq, inv = np.unique(a, axis=0, return_inverse=True)
        return uniq, inv.ravel()
    order = np.lexsort(a.T[::-1])  # the first column is the primary key
    s = a[order]
    new = np.empty(n, bool)
    new[0] = True
    np.any(s[1:] != s[:-1], axis=1, out=new[1:])
    inv = np.empty(n, np.intp)
    inv[order] = np.cumsum(new) - 1
    return s[new], inv


#: streams of at least this many rows are factorised by LAPACK's tpqrt through scipy
#: instead of numpy: 1.2 against 2.5 us a row of 90 columns (geqrf does not block a
#: matrix that narrow), and an identification factorises its rows twice (the datum's
#: and the field's R), so from about 50,000 readings the saving exceeds scipy's import
#: (~0.15 s)
LAPACK_TPQRT_ROWS = 50_000


class StackedQR:
    """The R factor (n, n) of a tall matrix fed in blocks of rows, without the matrix.

    Each block is factorised together with the R of the blocks before it (a sequential
    TSQR: QR of ``[R; block]``), so only one block and an n x n triangle are held.  The
    result is the R of one Householder QR of the whole stack up to the signs of its rows
    and rounding: ``R^T R = A^T A`` and the singular values and right singular vectors of
    R are A's (no normal equations are formed, so the conditioning is A's, not its
    square).  Rows of R beyond the rank of the stack are zero."""

    def __init__(self, n: int, *, expected_rows: int = 0) -> None:
        """``expected_rows``: about how many rows will be fed, the whole stream's (see
        :data:`LAPACK_TPQRT_ROWS`); the R is the same either way up to rounding."""
        self.n = int(n)
        self.rows = 0
        self._R = np.zeros((self.n, self.n), order="F")
        self._tpqrt = int(expected_rows) >= LAPACK_TPQRT_ROWS

    def add(self, block: np.ndarray) -> None:
        """Feed a block (m_k, n) of rows (any m_k >= 0)."""
        block = np.asarray(block, float)
        m = block.shape[0]
        if m == 0 or self.n == 0:
            self.rows += m
            return
        if not self._tpqrt:
            # numpy's geqrf of the stacked rows: twice tpqrt's work, but no scipy import
            R = np.linalg.qr(np.concatenate([self._R, block]), mode="r")
            self._R = np.asfortranarray(R[: self.n])
            self.rows += m
            return
        import scipy.linalg as sla

        # LAPACK's triangular-pentagonal QR of [R; block] (tpqrt): the Householder QR
        # geqrf would do on the stacked rows, without the work on R's zeros or the copy
        # into one array (twice as fast on 512-row blocks of 91 columns)
        b = np.array(block, order="F")
        (tpqrt,) = sla.get_lapack_funcs(("tpqrt",), (self._R, b))
        r, _, _, info = tpqrt(0, min(32, self.n), self._R, b, overwrite_a=True, overwrite_b=True)
        if info != 0:  # pragma: no cover - only for invalid arguments
            raise np.linalg.LinAlgError(f"tpqrt failed (info {info})")
        self._R = np.asfortranarray(np.triu(r))
        self.rows += m

    @property
    def R(self) -> np.ndarray:
        """The (n, n) upper-triangular factor of the rows fed so far."""
        return self._R.copy()
