"""Error motions as functions of axis position, and the datum conventions that fix them.

Every error quantity of a machine (see :func:`volcal.model.spec.error_symbols`) gets a form
(:class:`ErrorForm`, docs/error_bases.md):

* ``poly``: a Legendre series of a chosen degree in the normalised axis position
  s = 2 (q - q_min) / (q_max - q_min) - 1 in [-1, 1].  Legendre rather than monomials:
  the columns stay nearly orthogonal, so the identification stays well conditioned.
  The default for linear axes and for rotary axes that turn less than a full turn.
* ``fourier``: 1, cos(k x), sin(k x) for k = 1 .. n, x the angle in rad (rotary axes).
  The error motions of a table that turns a full turn are periodic (ISO 230-7), which
  no polynomial follows: the default for a rotary axis whose travel spans >= 360 deg,
  with n the default degree.
* ``bspline``: a clamped uniform cubic B-spline with a given number of segments over the
  travel (segments + 3 functions; local, C2, reproduces cubics); beyond the travel the
  end segments' cubics continue.
* ``table``: piecewise-linear interpolation between values at a grid of axis positions
  (what a controller's compensation table holds);
* ``constant``: one value, the only form location and tool errors take.

Which form an error motion gets, first match wins: ``forms[error name]``,
``forms[axis name]`` (the Python API, ``volcal identify --basis``), the model file's
``error_basis`` then ``basis`` of its axis, then ``default`` (a Legendre ``default`` means
Fourier of the same degree on a full-turn rotary axis).

The error value at a pose is linear in the parameters: e(q) = B(q) theta.  Datum
conventions are linear equality constraints C theta = 0:

* ``"iso230"`` (paper 002 eq. 9, ISO 230-style): positioning and angular errors of a
  linear axis are zero at its reference position, its straightness errors are zero at both
  ends of travel; every component error motion of a rotary axis is zero at its reference.
* ``"reference"``: every component error motion is zero at its axis' reference position.
* ``"none"``: no constraint (the identification then detects and reports the gauge).

Parameters are named ``<error>_<k>`` for the k-th Legendre coefficient, ``<error>_0``,
``<error>_c<k>``, ``<error>_s<k>`` for the Fourier coefficients of 1, cos(k x), sin(k x),
``<error>_b<j>`` for the j-th B-spline coefficient, ``<error>@<pos>`` for a table value at
axis position pos (file units) and ``<error>`` for a constant; units are those of the error
(mm or rad).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import lru_cache
from typing import Any, Literal

import casadi as ca
import numpy as np

from volcal.base.exceptions import InputError
from volcal.model.spec import BASIS_KINDS, ErrorForm, ErrorSymbol, MachineSpec, error_symbols

__all__ = [
    "ErrorForm",
    "ErrorModel",
    "Datum",
    "legendre",
    "fourier",
    "bspline",
    "parse_basis",
    "BASIS_KINDS",
]

Datum = Literal["iso230", "reference", "none"]


def _is_casadi(x) -> bool:
    return isinstance(x, (ca.SX, ca.MX, ca.DM))


def legendre(s: np.ndarray | ca.SX, degree: int) -> list:
    """P_0..P_degree at s by Bonnet's recurrence (works for numpy arrays and CasADi SX)."""
    out = [s * 0 + 1.0]
    if degree >= 1:
        out.append(s)
    for n in range(1, degree):
        out.append(((2 * n + 1) * s * out[n] - n * out[n - 1]) / (n + 1))
    return out


def fourier(x, degree: int) -> list:
    """1, cos(x), sin(x), ..., cos(n x), sin(n x) at angle x (rad), n = degree (numpy arrays
    or CasADi SX)."""
    cos, sin = (ca.cos, ca.sin) if _is_casadi(x) else (np.cos, np.sin)
    out = [x * 0 + 1.0]
    for k in range(1, degree + 1):
        out += [cos(k * x), sin(k * x)]
    return out


@lru_cache(maxsize=64)
def _bspline_coefficients(segments: int) -> np.ndarray:
    """(segments + 3, segments, 4): the cubic of each clamped uniform B-spline basis
    function on each segment, coefficients of 1, u, u^2, u^3 in the local u in [0, 1]."""
    from scipy.interpolate import BSpline

    m = segments
    t = np.r_[[0.0] * 3, np.arange(m + 1, dtype=float), [float(m)] * 3]
    u = np.array([0.0, 1 / 3, 2 / 3, 1.0])
    V = np.vander(u, 4, increasing=True)
    out = np.zeros((m + 3, m, 4))
    for j in range(m + 3):
        c = np.zeros(m + 3)
        c[j] = 1.0
        b = BSpline(t, c, 3, extrapolate=True)
        for i in range(m):
            out[j, i] = np.linalg.solve(V, b(np.minimum(i + u, m)))
    out[np.abs(out) < 1e-13] = 0.0
    return out


def bspline(x, lo: float, hi: float, segments: int) -> list:
    """The segments + 3 clamped uniform cubic B-splines on [lo, hi] at x (numpy arrays,
    vectorised, or CasADi SX through ``if_else``); beyond [lo, hi] the end segments'
    cubics continue (the functions still sum to one and still reproduce cubics)."""
    m = segments
    C = _bspline_coefficients(m)
    h = (hi - lo) / m
    xs = (x - lo) / h

    def cubic(c, u):
        return ((c[3] * u + c[2]) * u + c[1]) * u + c[0]

    if not _is_casadi(x):
        xs = np.asarray(xs, float)
        i = np.clip(np.floor(xs), 0, m - 1).astype(int)
        u = xs - i
        return [cubic(C[j, i].T, u) for j in range(m + 3)]
    out = []
    for j in range(m + 3):
        a, b = max(0, j - 3), min(m - 1, j)  # the segments where function j is not zero
        expr = cubic(C[j, m - 1], xs - (m - 1)) if b == m - 1 else xs * 0
        for i in range(min(b, m - 2), a - 1, -1):
            expr = ca.if_else(xs < i + 1, cubic(C[j, i], xs - i), expr)
        if a > 0:
            expr = ca.if_else(xs < a, xs * 0, expr)
        out.append(expr)
    return out


def parse_basis(text: str, *, source: str = "--basis") -> tuple[str, ErrorForm]:
    """``NAME=KIND[:N]`` (the command line's ``--basis``) -> (name, form): NAME an axis or
    error name, N the degree (poly, fourier), the number of segments (bspline) or the knots
    (table, comma-separated positions in mm / deg).  ``C=fourier:3``, ``X=bspline:6``,
    ``EXX=table:0,200,400``, ``EBX=constant``."""
    name, eq, rest = str(text).partition("=")
    kind, _, arg = rest.partition(":")
    name, kind, arg = name.strip(), kind.strip(), arg.strip()
    if not eq or not name or kind not in BASIS_KINDS:
        raise InputError(
            f"expected NAME=KIND[:N] with KIND one of {list(BASIS_KINDS)} "
            f"(e.g. C=fourier:3, X=bspline:6), got {text!r}",
            source=source,
        )
    try:
        if kind == "table":
            form = ErrorForm("table", knots=tuple(float(v) for v in arg.split(",")))
        elif kind == "constant" or not arg:
            if kind == "constant" and arg:
                raise ValueError(arg)
            form = ErrorForm(kind)  # type: ignore[arg-type]  # kind checked against BASIS_KINDS
        elif kind == "bspline":
            form = ErrorForm("bspline", segments=int(arg))
        else:
            form = ErrorForm(kind, degree=int(arg))  # type: ignore[arg-type]  # checked above
    except ValueError:
        raise InputError(
            f"bad number in {text!r}: {kind} takes "
            + {
                "table": "comma-separated knot positions",
                "bspline": "an integer number of segments",
                "constant": "no number",
            }.get(kind, "an integer degree"),
            source=source,
        ) from None
    bad = form.problem()
    if bad:
        raise InputError(f"{text!r}: {bad}", source=source)
    return name, form


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
    axis) to an :class:`ErrorForm`; component errors that neither ``forms`` nor the model's
    declarations (``basis`` / ``error_basis`` of the axis) give a form get ``default``:
    ``None`` is Legendre degree 3; a Legendre ``default`` becomes the Fourier series of the
    same degree on a rotary axis whose travel spans a full turn (module docstring).
    """

    def __init__(
        self,
        spec: MachineSpec,
        forms: Mapping[str, ErrorForm] | None = None,
        *,
        default: ErrorForm | None = None,
        datum: Datum = "iso230",
    ):
        forms = dict(forms or {})
        default = ErrorForm("poly", 3) if default is None else default
        self.spec = spec
        self.errors: list[ErrorSymbol] = error_symbols(spec)
        self.datum: Datum = datum
        names = {s.name for s in self.errors} | set(spec.axis_names)
        unknown = sorted(set(forms) - names)
        if unknown:
            raise InputError(f"error forms given for unknown error/axis names {unknown}")
        self.forms: list[ErrorForm] = []
        for s in self.errors:
            if s.kind != "component":  # location and tool errors are constants
                self.forms.append(ErrorForm("constant"))
                continue
            a = spec.axis(s.axis)
            f = forms.get(s.name, forms.get(s.axis))
            if f is None:
                f = dict(a.error_basis).get(s.name, a.basis)
            if f is None:
                f = (
                    ErrorForm("fourier", default.degree)
                    if default.kind == "poly" and a.full_turn
                    else default
                )
            if not isinstance(f, ErrorForm):
                raise InputError(f"{s.name}: expected an ErrorForm, got {f!r}")
            bad = f.problem(a.is_rotary)
            if bad:
                raise InputError(f"{s.name} (axis {a.name}): {bad}")
            self.forms.append(f)
        self._axis_index = {a.name: k for k, a in enumerate(spec.axes)}
        # constants (location and tool errors) belong to no axis position: any column will do
        self._axis_index.setdefault("T", 0)
        self.param_names: list[str] = []
        self.param_error: list[int] = []  # index of the error quantity each parameter belongs to
        #: per parameter: its polynomial degree or harmonic number (0 for the other kinds)
        self.param_order: list[int] = []
        for k, (s, f) in enumerate(zip(self.errors, self.forms)):
            if f.kind == "constant":
                labels, order = [s.name], [0]
            elif f.kind == "poly":
                labels = [f"{s.name}_{j}" for j in range(f.degree + 1)]
                order = list(range(f.degree + 1))
            elif f.kind == "fourier":
                labels, order = [f"{s.name}_0"], [0]
                for j in range(1, f.degree + 1):
                    labels += [f"{s.name}_c{j}", f"{s.name}_s{j}"]
                    order += [j, j]
            elif f.kind == "bspline":
                labels = [f"{s.name}_b{j}" for j in range(f.n_params)]
                order = [0] * len(labels)
            else:
                labels = [f"{s.name}@{v:g}" for v in f.knots]
                order = [0] * len(labels)
            self.param_names += labels
            self.param_error += [k] * len(labels)
            self.param_order += order
        self.param_error_arr = np.asarray(self.param_error, int)
        # each error's parameters are contiguous, in error order: where each one's start
        self._param_start = np.searchsorted(self.param_error_arr, np.arange(len(self.errors)))
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
        if f.kind == "fourier":
            return fourier(x, f.degree)
        if f.kind == "bspline":
            return bspline(x, lo, hi, f.segments)
        knots = np.deg2rad(f.knots) if rot else np.asarray(f.knots, float)
        return [_hat(x, knots, j) for j in range(len(knots))]

    def basis(self, q: np.ndarray, errors: Sequence[int] | None = None) -> np.ndarray:
        """B(q): (N, n_errors, n_params) such that e = B theta; q (N, n_axes) internal units.

        With ``errors`` (indices into :attr:`errors`) only those rows, in that order: (N,
        len(errors), n_params).  A caller that needs a few errors' rows asks for them alone
        (the whole basis of the bundled 3-axis example on an axis' 401 positions is 7 MB,
        nearly all zeros, and was the peak of a small identification's memory)."""
        q = np.atleast_2d(np.asarray(q, float))
        rows = range(self.n_errors) if errors is None else [int(k) for k in errors]
        B = np.zeros((q.shape[0], len(rows), self.n_params))
        for i, k in enumerate(rows):
            cols = self._basis_columns(k, q[:, self._axis_index[self.errors[k].axis]])
            for j, c in zip(self._param_start[k] + np.arange(len(cols)), cols):
                B[:, i, j] = c
        return B

    def _columns(self, q: np.ndarray):
        """(error index, parameter index, basis column (N,)) of every parameter at poses q
        (N, n_axes) internal units; each error's columns evaluated once."""
        col = 0
        # the errors of one axis with one form share their columns: evaluated once (the
        # same numbers; 27 errors of a 3-axis machine have 3 distinct sets)
        built: dict = {}
        for k, s in enumerate(self.errors):
            key = (s.axis, self.forms[k])
            cols = built.get(key)
            if cols is None:
                cols = built[key] = [
                    np.broadcast_to(np.asarray(c, float), (q.shape[0],))
                    for c in self._basis_columns(k, q[:, self._axis_index[s.axis]])
                ]
            for c in cols:
                yield k, col, c
                col += 1

    def values(self, q: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Error values e (N, n_errors) at poses q (N, n_axes) for parameters theta."""
        q = np.atleast_2d(np.asarray(q, float))
        theta = np.asarray(theta, float)
        e = np.zeros((q.shape[0], self.n_errors))
        for k, j, c in self._columns(q):
            e[:, k] += theta[j] * c
        return e

    def apply_basis(self, A: np.ndarray, q: np.ndarray) -> np.ndarray:
        """``A @ basis(q)`` for A (N, m, n_errors) (e.g. d(point)/d(errors)): (N, m,
        n_params), without forming the basis (N, n_errors, n_params), whose entries are
        zero but for each error's own parameters (18 MB for the declared set of the bundled
        example, 1,056 points)."""
        q = np.atleast_2d(np.asarray(q, float))
        A = np.asarray(A, float)
        out = np.empty(A.shape[:2] + (self.n_params,))
        for k, j, c in self._columns(q):
            np.multiply(A[:, :, k], c[:, None], out=out[:, :, j])
        return out

    def values_function(self) -> ca.Function:
        """CasADi ``e = values(q[n_axes], theta[n_params])``, built once and reused."""
        if self._values_fn is None:
            q = ca.SX.sym("q", len(self.spec.axes))
            th = ca.SX.sym("theta", self.n_params)
            out = []
            col = 0
            # the errors of one axis with one form share their basis columns: built once
            # (CasADi's expressions, built op by op from Python, took 15 ms per problem)
            built: dict = {}
            for k, s in enumerate(self.errors):
                key = (s.axis, self.forms[k])
                cols = built.get(key)
                if cols is None:
                    cols = built[key] = self._basis_columns(k, q[self._axis_index[s.axis]])
                acc = 0
                for c in cols:
                    acc = acc + c * th[col]
                    col += 1
                out.append(acc)
            self._values_fn = ca.Function(
                "error_values", [q, th], [ca.vertcat(*out)], ["q", "theta"], ["e"], {"cse": True}
            )
        return self._values_fn

    def describe(self) -> dict[str, list[str]]:
        """{form label: [error names]} of the component error motions (readable summary)."""
        out: dict[str, list[str]] = {}
        for s, f in zip(self.errors, self.forms):
            if s.kind == "component":
                out.setdefault(f.describe(), []).append(s.name)
        return out

    def summary(self) -> str:
        """One line: each basis of the component error motions and the axes (or single
        error motions) that have it, e.g. ``Legendre polynomial, degree 3 (X, Y, Z);
        Fourier series, harmonics 1..3 (C)``."""
        groups: dict[str, list[str]] = {}
        by_axis: dict[str, set[str]] = {}
        for s, f in zip(self.errors, self.forms):
            if s.kind == "component":
                by_axis.setdefault(s.axis, set()).add(f.describe())
        for s, f in zip(self.errors, self.forms):
            if s.kind != "component":
                continue
            who = s.axis if len(by_axis[s.axis]) == 1 else s.name
            members = groups.setdefault(f.describe(), [])
            if who not in members:
                members.append(who)
        return (
            "; ".join(f"{label} ({', '.join(m)})" for label, m in groups.items())
            or "constants only"
        )

    # ---- datum constraints -------------------------------------------------------------
    def constraints(
        self, datum: Datum | None = None, *, constants: bool = False
    ) -> tuple[np.ndarray, list[str]]:
        """The ISO 230 datum conditions on the component error motions as (C, labels) with
        C theta = 0, linearly dependent rows dropped; with ``constants`` also the candidate
        conditions on location and tool errors.  These are candidates: an identification
        imposes only those that remove a null direction of the data's Jacobian
        (:mod:`volcal.model.datum`); the simulator projects drawn truths onto them."""
        from volcal.model.datum import candidate_conditions

        conds = candidate_conditions(self, self.datum if datum is None else datum)
        if not constants:
            conds = [
                c for c in conds if c.klass not in ("tool position", "tool orientation", "location")
            ]
        if not conds:
            return np.zeros((0, self.n_params)), []
        C = np.array([c.row for c in conds])
        keep = _independent_rows(C)
        return C[keep], [conds[i].label for i in keep]

    # ---- parameter vectors -------------------------------------------------------------
    def theta_from_mapping(self, values: Mapping[str, float]) -> np.ndarray:
        """A parameter vector from {name: value} (missing names are zero)."""
        unknown = sorted(set(values) - set(self.param_names))
        if unknown:
            raise InputError(
                f"unknown parameter name(s) {unknown[:5]}; expected names like "
                f"{self.param_names[:4]}"
            )
        pos = {n: i for i, n in enumerate(self.param_names)}
        th = np.zeros(self.n_params)
        for n, v in values.items():
            th[pos[n]] = v
        return th

    def fit_functions(
        self, funcs: Mapping[str, Callable[[np.ndarray], Any]], n_samples: int = 64
    ) -> np.ndarray:
        """Least-squares parameters reproducing given error functions f(x) (x internal units
        along the axis' travel); errors not in ``funcs`` are zero."""
        th = np.zeros(self.n_params)
        for k, s in enumerate(self.errors):
            if s.name not in funcs:
                continue
            # constants (location, tool errors) belong to no axis position
            lo, hi, _ = (
                (0.0, 1.0, False) if self.forms[k].kind == "constant" else self._axis_range(s)
            )
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
        if np.linalg.norm(res) > tol * max(1.0, float(np.linalg.norm(r))):
            basis = np.vstack([basis, res / np.linalg.norm(res)])
            keep.append(i)
    return keep
