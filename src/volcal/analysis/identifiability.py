"""What a data set can and cannot determine: scaled SVD, rank, named null space.

The Jacobian J (whitened residuals by variables) is analysed together with the linear
equality constraints C x = 0 (datum conventions): only directions inside null(C) count.
Columns are scaled to unit norm first, so that the rank and the condition number speak of
the experiment, not of units.  Rank tolerance: max(m, n) * eps * s_max (DESIGN.md).

Null directions are named by QR with column pivoting on the null-space basis: the pivot
columns are the variables whose values the data cannot fix (one per null direction); the
basis brought to reduced row-echelon form on those pivots gives each direction as a
combination "A + 0.8 B" in the variables' own (scaled) units.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla


@dataclass
class Identifiability:
    """Result of :func:`analyse_jacobian` (all on column-scaled variables).

    singular_values: of the scaled, constrained Jacobian, descending; rank and tol;
    condition: s_max / s_min of the identifiable part; condition_unscaled: the same without
    column scaling; null_basis: (n, k) orthonormal basis (scaled variables) of the
    unidentifiable directions; pivots: index of one variable per null direction (the one
    to fix); combinations: a readable description of each null direction; unidentifiable:
    mask of variables that take part in some null direction; weak: (singular value,
    description) of directions with s < weak_ratio * s_max that are still above tol.
    """

    names: list[str]
    singular_values: np.ndarray
    rank: int
    tol: float
    condition: float
    condition_unscaled: float
    null_basis: np.ndarray
    pivots: list[int]
    combinations: list[str]
    unidentifiable: np.ndarray
    weak: list[tuple[float, str]] = field(default_factory=list)

    @property
    def n_null(self) -> int:
        return self.null_basis.shape[1]

    def summary(self) -> str:
        lines = [f"rank {self.rank} of {len(self.names) - self._n_constrained()} free directions "
                 f"(tol {self.tol:.2e}); scaled condition number {self.condition:.3g}"]
        for c in self.combinations:
            lines.append(f"  unidentifiable: {c}")
        for s, c in self.weak:
            lines.append(f"  weak (s = {s:.2e}): {c}")
        return "\n".join(lines)

    def _n_constrained(self) -> int:
        return len(self.names) - (self.rank + self.n_null)


def _describe(v: np.ndarray, names: list[str], lead: int, rel: float = 1e-3) -> str:
    """'NAME' or 'NAME + 0.8 OTHER - 0.1 THIRD' for a direction normalised so v[lead] = 1."""
    v = v / v[lead]
    order = [lead] + [i for i in np.argsort(-np.abs(v)) if i != lead and abs(v[i]) > rel]
    parts = []
    for k, i in enumerate(order[:8]):
        c = v[i]
        if k == 0:
            parts.append(names[i])
        else:
            parts.append(f"{'-' if c < 0 else '+'} {abs(c):.3g} {names[i]}")
    if len(order) > 8:
        parts.append(f"+ ... ({len(order) - 8} more)")
    return " ".join(parts)


def _r_factor(A: np.ndarray) -> np.ndarray:
    """R of a QR factorisation (square, n x n); LAPACK geqrf through SciPy, which is much
    faster than numpy's mode='r' on tall matrices."""
    m, n = A.shape
    if m <= n:
        return np.vstack([A, np.zeros((n - m, n))]) if m < n else A.copy()
    return sla.qr(A, mode="r", check_finite=False)[0][:n]


@dataclass
class ScaledSVD:
    """SVD of the column-scaled Jacobian restricted to the free variables and to null(C).

    free: indices of the free variables; norms: their column norms; d = 1 / norms (1 for
    zero columns); Z: orthonormal basis of null(C d) in scaled free variables; R: the R
    factor of the scaled J; s, Vt: singular values (descending, padded with zeros) and right
    singular vectors of R Z; tol, rank: the rank tolerance max(m, n) eps s_max and the rank.
    A direction j in the free physical variables is ``d * (Z @ Vt[j])``.
    """

    free: np.ndarray
    norms: np.ndarray
    d: np.ndarray
    Z: np.ndarray
    R: np.ndarray
    s: np.ndarray
    Vt: np.ndarray
    tol: float
    rank: int


def scaled_constrained_svd(J: np.ndarray, C: np.ndarray | None = None,
                           fixed: np.ndarray | None = None) -> ScaledSVD:
    """The factorisation behind :func:`analyse_jacobian` (see :class:`ScaledSVD`)."""
    J = np.asarray(J, float)
    m, n = J.shape
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    free = np.flatnonzero(~fixed)
    Jf = J[:, free]
    norms = np.linalg.norm(Jf, axis=0)
    d = 1.0 / np.where(norms == 0, 1.0, norms)
    Cf = np.zeros((0, len(free))) if C is None or len(C) == 0 else np.asarray(C, float)[:, free]
    Cs = Cf * d
    Cs = Cs[np.linalg.norm(Cs, axis=1) > 0] if Cs.shape[0] else Cs
    Z = sla.null_space(Cs) if Cs.shape[0] else np.eye(len(free))
    # One QR of the tall scaled Jacobian; everything else works on its small R factor
    # (J Z and J diag(norms) Z have the singular values of R Z and R diag(norms) Z).
    R = _r_factor(Jf * d)
    _, s, Vt = np.linalg.svd(R @ Z, full_matrices=True)
    s_full = np.zeros(Z.shape[1])
    s_full[:len(s)] = s
    tol = max(m, n) * np.finfo(float).eps * (s_full[0] if len(s_full) else 0.0)
    return ScaledSVD(free, norms, d, Z, R, s_full, Vt, float(tol), int(np.sum(s_full > tol)))


def analyse_jacobian(J: np.ndarray, names: list[str], C: np.ndarray | None = None, *,
                     fixed: np.ndarray | None = None, prefer: np.ndarray | None = None,
                     weak_ratio: float = 1e-4) -> Identifiability:
    """Rank, conditioning and named null space of J under C x = 0.

    J: (m, n) Jacobian of whitened residuals; C: (c, n) equality constraints; fixed: mask of
    variables held fixed (left out of the analysis); prefer: priority per variable for being
    chosen as the one to fix in a null direction (higher is chosen first; ties by pivoting).
    """
    J = np.asarray(J, float)
    m, n = J.shape
    sv = scaled_constrained_svd(J, C, fixed)
    free, d, Z, R, s_full, Vt, tol, rank = (sv.free, sv.d, sv.Z, sv.R, sv.s, sv.Vt, sv.tol,
                                            sv.rank)
    norms, zero_col = sv.norms, sv.norms == 0
    s0 = s_full[0] if len(s_full) else 0.0
    N_y = Z @ Vt[rank:].T  # null directions in scaled free variables, orthonormal
    # condition numbers of the identifiable part
    cond = s_full[0] / s_full[rank - 1] if rank else np.inf
    su = np.linalg.svd((R * np.where(zero_col, 0.0, norms)) @ Z, compute_uv=False) \
        if rank else np.array([0.0])
    cond_u = su[0] / su[rank - 1] if rank and su[rank - 1] > 0 else np.inf

    k = N_y.shape[1]
    pivots_free: list[int] = []
    combos: list[str] = []
    full_names = [names[i] for i in free]
    if k:
        W = N_y.T.copy()
        if prefer is not None:
            W = W * (1.0 + np.asarray(prefer, float)[free])[None, :]
        _, _, piv = sla.qr(W, pivoting=True, mode="economic")
        pivots_free = [int(p) for p in piv[:k]]
        # reduced row echelon on the pivot columns: one direction per pivot variable
        R = np.linalg.solve(N_y[pivots_free, :].T, N_y.T)  # rows: directions, R[:, piv] = I
        for j, pv in enumerate(pivots_free):
            combos.append(_describe(R[j], full_names, pv))
    unident_free = np.linalg.norm(N_y, axis=1) > 1e-6 if k else np.zeros(len(free), bool)
    unident = np.zeros(n, bool)
    unident[free] = unident_free
    basis = np.zeros((n, k))
    basis[free] = N_y * d[:, None] if k else basis[free]
    weak = []
    for j in range(rank):
        if s_full[j] < weak_ratio * s0:
            v = Z @ Vt[j]
            lead = int(np.argmax(np.abs(v)))
            weak.append((float(s_full[j]), _describe(v, full_names, lead)))
    return Identifiability(list(names), s_full, rank, float(tol), float(cond), float(cond_u),
                           basis, [int(free[p]) for p in pivots_free], combos, unident, weak)
