"""Error motions as functions of axis position, and the datum conventions that fix them.

Every error quantity of a machine (see :func:`volcal.spec.error_symbols`) gets a form:

* ``poly``: a Legendre series of a chosen degree in the normalised axis position
  s = 2 (q - q_min) / (q_max - q_min) - 1 in [-1, 1].  Legendre rather than monomials:
  the columns stay nearly orthogonal, so the identification stays well conditioned.
* ``table``: piecewise-linear interpolation between values at a grid of axis positions
  (what a controller's compensation table holds);
* ``constant``: one value, the only form location errors take.

The error value at a pose is linear in the parameters: e(q) = B(q) theta.  Datum
conventions are linear equality constraints C theta = 0:

* ``"iso230"`` (paper 002 eq. 9, ISO 230-style): positioning and angular errors of a
  linear axis are zero at its reference position, its straightness errors are zero at both
  ends of travel; every component error motion of a rotary axis is zero at its reference.
* ``"reference"``: every component error motion is zero at its axis' reference position.
* ``"none"``: no constraint (the identification then detects and reports the gauge).

Parameters are named ``<error>_<k>`` for the k-th Legendre coefficient, ``<error>@<pos>``
for a table value at axis position pos (file units) and ``<error>`` for a constant; units
are those of the error (mm or rad).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np

from volcal.exceptions import InputError
from volcal.spec import ErrorSymbol, MachineSpec, error_symbols

Datum = Literal["iso230", "reference", "none"]


@dataclass(frozen=True)
class ErrorForm:
    """The form of one error quantity: ``poly`` (degree), ``table`` (knots in file units:
    mm or deg) or ``constant``."""

    kind: Literal["poly", "table", "constant"] = "poly"
    degree: int = 3
    knots: tuple[float, ...] = ()


def legendre(s: np.ndarray | ca.SX, degree: int) -> list:
    """P_0..P_degree at s by Bonnet's recurrence (works for numpy arrays and CasADi SX)."""
    out = [s * 0 + 1.0]
    if degree >= 1:
        out.append(s)
    for n in range(1, degree):
        out.append(((2 * n + 1) * s * out[n] - n * out[n - 1]) / (n + 1))
    return out


def _hat(x, knots: np.ndarray, j: int):
    """Piecewise-linear hat function j on the knots, held flat beyond the ends of the grid
    (works for numpy arrays and CasADi SX)."""
    lo_, hi_ = (np.minimum, np.maximum) if isinstance(x, np.ndarray) else (ca.fmin, ca.fmax)
    big = 1e30
    left = (x - knots[j - 1]) / (knots[j] - knots[j - 1]) if j > 0 else x * 0 + big
    right = (knots[j + 1] - x) / (knots[j + 1] - knots[j]) if j < len(knots) - 1 else x * 0 + big
    return hi_(0.0, lo_(1.0, lo_(left, right)))


class ErrorModel:
    """Parameterisation of every error quantity of a machine.

    ``forms`` maps error names (or axis names, applying to all component errors of that
    axis) to an :class:`ErrorForm`; unspecified component errors get ``default``.
    """

    def __init__(self, spec: MachineSpec, forms: Mapping[str, ErrorForm] | None = None, *,
                 default: ErrorForm = ErrorForm("poly", 3), datum: Datum = "iso230"):
        forms = dict(forms or {})
        self.spec = spec
        self.errors: list[ErrorSymbol] = error_symbols(spec)
        self.datum: Datum = datum
        names = {s.name for s in self.errors} | set(spec.axis_names)
        unknown = sorted(set(forms) - names)
        if unknown:
            raise InputError(f"error forms given for unknown error/axis names {unknown}")
        self.forms: list[ErrorForm] = []
        for s in self.errors:
            if s.kind == "location":
                self.forms.append(ErrorForm("constant"))
            else:
                self.forms.append(forms.get(s.name, forms.get(s.axis, default)))
        self._axis_index = {a.name: k for k, a in enumerate(spec.axes)}
        self.param_names: list[str] = []
        self.param_error: list[int] = []  # index of the error quantity each parameter belongs to
        for k, (s, f) in enumerate(zip(self.errors, self.forms)):
            if f.kind == "constant":
                labels = [s.name]
            elif f.kind == "poly":
                if f.degree < 0:
                    raise InputError(f"{s.name}: polynomial degree must be >= 0")
                labels = [f"{s.name}_{j}" for j in range(f.degree + 1)]
            else:
                if len(f.knots) < 2 or np.any(np.diff(f.knots) <= 0):
                    raise InputError(f"{s.name}: table knots must be at least two increasing "
                                     f"positions, got {f.knots}")
                labels = [f"{s.name}@{v:g}" for v in f.knots]
            self.param_names += labels
            self.param_error += [k] * len(labels)
        self.param_error_arr = np.asarray(self.param_error, int)
        self._values_fn: ca.Function | None = None

    # ---- sizes and units ---------------------------------------------------------------
    @property
    def n_params(self) -> int:
        return len(self.param_names)

    @property
    def n_errors(self) -> int:
        return len(self.errors)

    @property
    def param_units(self) -> list[str]:
        return [self.errors[k].unit for k in self.param_error]

    def _axis_range(self, s: ErrorSymbol) -> tuple[float, float, bool]:
        a = self.spec.axis(s.axis)
        lo, hi = a.travel
        return (np.deg2rad(lo), np.deg2rad(hi), True) if a.is_rotary else (lo, hi, False)

    # ---- the basis ---------------------------------------------------------------------
    def _basis_columns(self, k: int, x):
        """Basis functions of error k at internal axis position x (numpy or SX)."""
        s, f = self.errors[k], self.forms[k]
        if f.kind == "constant":
            return [x * 0 + 1.0]
        lo, hi, rot = self._axis_range(s)
        if f.kind == "poly":
            return legendre(2 * (x - lo) / (hi - lo) - 1, f.degree)
        knots = np.deg2rad(f.knots) if rot else np.asarray(f.knots, float)
        return [_hat(x, knots, j) for j in range(len(knots))]

    def basis(self, q: np.ndarray) -> np.ndarray:
        """B(q): (N, n_errors, n_params) such that e = B theta; q (N, n_axes) internal units."""
        q = np.atleast_2d(np.asarray(q, float))
        B = np.zeros((q.shape[0], self.n_errors, self.n_params))
        col = 0
        for k, s in enumerate(self.errors):
            cols = self._basis_columns(k, q[:, self._axis_index[s.axis]])
            for c in cols:
                B[:, k, col] = c
                col += 1
        return B

    def values(self, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Error values e (N, n_errors) at poses q (N, n_axes) for parameters theta."""
        return np.einsum("nkp,p->nk", self.basis(q), np.asarray(theta, float))

    def values_function(self) -> ca.Function:
        """CasADi ``e = values(q[n_axes], theta[n_params])``, built once and reused."""
        if self._values_fn is None:
            q = ca.SX.sym("q", len(self.spec.axes))
            th = ca.SX.sym("theta", self.n_params)
            out = []
            col = 0
            for k, s in enumerate(self.errors):
                cols = self._basis_columns(k, q[self._axis_index[s.axis]])
                acc = 0
                for c in cols:
                    acc = acc + c * th[col]
                    col += 1
                out.append(acc)
            self._values_fn = ca.Function("error_values", [q, th], [ca.vertcat(*out)],
                                          ["q", "theta"], ["e"], {"cse": True})
        return self._values_fn

    # ---- datum constraints -------------------------------------------------------------
    def constraints(self, datum: Datum | None = None) -> tuple[np.ndarray, list[str]]:
        """Datum constraints as (C, labels) with C theta = 0; linearly dependent rows dropped."""
        datum = self.datum if datum is None else datum
        rows, labels = [], []
        if datum == "none":
            return np.zeros((0, self.n_params)), []
        for k, s in enumerate(self.errors):
            if s.kind != "component":
                continue
            a = self.spec.axis(s.axis)
            lo, hi, rot = self._axis_range(s)
            ref = np.deg2rad(a.reference) if rot else a.reference
            straightness = (datum == "iso230" and not rot and s.quantity == "translation"
                            and s.component != a.dir_index)
            points = [(lo, "start of travel"), (hi, "end of travel")] if straightness \
                else [(ref, "reference position")]
            for x, where in points:
                r = np.zeros(self.n_params)
                idx = np.flatnonzero(self.param_error_arr == k)
                r[idx] = [np.ravel(c)[0] for c in self._basis_columns(k, np.array([x]))]
                rows.append(r)
                labels.append(f"{s.name} = 0 at {where}")
        C = np.array(rows).reshape(-1, self.n_params)
        keep = _independent_rows(C)
        return C[keep], [labels[i] for i in keep]

    # ---- parameter vectors -------------------------------------------------------------
    def theta_from_mapping(self, values: Mapping[str, float]) -> np.ndarray:
        """A parameter vector from {name: value} (missing names are zero)."""
        unknown = sorted(set(values) - set(self.param_names))
        if unknown:
            raise InputError(f"unknown parameter name(s) {unknown[:5]}; expected names like "
                             f"{self.param_names[:4]}")
        pos = {n: i for i, n in enumerate(self.param_names)}
        th = np.zeros(self.n_params)
        for n, v in values.items():
            th[pos[n]] = v
        return th

    def fit_functions(self, funcs: Mapping[str, callable], n_samples: int = 64) -> np.ndarray:
        """Least-squares parameters reproducing given error functions f(x) (x internal units
        along the axis' travel); errors not in ``funcs`` are zero."""
        th = np.zeros(self.n_params)
        for k, s in enumerate(self.errors):
            if s.name not in funcs:
                continue
            lo, hi, _ = self._axis_range(s)
            x = np.linspace(lo, hi, n_samples)
            A = np.column_stack([np.broadcast_to(c, x.shape) for c in self._basis_columns(k, x)])
            y = np.asarray(funcs[s.name](x), float)
            idx = np.flatnonzero(self.param_error_arr == k)
            th[idx] = np.linalg.lstsq(A, np.broadcast_to(y, x.shape), rcond=None)[0]
        return th


def _independent_rows(C: np.ndarray, tol: float = 1e-10) -> list[int]:
    """Indices of a maximal linearly independent subset of the rows of C, in order."""
    keep: list[int] = []
    basis = np.zeros((0, C.shape[1]))
    for i, r in enumerate(C):
        if not np.any(r):
            continue
        res = r - basis.T @ (basis @ r) if len(basis) else r.copy()
        if np.linalg.norm(res) > tol * max(1.0, np.linalg.norm(r)):
            basis = np.vstack([basis, res / np.linalg.norm(res)])
            keep.append(i)
    return keep
