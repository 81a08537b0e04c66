"""The datum: conditions that fix what the data cannot see, and nothing else.

Multilateration with estimated stations cannot see a rigid motion of the whole point cloud,
and an error model has reparameterisations the volumetric error does not see either (a
constant offset of the tool is the same field as a constant positioning error).  These are
the null directions of the *full* Jacobian (error parameters, stations, dead lengths
together).  A datum picks one representative: it must remove null directions and never
constrain a combination the data determine, otherwise it changes the fit (paper 002 eq. 9
and ISO 230 conventions, applied blindly, do exactly that as soon as the tool offset
varies: "angular errors zero at the reference" then forbids the tool orientation the data
see).

So the datum is built from *candidate* conditions, in a documented order of preference, and
a candidate is imposed only while it removes a null direction of the Jacobian of the data at
hand (:func:`select_conditions`).  Invariant: the weighted residuals of the datum'd fit equal
those of the fit without any datum (tests/test_datum.py checks it on every bundled model and
datum option).  Conditions that are not imposed are reported with the value they take.

Candidates, in order of preference (``datum="iso230"``):

1. positioning error motion of each linear axis zero at its reference position;
2. straightness error motions of each linear axis zero at both ends of its travel;
3. angular error motions of each linear axis zero at its reference position;
4. every component error motion of a rotary axis zero at its reference position;
5. the tool's zero position (``EX0T EY0T EZ0T``) zero;
6. the tool's zero orientation (``EA0T EB0T EC0T``) zero;
7. location errors (squareness, rotary axis lines) zero.

``datum="reference"`` is the same with straightness zero at the reference position (one
condition instead of two); ``datum="none"`` has no candidates (null directions are then held
by pivoting, see :mod:`volcal.analysis.identifiability`).  Axes come in chain order within
each class.  Values of the conditions are in the parameters' units (mm, rad).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:  # pandas is imported where the table is built
    import pandas as pd

from volcal.base.linalg import scale_columns
from volcal.base.units import report_factor, report_unit

DatumName = Literal["iso230", "reference", "none"]
DATUMS: tuple[str, ...] = ("iso230", "reference", "none")

#: A candidate is imposed when the part of its (column-scaled, normalised) row that acts on
#: the null space left by the candidates already imposed exceeds this.
NULL_TOL = 1e-2


@dataclass(frozen=True)
class Condition:
    """One candidate datum condition ``row @ theta = 0``.

    label: readable form (``"EXX = 0 at reference position"``); error: the error quantity
    it holds; klass: the preference class (see the module docstring); row: (n_params,)
    coefficients on theta (mm, rad); unit: ``"mm"`` or ``"rad"`` (unit of its value).
    """

    label: str
    error: str
    klass: str
    row: np.ndarray
    unit: str


_CLASSES = (
    "positioning",
    "straightness",
    "angular",
    "rotary",
    "tool position",
    "tool orientation",
    "location",
)


def candidate_conditions(error_model, datum: str) -> list[Condition]:
    """The candidate conditions of a datum option in order of preference (module doc).

    error_model: :class:`volcal.model.errors.ErrorModel`; datum: ``iso230``, ``reference`` or
    ``none``."""
    if datum not in DATUMS:
        raise ValueError(f"unknown datum {datum!r}; expected one of {list(DATUMS)}")
    if datum == "none":
        return []
    em = error_model
    out: dict[str, list[Condition]] = {c: [] for c in _CLASSES}
    for k, s in enumerate(em.errors):
        idx = np.flatnonzero(em.param_error_arr == k)
        if s.kind in ("location", "tool"):
            row = np.zeros(em.n_params)
            row[idx] = 1.0
            klass = (
                "location"
                if s.kind == "location"
                else ("tool position" if s.quantity == "translation" else "tool orientation")
            )
            out[klass].append(Condition(f"{s.name} = 0", s.name, klass, row, s.unit))
            continue
        a = em.spec.axis(s.axis)
        lo, hi, rot = em._axis_range(s)
        ref = np.deg2rad(a.reference) if rot else a.reference
        if rot:
            klass = "rotary"
        elif s.quantity == "rotation":
            klass = "angular"
        elif s.component == a.dir_index:
            klass = "positioning"
        else:
            klass = "straightness"
        points = [(ref, "reference position")]
        if klass == "straightness" and datum == "iso230":
            points = [(lo, "start of travel"), (hi, "end of travel")]
        for x, where in points:
            row = np.zeros(em.n_params)
            row[idx] = [float(np.ravel(c)[0]) for c in em._basis_columns(k, np.array([x]))]
            out[klass].append(Condition(f"{s.name} = 0 at {where}", s.name, klass, row, s.unit))
    return [c for klass in _CLASSES for c in out[klass]]


def null_space(
    J: np.ndarray, fixed: np.ndarray | None = None, *, n_rows: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Null space of J restricted to the free variables, on column-scaled variables.

    Returns (free indices, d, N): a null direction in the free variables is ``d * N[:, j]``
    (N orthonormal, (n_free, k)).  Rank tolerance max(m, n) eps s_max (DESIGN.md).

    J may be any matrix with the Jacobian's J^T J, e.g. its R factor
    (:meth:`volcal.problem.residuals.DenseJacobian.r_factor`); ``n_rows`` is then the
    Jacobian's number of rows m (the tolerance's)."""
    rows, n = np.shape(J)
    m = rows if n_rows is None else int(n_rows)
    free, _, d, A = scale_columns(J, fixed)
    # one QR of the tall matrix, then the SVD of its small R factor
    R = np.linalg.qr(A, mode="r")[: len(free)] if rows > len(free) else A
    _, s, Vt = np.linalg.svd(R, full_matrices=True)
    s_full = np.zeros(len(free))
    s_full[: len(s)] = s
    tol = max(m, n) * np.finfo(float).eps * (s_full[0] if len(s_full) else 0.0)
    rank = int(np.sum(s_full > tol))
    return free, d, Vt[rank:].T


def select_conditions(
    J: np.ndarray,
    C: np.ndarray,
    fixed: np.ndarray | None = None,
    *,
    tol: float = NULL_TOL,
    n_rows: int | None = None,
) -> np.ndarray:
    """Which candidate rows to impose: mask over the rows of C.

    J: (m, n) Jacobian of the whitened residuals wrt the (solver-scaled) variables; C: (c, n)
    candidate rows on the same variables, in order of preference; fixed: variables held
    (J may be the Jacobian's R factor, ``n_rows`` then its number of rows: :func:`null_space`).
    A row is imposed when it removes a null direction left by the rows imposed before it, so
    the imposed set ``C_s`` has ``C_s N`` of full row rank: for any minimiser x there is a
    null direction v with ``C_s (x + v) = 0``, and the minimum is unchanged."""
    C = np.asarray(C, float)
    keep = np.zeros(C.shape[0], bool)
    if C.shape[0] == 0:
        return keep
    free, d, N = null_space(J, fixed, n_rows=n_rows)
    if N.shape[1] == 0:
        return keep
    Cy = C[:, free] * d[None, :]
    basis = np.zeros((0, N.shape[1]))
    for i, cy in enumerate(Cy):
        nrm = np.linalg.norm(cy)
        if nrm == 0:
            continue
        v = (cy / nrm) @ N
        if len(basis):
            v = v - basis.T @ (basis @ v)
        if np.linalg.norm(v) > tol:
            basis = np.vstack([basis, v / np.linalg.norm(v)])
            keep[i] = True
            if len(basis) == N.shape[1]:
                break
    return keep


def imposed_parameters(
    conditions: list[Condition], active: np.ndarray, n_params: int, *, tol: float = 1e-9
) -> np.ndarray:
    """Which parameters the imposed conditions alone set (to zero): mask (n_params,).

    A parameter is imposed when its unit vector lies in the row space of the imposed
    condition rows (e.g. a squareness or a location error held at zero): its value is a
    convention, not a measurement, whatever the data.  Parameters that a condition only
    ties to others (the coefficients of a motion held at zero at its reference position)
    are not imposed: the data determine them together with the others."""
    rows = [c.row for c, on in zip(conditions, np.asarray(active, bool)) if on]
    if not rows:
        return np.zeros(n_params, bool)
    C = np.asarray(rows, float)[:, :n_params]
    # row space basis; membership of a unit vector does not depend on column scaling
    _, s, vt = np.linalg.svd(C, full_matrices=False)
    V = vt[s > s[0] * 1e-12] if len(s) and s[0] > 0 else vt[:0]
    return np.asarray(np.sum(V * V, axis=0) > 1.0 - tol, bool)


def condition_table(
    conditions: list[Condition], imposed: np.ndarray, theta: np.ndarray
) -> pd.DataFrame:
    """condition, class, imposed, value (um or urad), unit: every candidate with the value
    it takes at theta (mm / rad).  An imposed condition holds exactly (value 0 to rounding);
    the others take whatever the data say."""
    import pandas as pd

    theta = np.asarray(theta, float)
    vals = [float(c.row @ theta) * report_factor(c.unit) for c in conditions]
    return pd.DataFrame(
        {
            "condition": [c.label for c in conditions],
            "class": [c.klass for c in conditions],
            "imposed": np.asarray(imposed, bool)[: len(conditions)],
            "value": vals,
            "unit": [report_unit(c.unit) for c in conditions],
        }
    )
