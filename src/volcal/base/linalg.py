"""Small numerical kernels shared by the layers (numpy only)."""

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


class StackedQR:
    """The R factor (n, n) of a tall matrix fed in blocks of rows, without the matrix.

    Each block is factorised together with the R of the blocks before it (a sequential
    TSQR: QR of ``[R; block]``), so only one block and an n x n triangle are held.  The
    result is the R of one Householder QR of the whole stack up to the signs of its rows
    and rounding: ``R^T R = A^T A`` and the singular values and right singular vectors of
    R are A's (no normal equations are formed, so the conditioning is A's, not its
    square).  Rows of R beyond the rank of the stack are zero."""

    def __init__(self, n: int) -> None:
        self.n = int(n)
        self.rows = 0
        self._R = np.zeros((self.n, self.n), order="F")

    def add(self, block: np.ndarray) -> None:
        """Feed a block (m_k, n) of rows (any m_k >= 0)."""
        import scipy.linalg as sla

        block = np.asarray(block, float)
        m = block.shape[0]
        if m == 0 or self.n == 0:
            self.rows += m
            return
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
