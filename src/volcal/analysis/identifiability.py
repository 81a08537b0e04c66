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

from volcal.base.linalg import null_space, pivot_order, scale_columns


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
    #: (n, k): the null direction of each combination (variables as J's columns), scaled so
    #: that its pivot variable is 1
    directions: np.ndarray | None = None
    #: per combination: "gauge" (the volumetric error over the declared workspace and tool
    #: offsets changes at most by a rigid motion no multilateration sees) or
    #: "unidentifiable" (it changes the error somewhere); None until :func:`split_gauge`
    kinds: list[str] | None = None

    @property
    def gauge_combinations(self) -> list[str]:
        """Held null directions that only move the volumetric error rigidly (or not at all)."""
        return [c for c, k in zip(self.combinations, self.kinds or []) if k == "gauge"]

    @property
    def unidentifiable_combinations(self) -> list[str]:
        """Held null directions that change the volumetric error in the workspace."""
        if self.kinds is None:
            return list(self.combinations)
        return [c for c, k in zip(self.combinations, self.kinds) if k != "gauge"]

    @property
    def n_null(self) -> int:
        return self.null_basis.shape[1]

    def summary(self) -> str:
        lines = [
            f"rank {self.rank} of {len(self.names) - self._n_constrained()} free directions "
            f"(tol {self.tol:.2e}); scaled condition number {self.condition:.3g}"
        ]
        kinds = self.kinds or ["unidentifiable"] * len(self.combinations)
        for c, k in zip(self.combinations, kinds):
            lines.append(f"  {k}: {c}")
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
    """R of a QR factorisation (square, n x n); LAPACK geqrf through numpy (as fast as
    scipy's on tall matrices, without scipy's import: :mod:`volcal.base.linalg`)."""
    m, n = A.shape
    if m <= n:
        return np.vstack([A, np.zeros((n - m, n))]) if m < n else A.copy()
    return np.asarray(np.linalg.qr(A, mode="r"))[:n]


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


def scaled_constrained_svd(
    J: np.ndarray,
    C: np.ndarray | None = None,
    fixed: np.ndarray | None = None,
    n_rows: int | None = None,
) -> ScaledSVD:
    """The factorisation behind :func:`analyse_jacobian` (see :class:`ScaledSVD`); J may be
    the Jacobian's R factor, ``n_rows`` then the Jacobian's number of rows."""
    J = np.asarray(J, float)
    m, n = J.shape
    m = m if n_rows is None else int(n_rows)
    free, norms, d, A = scale_columns(J, fixed)
    Cf = np.zeros((0, len(free))) if C is None or len(C) == 0 else np.asarray(C, float)[:, free]
    Cs = Cf * d
    Cs = Cs[np.linalg.norm(Cs, axis=1) > 0] if Cs.shape[0] else Cs
    Z = null_space(Cs) if Cs.shape[0] else np.eye(len(free))
    # One QR of the tall scaled Jacobian; everything else works on its small R factor
    # (J Z and J diag(norms) Z have the singular values of R Z and R diag(norms) Z).
    R = _r_factor(A)
    _, s, Vt = np.linalg.svd(R @ Z, full_matrices=True)
    s_full = np.zeros(Z.shape[1])
    s_full[: len(s)] = s
    tol = max(m, n) * np.finfo(float).eps * (s_full[0] if len(s_full) else 0.0)
    return ScaledSVD(free, norms, d, Z, R, s_full, Vt, float(tol), int(np.sum(s_full > tol)))


def analyse_jacobian(
    J: np.ndarray,
    names: list[str],
    C: np.ndarray | None = None,
    *,
    fixed: np.ndarray | None = None,
    prefer: np.ndarray | None = None,
    weak_ratio: float = 1e-4,
    decide_on: np.ndarray | None = None,
    n_rows: int | None = None,
) -> Identifiability:
    """Rank, conditioning and named null space of J under C x = 0.

    J: (m, n) Jacobian of whitened residuals; C: (c, n) equality constraints; fixed: mask of
    variables held fixed (left out of the analysis); prefer: priority per variable for being
    chosen as the one to fix in a null direction (higher is chosen first; ties by pivoting);
    decide_on: the Jacobian (same variables) on which rank, null space and pivots are
    decided, when not J itself: the one at zero errors, where the first-order model's gauge
    is exact (:meth:`volcal.analysis.identify.Identifier.structural`).  Singular values,
    condition numbers and weak directions are J's; its smallest ``n_free - rank`` singular
    values belong to the directions decided null.

    J and decide_on may be R factors of the Jacobians (``J = Q R``, the same J^T J: what
    :meth:`volcal.problem.residuals.DenseJacobian.r_factor` gives) with ``n_rows`` the
    Jacobians' number of rows, for the rank tolerance.
    """
    J = np.asarray(J, float)
    n = J.shape[1]
    sv = scaled_constrained_svd(J, C, fixed, n_rows)
    sv0 = (
        sv
        if decide_on is None or decide_on is J
        else scaled_constrained_svd(decide_on, C, fixed, n_rows)
    )
    free, Z, R, s_full, Vt = (sv.free, sv.Z, sv.R, sv.s, sv.Vt)
    tol, rank, d = sv0.tol, sv0.rank, sv0.d
    norms, zero_col = sv.norms, sv.norms == 0
    s0 = s_full[0] if len(s_full) else 0.0
    N_y = sv0.Z @ sv0.Vt[rank:].T  # null directions in scaled free variables, orthonormal
    # condition numbers of the identifiable part
    cond = s_full[0] / s_full[rank - 1] if rank and s_full[rank - 1] > 0 else np.inf
    su = (
        np.linalg.svd((R * np.where(zero_col, 0.0, norms)) @ Z, compute_uv=False)
        if rank
        else np.array([0.0])
    )
    cond_u = su[0] / su[rank - 1] if rank and su[rank - 1] > 0 else np.inf

    k = N_y.shape[1]
    pivots_free: list[int] = []
    combos: list[str] = []
    full_names = [names[i] for i in free]
    if k:
        W = N_y.T.copy()
        if prefer is not None:
            W = W * (1.0 + np.asarray(prefer, float)[free])[None, :]
        piv = pivot_order(W)
        pivots_free = [int(p) for p in piv[:k]]
        # reduced row echelon on the pivot columns: one direction per pivot variable
        R = np.linalg.solve(N_y[pivots_free, :].T, N_y.T)  # rows: directions, R[:, piv] = I
        for j, pv in enumerate(pivots_free):
            combos.append(_describe(R[j], full_names, pv))
    directions = np.zeros((n, k))
    if k:
        directions[free] = (R * d[None, :]).T * (1.0 / d[pivots_free])[None, :]
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
    return Identifiability(
        list(names),
        s_full,
        rank,
        float(tol),
        float(cond),
        float(cond_u),
        basis,
        [int(free[p]) for p in pivots_free],
        combos,
        unident,
        weak,
        directions,
    )


def rigid_columns(points: np.ndarray) -> np.ndarray:
    """(3N, 6) design matrix of a small rigid motion a + w x p at points (N, 3): columns
    a_x, a_y, a_z (mm) and w_x, w_y, w_z (rad), rows x, y, z of each point."""
    points = np.asarray(points, float)
    n = len(points)
    A = np.zeros((3 * n, 6))
    A[0::3, 0] = A[1::3, 1] = A[2::3, 2] = 1.0
    x, y, z = points.T
    # w x p = (wy z - wz y, wz x - wx z, wx y - wy x)
    A[0::3, 4], A[0::3, 5] = z, -y
    A[1::3, 3], A[1::3, 5] = -z, x
    A[2::3, 3], A[2::3, 4] = y, -x
    return A


@dataclass
class FieldSets:
    """Where the volumetric error is looked at: the measured set (every distinct pose and
    tool offset of the data) and the declared set (the travel of every axis at the
    measured tool offsets).  G_*: (N, 3, n_theta) d(error)/d(theta) (mm per mm / rad);
    p_*: (N, 3) nominal tool points (mm)."""

    G_meas: np.ndarray
    p_meas: np.ndarray
    G_decl: np.ndarray
    p_decl: np.ndarray


#: a direction moves the error at a pose when it departs there from the rigid motion it
#: makes at the measured poses by more than this fraction of its largest effect
GAUGE_TOL = 1e-3
#: a unit step (1 um or 1 urad) of a null direction that moves the error by less than this
#: (mm) anywhere moves nothing (station and frame duplicates, rounding in theta)
NIL_FIELD_MM = 1e-9


def _field(G: np.ndarray, th: np.ndarray) -> np.ndarray:
    """(N, 3, k): the volumetric error each theta direction th (n_theta, k) makes where
    d(error)/d(theta) is G (N, 3, n_theta): one matrix product (an einsum over the same
    indices took ten times longer: its own loops, not BLAS)."""
    n, _, nt = G.shape
    return (G.reshape(-1, nt) @ th).reshape(n, 3, th.shape[1])


def _rigid_reference(G_meas: np.ndarray, p_meas: np.ndarray, th: np.ndarray) -> np.ndarray:
    """(6, k): the rigid motion each theta direction makes at the measured poses.  A null
    direction of the data changes no reading, so at the measured poses its field is the
    rigid motion the stations follow; that motion, not a fit over other poses, is the
    reference for deciding what else it changes."""
    F = _field(G_meas, th).reshape(-1, th.shape[1])
    A = rigid_columns(p_meas)
    return np.linalg.lstsq(A, F, rcond=None)[0]


def _deviation(G: np.ndarray, points: np.ndarray, th: np.ndarray, rigid: np.ndarray) -> np.ndarray:
    """(N, 3, k): field of each direction minus its measured-set rigid motion, mm."""
    F = _field(G, th)
    return F - (rigid_columns(points) @ rigid).reshape(F.shape)


@dataclass
class FieldNullSpace:
    """How the null directions of a fit act on the volumetric error (for ``predict``).

    theta_dirs: (n_theta, k) the error-parameter part of a basis of the null space of the
    full Jacobian (mm, rad per unit step); rigid: (6, k) the rigid motion each direction
    makes at the measured poses (mm, rad); field_scale: (k,) its largest effect over the
    measured and declared sets (mm; huge for directions that move nothing);
    n_gauge / n_unidentifiable: how many independent directions move the error over the
    declared set at most by that rigid motion / change it.
    """

    theta_dirs: np.ndarray
    rigid: np.ndarray
    field_scale: np.ndarray
    n_gauge: int
    n_unidentifiable: int

    def determined(self, G: np.ndarray, points: np.ndarray, tol: float = GAUGE_TOL) -> np.ndarray:
        """Per pose: does its volumetric error follow from the data alone (up to the rigid
        motion no multilateration sees)?  G: (N, 3, n_theta) d(error)/d(theta) at the poses
        (mm per mm / rad); points: (N, 3) their nominal tool points (mm)."""
        G = np.asarray(G, float)
        if self.theta_dirs.shape[1] == 0:
            return np.ones(len(G), bool)
        D = _deviation(G, points, self.theta_dirs, self.rigid)
        dev = np.max(np.abs(D) / self.field_scale[None, None, :], axis=(1, 2))
        return dev <= tol

    def to_dict(self) -> dict:
        return {
            "theta_dirs": self.theta_dirs.tolist(),
            "rigid": self.rigid.tolist(),
            "field_scale": self.field_scale.tolist(),
            "n_gauge": self.n_gauge,
            "n_unidentifiable": self.n_unidentifiable,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FieldNullSpace:
        nt = len(d["theta_dirs"])
        return cls(
            np.asarray(d["theta_dirs"], float).reshape(nt, -1),
            np.asarray(d["rigid"], float).reshape(6, -1),
            np.asarray(d["field_scale"], float),
            int(d["n_gauge"]),
            int(d["n_unidentifiable"]),
        )


def field_null_space(
    theta_dirs: np.ndarray, sets: FieldSets, tol: float = GAUGE_TOL
) -> FieldNullSpace:
    """Classify null directions by their effect on the volumetric error.

    theta_dirs: (n_theta, k) error-parameter part of null directions (mm, rad); sets: the
    measured and declared sets (:class:`FieldSets`)."""
    th = np.asarray(theta_dirs, float)
    k = th.shape[1]
    if k == 0:
        return FieldNullSpace(th, np.zeros((6, 0)), np.zeros(0), 0, 0)
    rigid = _rigid_reference(sets.G_meas, sets.p_meas, th)
    F_all = np.concatenate(
        [
            _field(sets.G_meas, th).reshape(-1, k),
            _field(sets.G_decl, th).reshape(-1, k),
        ]
    )
    scale = np.max(np.abs(F_all), axis=0)
    # a direction (a unit step of its variables: 1 um or 1 urad) that moves the error by
    # less than NIL_FIELD_MM anywhere moves nothing: it never flags a pose
    scale = np.where(scale <= NIL_FIELD_MM, 1e300, scale)
    D = _deviation(sets.G_decl, sets.p_decl, th, rigid).reshape(-1, k) / scale[None, :]
    # singular values of the RMS deviation (per entry, as ``determined`` judges a pose)
    sv = np.linalg.svd(D, compute_uv=False) / np.sqrt(len(D)) if D.size else np.zeros(0)
    n_unid = int(np.sum(sv > tol))
    return FieldNullSpace(th, rigid, scale, k - n_unid, n_unid)


def split_gauge(
    ident: Identifiability,
    n_theta: int,
    sets: FieldSets,
    theta_scale: np.ndarray,
    tol: float = GAUGE_TOL,
) -> Identifiability:
    """Label each held combination of ``ident`` gauge or unidentifiable (in place; also
    returned) with the same rule as :func:`field_null_space`: unidentifiable when its
    field over the declared set departs from the rigid motion it makes at the measured
    poses.  ``ident.unidentifiable`` is left as it is: a variable in a held direction of
    either kind has no value of its own (it depends on which variable was held).

    n_theta: the error parameters are the first n_theta variables; theta_scale: physical
    units per variable unit for them (mm, rad)."""
    if ident.directions is None or not ident.combinations:
        ident.kinds = []
        return ident
    th = ident.directions[:n_theta] * np.asarray(theta_scale, float)[:, None]
    fns = field_null_space(th, sets, tol)
    D = _deviation(sets.G_decl, sets.p_decl, th, fns.rigid)
    dev = np.max(np.abs(D), axis=(0, 1)) / fns.field_scale
    ident.kinds = ["unidentifiable" if v > tol else "gauge" for v in dev]
    return ident
