"""Grids for compensation tables: spacing from the error's curvature, nodes, linear
interpolation as a controller does it, table fits, and controller limits.

**Spacing.**  Linear interpolation between nodes h apart misses a function f by at most
``h^2 max|f''| / 8``.  A compensation adds several tables (or interpolates along several
axes); with S_j the largest second derivative along axis j of everything tabulated over
that axis (expressed at the tool point, in um, so angular errors count with their lever
arm), the interpolation error at the tool point is at most ``sum_j h_j^2 S_j / 8``.
:func:`choose_spacing` picks the h_j that meet a stated tolerance with the fewest nodes
(h_j proportional to (L_j / S_j)^(1/3), L_j the travel), and the formats then measure the
interpolation error they really have.

**Interpolation as a controller does it.**  Values at uniformly spaced nodes, linear
between them, held constant beyond the ends; a full-turn rotary axis is periodic (the
position is taken modulo 360 deg into the table's range, whose first and last values are
equal).  :func:`interp1` and :func:`multilinear` implement exactly that.

**Limits.**  :func:`check_limit` raises :class:`LimitError` naming the controller limit
(points per table, number of tables, ...) and the option that changes it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from volcal.base.exceptions import InputError

__all__ = [
    "LimitError",
    "check_limit",
    "halton",
    "workspace_sample",
    "curvature_1d",
    "curvature_nd",
    "choose_spacing",
    "uniform_nodes",
    "interp1",
    "hat_matrix",
    "multilinear",
    "Spacing",
]

_PRIMES = (2, 3, 5, 7, 11, 13, 17, 19, 23, 29, 31, 37)


class LimitError(InputError):
    """A compensation that does not fit the target controller's limits."""


def check_limit(value: int, limit: int | None, what: str, limit_name: str, hint: str) -> None:
    """Raise :class:`LimitError` when ``value`` exceeds ``limit`` (None: no limit)."""
    if limit is not None and value > limit:
        raise LimitError(f"{what}: {value}, more than the limit of {limit} ({limit_name}); {hint}")


def halton(n: int, d: int, skip: int = 1) -> np.ndarray:
    """The points skip .. skip + n - 1 of the d-dimensional Halton sequence in [0, 1)^d."""
    out = np.empty((n, d))
    idx = np.arange(skip, skip + n)
    for j in range(d):
        b = _PRIMES[j]
        f, r, i = 1.0, np.zeros(n), idx.copy()
        while np.any(i > 0):
            f /= b
            r += f * (i % b)
            i //= b
        out[:, j] = r
    return out


def workspace_sample(
    lo: np.ndarray, hi: np.ndarray, n: int, *, skip: int = 1, corners: bool = True
) -> np.ndarray:
    """n Halton poses in the box [lo, hi] (internal units), plus its corners (up to 64)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = len(lo)
    pts = lo + halton(n, d, skip) * (hi - lo)
    if corners and d <= 6:
        c = np.array(np.meshgrid(*[[0.0, 1.0]] * d, indexing="ij")).reshape(d, -1).T
        pts = np.vstack([lo + c * (hi - lo), pts])
    return pts


def curvature_1d(fun, lo: float, hi: float, *, periodic: bool = False, n: int = 2049) -> np.ndarray:
    """max |f''| of each column of ``fun(x)`` (x an (n,) array of positions in [lo, hi],
    returning (n,) or (n, m)) from second differences on n points."""
    x = np.linspace(lo, hi, n)
    y = np.asarray(fun(x), float)
    y = y[:, None] if y.ndim == 1 else y
    h = x[1] - x[0]
    if periodic:  # the last point repeats the first: close the loop
        yy = np.vstack([y[-2:-1], y, y[1:2]])
        d2 = (yy[2:] - 2 * yy[1:-1] + yy[:-2]) / h**2
    else:
        d2 = (y[2:] - 2 * y[1:-1] + y[:-2]) / h**2
    return np.max(np.abs(d2), axis=0) if len(d2) else np.zeros(y.shape[1])


def curvature_nd(
    fun, lo: np.ndarray, hi: np.ndarray, *, n: int = 400, steps: int = 48
) -> np.ndarray:
    """max over a sample of |d^2 f / d q_j^2| for each axis j (the largest over f's
    columns, which ``fun(q)`` returns as (N, m) for poses q (N, d)), from second
    differences with step (hi - lo) / ``steps``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    d = len(lo)
    h = (hi - lo) / steps
    base = workspace_sample(lo + h, hi - h, n)
    out = np.zeros(d)
    f0 = np.asarray(fun(base), float)
    for j in range(d):
        dq = np.zeros(d)
        dq[j] = h[j]
        fp = np.asarray(fun(base + dq), float)
        fm = np.asarray(fun(base - dq), float)
        d2 = (fp - 2 * f0 + fm) / h[j] ** 2
        out[j] = float(np.max(np.abs(d2))) if d2.size else 0.0
    return out


@dataclass(frozen=True)
class Spacing:
    """Node spacing per axis (internal units) and the interpolation bound it gives (um)."""

    h: np.ndarray
    bound_um: float


def choose_spacing(
    lengths: Sequence[float],
    curvatures_um: Sequence[float] | np.ndarray,
    tolerance_um: float,
    *,
    min_intervals: Sequence[int] | None = None,
) -> Spacing:
    """Spacings h_j meeting ``sum_j h_j^2 S_j / 8 <= tolerance`` with the fewest nodes
    (minimise sum_j L_j / h_j: h_j = c (L_j / S_j)^(1/3)); S_j in um per unit^2.  An axis
    with S_j = 0 gets its whole length (or ``min_intervals``)."""
    L = np.asarray(lengths, float)
    S = np.asarray(curvatures_um, float)
    mi = np.ones(len(L), int) if min_intervals is None else np.asarray(min_intervals, int)
    if tolerance_um <= 0 or not math.isfinite(tolerance_um):
        raise InputError(f"expected a tolerance > 0 um, got {tolerance_um!r}", source="tolerance")
    h = L / mi
    pos = S > 0
    if pos.any():
        w = (L[pos] / S[pos]) ** (1 / 3)
        c2 = 8 * tolerance_um / np.sum(w**2 * S[pos])
        h[pos] = np.minimum(np.sqrt(c2) * w, L[pos] / mi[pos])
    # whole intervals: the uniform grid's real spacing
    n_int = np.maximum(mi, np.ceil(L / h - 1e-9).astype(int))
    h = L / n_int
    return Spacing(h, float(np.sum(h**2 * S) / 8))


def uniform_nodes(lo: float, hi: float, h: float) -> np.ndarray:
    """Uniform nodes from lo to hi (both included) at most h apart."""
    n = max(1, int(math.ceil((hi - lo) / h - 1e-9)))
    return np.linspace(lo, hi, n + 1)


def _locate(nodes: np.ndarray, x: np.ndarray, periodic: bool) -> tuple[np.ndarray, np.ndarray]:
    """(interval index i, weight w of node i + 1) of positions x on uniform nodes;
    clamped at the ends, or taken modulo the range when periodic."""
    lo, hi = nodes[0], nodes[-1]
    x = np.asarray(x, float)
    if periodic:
        x = lo + np.mod(x - lo, hi - lo)
    else:
        x = np.clip(x, lo, hi)
    n = len(nodes) - 1
    s = (x - lo) / (hi - lo) * n
    i = np.clip(np.floor(s).astype(int), 0, n - 1)
    return i, s - i


def interp1(
    nodes: np.ndarray, values: np.ndarray, x: np.ndarray, *, periodic: bool = False
) -> np.ndarray:
    """Linear interpolation on uniform nodes (values (n,) or (n, m)), held at the ends or
    periodic."""
    values = np.asarray(values, float)
    i, w = _locate(np.asarray(nodes, float), x, periodic)
    if values.ndim == 2:
        w = w[:, None]
    return values[i] * (1 - w) + values[i + 1] * w


def hat_matrix(nodes: np.ndarray, x: np.ndarray, *, periodic: bool = False):
    """Sparse (len(x), n_nodes) matrix H with ``H @ values`` = :func:`interp1`; for a
    periodic table the last node is the first one (n_nodes - 1 columns)."""
    from scipy import sparse

    nodes = np.asarray(nodes, float)
    i, w = _locate(nodes, x, periodic)
    m = len(nodes) - 1 if periodic else len(nodes)
    j2 = i + 1
    if periodic:
        j2 = np.where(j2 == len(nodes) - 1, 0, j2)
    rows = np.r_[np.arange(len(i)), np.arange(len(i))]
    return sparse.csr_matrix((np.r_[1 - w, w], (rows, np.r_[i, j2])), shape=(len(i), m))


def multilinear(
    nodes: Sequence[np.ndarray], values: np.ndarray, x: np.ndarray, periodic: Sequence[bool]
) -> np.ndarray:
    """Multilinear interpolation of ``values`` (n_1, ..., n_d, m) on uniform nodes at
    points x (N, d)."""
    d = len(nodes)
    idx, wts = [], []
    for j in range(d):
        i, w = _locate(np.asarray(nodes[j], float), x[:, j], periodic[j])
        idx.append(i)
        wts.append(w)
    out = np.zeros((len(x), values.shape[-1]))
    for corner in range(2**d):
        bits = [(corner >> j) & 1 for j in range(d)]
        w = np.ones(len(x))
        ii = []
        for j, b in enumerate(bits):
            w = w * (wts[j] if b else 1 - wts[j])
            ii.append(idx[j] + b)
        out += w[:, None] * values[tuple(ii)]
    return out


# ======================================================================================
# component error tables (ISG, generic): error motions on uniform nodes per axis


@dataclass
class ComponentTables:
    """Component error motions tabulated per axis (internal units).

    axes: the axes with a table, chain order; nodes[axis] (internal positions);
    columns[axis]: the error names of its columns; values[axis]: (n_nodes, n_columns)
    mm / rad; folded: the tool errors folded into ``fold_axis``'s columns (empty when
    none); constants: {name: value} of the errors written as constants; spacing;
    interp_max_um: the interpolation error measured at the tool point (largest over the
    check sample and tool offsets); not_carried: what these tables leave out.
    """

    axes: list[str]
    nodes: dict[str, np.ndarray]
    columns: dict[str, list[str]]
    values: dict[str, np.ndarray]
    periodic: dict[str, bool]
    constants: dict[str, float]
    folded: list[str]
    fold_axis: str | None
    spacing: Spacing
    interp_max_um: float
    not_carried: list[str]

    def errors_at(self, field, q: np.ndarray) -> np.ndarray:
        """Every error quantity (N, n_errors) the tables and constants give at poses q
        (what a controller holding these tables uses; errors in neither are zero)."""
        q = np.atleast_2d(np.asarray(q, float))
        names = [s.name for s in field.errors_list]
        pos = {n: i for i, n in enumerate(names)}
        e = np.zeros((len(q), len(names)))
        for n, v in self.constants.items():
            e[:, pos[n]] = v
        for ax in self.axes:
            a = field.axis(ax)
            vals = interp1(
                self.nodes[ax], self.values[ax], q[:, a.index], periodic=self.periodic[ax]
            )
            for j, n in enumerate(self.columns[ax]):
                e[:, pos[n]] = vals[:, j]
        return e


def _rotation(i: int, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) by ``angle`` about machine axis i."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros((len(angle), 3, 3))
    j, k = (i + 1) % 3, (i + 2) % 3
    R[:, i, i] = 1
    R[:, j, j], R[:, j, k], R[:, k, j], R[:, k, k] = c, -s, s, c
    return R


def tool_fold(field, x: np.ndarray) -> tuple[str | None, np.ndarray]:
    """The tool's zero position and orientation errors (EX0T ... EC0T) expressed as
    component errors of the last tool-branch axis J at positions x of J: (J, (N, 6)
    additions to EXJ EYJ EZJ EAJ EBJ ECJ).  Exact to first order (docs/compensation.md):
    the tool frame sits on J's moving component, so for a linear J the additions are the
    constants themselves; for a rotary J with nominal centre c and rotation R(q) they are
    R(q) (d0 + phi x c) and R(q) phi.  (None, zeros) when no axis carries the tool."""
    tool_axes = [a for a in field.axes if a.branch == "tool"]
    e0 = field.errors(field.reference[None])[0]
    names = [s.name for s in field.errors_list]
    d0 = np.array([e0[names.index(f"E{c}0T")] if f"E{c}0T" in names else 0.0 for c in "XYZ"])
    phi = np.array([e0[names.index(f"E{c}0T")] if f"E{c}0T" in names else 0.0 for c in "ABC"])
    x = np.asarray(x, float)
    if not tool_axes:
        return None, np.zeros((len(x), 6))
    a = tool_axes[-1]
    if not a.rotary:
        return a.name, np.tile(np.r_[d0, phi], (len(x), 1))
    R = _rotation(a.dir_index, a.dir_sign * x)
    c = np.asarray(a.center, float)
    return a.name, np.hstack([R @ (d0 + np.cross(phi, c)), R @ phi])


def component_tables(
    field,
    tools: np.ndarray,
    tolerance_um: float,
    *,
    fold_tool: bool,
    sample: int = 400,
    max_iter: int = 5,
    turn_start: float | None = None,
) -> ComponentTables:
    """Tabulate every component error motion of the model on uniform nodes per axis,
    spaced from the curvature of the motions times their lever arm at the tool point (the
    largest first-order effect of a unit error over the workspace and ``tools``) so that
    the volumetric interpolation error stays within ``tolerance_um``; then measure it on a
    sample of the workspace and refine until it does.  With ``fold_tool`` the tool's
    zero position and orientation go into the last tool-branch axis' columns
    (:func:`tool_fold`); else they stay constants.  ``turn_start`` (rad): the tables of
    full-turn axes with periodic errors span [turn_start, turn_start + 2 pi] (the range the
    control reports, e.g. [0, 360) deg) instead of the travel."""
    errs = field.errors_list
    names = [s.name for s in errs]
    e_ref = field.errors(field.reference[None])[0]
    consts = {s.name: float(e_ref[k]) for k, s in enumerate(errs) if s.kind != "component"}
    not_carried: list[str] = []
    fold_axis, folded = None, []
    tool_names = [s.name for s in errs if s.kind == "tool"]
    if fold_tool and any(abs(consts[n]) > 0 for n in tool_names):
        fold_axis, _ = tool_fold(field, np.zeros(1))
        if fold_axis is None:
            not_carried.append(
                "the tool's zero position and orientation errors "
                f"({', '.join(tool_names)}): no tool-side axis carries them"
            )
        else:
            folded = [n for n in tool_names]
    if fold_tool:
        for n in tool_names:
            consts.pop(n)
    comp = {
        a.name: [k for k, s in enumerate(errs) if s.kind == "component" and s.axis == a.name]
        for a in field.axes
    }
    columns = {ax: [names[k] for k in ks] for ax, ks in comp.items()}
    if fold_axis is not None:
        missing = [f"E{c}{fold_axis}" for c in "XYZABC" if f"E{c}{fold_axis}" not in names]
        if missing:
            not_carried.append(
                f"the part of the tool's zero position and orientation that "
                f"{', '.join(missing)} would carry (not in the model)"
            )

    def fun(ax: str, x: np.ndarray) -> np.ndarray:
        v = field.axis_errors(ax, x)[:, comp[ax]]
        if ax == fold_axis:
            _, add = tool_fold(field, x)
            for j, c in enumerate("XYZABC"):
                n = f"E{c}{ax}"
                if n in columns[ax]:
                    v[:, columns[ax].index(n)] += add[:, j]
        return v

    axes = [a for a in field.axes if comp[a.name]]
    # the check sample: poses x tools, with the first-order effect of every error
    q = workspace_sample(field.lower, field.upper, sample, skip=101)
    tools = np.atleast_2d(np.asarray(tools, float))
    Q = np.repeat(q, len(tools), axis=0)
    T = np.tile(tools, (len(q), 1))
    J = field.error_jacobian(Q, T)  # (N K, 3, n_err)
    lever = np.linalg.norm(J, axis=1).max(axis=0)  # mm per mm / mm per rad
    S = np.zeros(len(axes))
    for i, a in enumerate(axes):
        curv = curvature_1d(lambda x, a=a: fun(a.name, x), a.lo, a.hi, periodic=a.full_turn)
        S[i] = float(np.sum(curv * lever[comp[a.name]])) * 1e3
    exact = {a.name: fun(a.name, q[:, a.index]) for a in axes}
    scale, measured = 1.0, np.inf
    for _ in range(max_iter):
        sp = choose_spacing(
            [a.length for a in axes],
            S * scale,
            tolerance_um,
            min_intervals=[8 if a.full_turn else 1 for a in axes],
        )
        nodes, values = {}, {}
        diff = np.zeros((len(q), len(names)))
        for i, a in enumerate(axes):
            lo = a.lo if turn_start is None or not a.full_turn else turn_start
            nodes[a.name] = uniform_nodes(lo, lo + (a.hi - a.lo), sp.h[i])
            values[a.name] = fun(a.name, nodes[a.name])
            if a.full_turn:
                values[a.name][-1] = values[a.name][0]
            diff[:, comp[a.name]] = (
                interp1(nodes[a.name], values[a.name], q[:, a.index], periodic=a.full_turn)
                - exact[a.name]
            )
        dd = np.einsum("nik,nk->ni", J, np.repeat(diff, len(tools), axis=0))
        measured = float(np.max(np.linalg.norm(dd, axis=1))) * 1e3 if len(dd) else 0.0
        if measured <= tolerance_um:
            break
        scale *= max(1.2, 1.1 * measured / tolerance_um)
    if measured > tolerance_um:
        raise InputError(
            f"could not meet the interpolation tolerance of {tolerance_um:g} um "
            f"(measured {measured:.3g} um); raise --tolerance"
        )
    return ComponentTables(
        [a.name for a in axes],
        nodes,
        {a.name: columns[a.name] for a in axes},
        values,
        {a.name: a.full_turn for a in axes},
        consts,
        folded,
        fold_axis,
        sp,
        measured,
        not_carried,
    )


# ======================================================================================
# 1-D compensation tables on the axes (Siemens CEC / LEC, HEIDENHAIN *.COM)


@dataclass(eq=False)
class AxisTable:
    """One 1-D table: ``values`` at ``nodes`` of axis ``input`` (internal units) added to
    the command of axis ``output`` (mm, or rad for a rotary output).  kind: ``base`` (a
    function of another axis), ``lec`` (a linear axis over its own position), ``own`` (a
    rotary axis' positioning error corrected on that axis).  No table multiplies another:
    its factor would hold a position (siemens module docstring)."""

    input: str
    output: str
    nodes: np.ndarray
    values: np.ndarray
    periodic: bool
    kind: str = "base"

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return interp1(self.nodes, self.values, x, periodic=self.periodic)

    def file_values(self, field, sign: float) -> np.ndarray:
        """The values times ``sign`` in file units: mm on a linear output axis, deg on a
        rotary one."""
        v = sign * self.values
        return np.rad2deg(v) if field.axis(self.output).rotary else v


def table_corrections(field, tables: list[AxisTable], q: np.ndarray) -> np.ndarray:
    """Axis corrections (N, n_axes), internal units, that ``tables`` give at poses q."""
    q = np.atleast_2d(np.asarray(q, float))
    c = np.zeros((len(q), field.n_axes))
    for t in tables:
        c[:, field.axis(t.output).index] += t(q[:, field.axis(t.input).index])
    return c


def correction_residual(field, tables: list[AxisTable], q: np.ndarray, tools) -> np.ndarray:
    """Volumetric error (N, 3) mm left at poses q and tool offsets after the axis
    corrections of ``tables`` (first order: dp + M c)."""
    c = table_corrections(field, tables, q)
    M = field.axis_jacobian(q, tools)
    return field.volumetric(q, tools) + np.einsum("nij,nj->ni", M, c)


@dataclass
class CorrectionTargets:
    """What the axes must do to cancel the error at one tool offset.

    own: {rotary axis: (error name, s)} with the axis' own angular positioning error
    corrected on that axis by -s e (s = +-1, from the chain); linear: the linear axes
    (model order)."""

    own: dict[str, tuple[str, float]]
    linear: list[str]
    tool: np.ndarray

    def own_value(self, field, axis: str, x: np.ndarray) -> np.ndarray:
        name, s = self.own[axis]
        k = [e.name for e in field.errors_list].index(name)
        return -s * field.axis_errors(axis, x)[:, k]

    def linear_values(self, field, q: np.ndarray) -> np.ndarray:
        """Corrections (N, n_linear) mm of the linear axes that cancel what the own
        corrections leave of the error at poses q and this tool offset."""
        q = np.atleast_2d(np.asarray(q, float))
        M = field.axis_jacobian(q, self.tool)
        r = field.volumetric(q, self.tool)
        for ax in self.own:
            a = field.axis(ax)
            r = r + M[:, :, a.index] * self.own_value(field, ax, q[:, a.index])[:, None]
        lin = [field.axis(n).index for n in self.linear]
        return -np.linalg.solve(M[:, :, lin], r[:, :, None])[:, :, 0]


def correction_targets(field, tool: np.ndarray) -> CorrectionTargets:
    """The split of the correction between the axes (see :class:`CorrectionTargets`);
    the linear axes must span the three directions."""
    lin = [a.name for a in field.axes if not a.rotary]
    if sorted(field.axis(n).dir_index for n in lin) != [0, 1, 2]:
        raise InputError(
            f"1-D compensation tables correct the tool point with three linear "
            f"axes along x, y and z; model {field.spec.name} has "
            f"{', '.join(lin) or 'none'}"
        )
    names = [s.name for s in field.errors_list]
    own: dict[str, tuple[str, float]] = {}
    q = workspace_sample(field.lower, field.upper, 64, skip=7)
    J = M = None
    for a in field.axes:
        n = f"E{'ABC'[a.dir_index]}{a.name}"
        if not a.rotary or n not in names:
            continue
        if J is None:
            J = field.error_jacobian(q, tool)
            M = field.axis_jacobian(q, tool)
        assert J is not None and M is not None
        jk, m = J[:, :, names.index(n)], M[:, :, a.index]
        s = float(np.sum(jk * m) / max(np.sum(m * m), 1e-300))
        if np.max(np.abs(jk - s * m)) <= 1e-6 * max(np.max(np.abs(jk)), 1e-300):
            own[a.name] = (n, round(s))
    return CorrectionTargets(own, lin, np.asarray(tool, float))


def fit_tables(
    field,
    tables: list[AxisTable],
    q: np.ndarray,
    target: np.ndarray,
    outputs: list[str],
    fixed: Sequence[int] = (),
) -> None:
    """Least-squares values of ``tables`` (in place) so that their sum per output axis
    matches ``target`` (N, len(outputs)) at poses q; tables listed in ``fixed`` keep
    their values (their contribution is taken from the target first).  Values common to
    several tables (constants) are split by a tiny ridge."""
    from scipy import sparse

    q = np.atleast_2d(np.asarray(q, float))
    held = set(fixed)
    vals = {i: t(q[:, field.axis(t.input).index]) for i, t in enumerate(tables) if i in held}
    for o_i, out in enumerate(outputs):
        y = target[:, o_i].copy()
        cols, owners = [], []
        for i, t in enumerate(tables):
            if t.output != out:
                continue
            if i in held:
                y -= vals[i]
                continue
            H = hat_matrix(t.nodes, q[:, field.axis(t.input).index], periodic=t.periodic)
            cols.append(H)
            owners.append((i, H.shape[1]))
        if not cols:
            continue
        A = sparse.hstack(cols).tocsr()
        N = (A.T @ A).toarray()
        d = np.diag(N).copy()
        D = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))  # unit columns, then a tiny ridge
        x = D * np.linalg.solve(D[:, None] * N * D[None, :] + 1e-9 * np.eye(len(N)), D * (A.T @ y))
        k = 0
        for i, m in owners:
            v = x[k : k + m]
            k += m
            tables[i].values = np.r_[v, v[0]] if tables[i].periodic else v


def correction_spacing(
    field, targets: CorrectionTargets, tolerance_um: float, inputs: list[str]
) -> tuple[Spacing, np.ndarray]:
    """Node spacing of the tables over each axis in ``inputs`` from the curvature of the
    corrections along it (linear axes: the linear-axis corrections, in um at the tool
    point; a rotary axis also its own correction times its lever arm).  Returns the
    spacing and the curvatures S (um per unit^2)."""
    lo, hi = field.lower, field.upper
    idx = [field.axis(n).index for n in inputs]
    curv = curvature_nd(lambda qq: targets.linear_values(field, qq), lo, hi) * 1e3
    S = curv[idx]
    if targets.own:
        qs = workspace_sample(lo, hi, 200, skip=11)
        M = field.axis_jacobian(qs, targets.tool)
        for j, n in enumerate(inputs):
            if n in targets.own:
                a = field.axis(n)
                lever = float(np.max(np.linalg.norm(M[:, :, a.index], axis=1)))
                c1 = curvature_1d(
                    lambda x, n=n: targets.own_value(field, n, x), a.lo, a.hi, periodic=a.full_turn
                )[0]
                S[j] += c1 * lever * 1e3
    axes = [field.axis(n) for n in inputs]
    sp = choose_spacing(
        [a.length for a in axes],
        S,
        tolerance_um,
        min_intervals=[8 if a.full_turn else 1 for a in axes],
    )
    return sp, S


def one_axis_tables(
    field, tool: np.ndarray, tolerance_um: float
) -> tuple[CorrectionTargets, Spacing, dict[str, np.ndarray], list[AxisTable]]:
    """The start of the 1-D tables of a control (siemens, heidenhain) for the tool offset
    ``tool`` (3,) mm: the split of the correction (:func:`correction_targets`), the node
    spacing over every axis for ``tolerance_um`` (:func:`correction_spacing`), the nodes
    (:func:`axis_table_nodes`) and the tables of the rotary axes' own angular positioning
    corrections (kind ``"own"``, values set)."""
    targets = correction_targets(field, tool)
    sp, _ = correction_spacing(field, targets, tolerance_um, [a.name for a in field.axes])
    nodes = axis_table_nodes(field, sp.h)
    own = [
        AxisTable(
            r, r, nodes[r], targets.own_value(field, r, nodes[r]), field.axis(r).full_turn, "own"
        )
        for r in targets.own
    ]
    return targets, sp, nodes, own


def axis_table_nodes(field, h: Sequence[float] | np.ndarray) -> dict[str, np.ndarray]:
    """Uniform nodes (internal units) of a 1-D table over each axis at spacing ``h`` (one
    per axis, model order): over the travel, except that a full-turn axis' table spans
    [0, 360] deg, the range the control reports it in."""
    nodes = {}
    for i, a in enumerate(field.axes):
        lo, hi = (0.0, a.hi - a.lo) if a.full_turn else (a.lo, a.hi)
        nodes[a.name] = uniform_nodes(lo, hi, h[i])
    return nodes


def table_fit_poses(field, nodes: dict[str, np.ndarray]) -> np.ndarray:
    """The poses (N, n_axes) the 1-D tables are fitted at: a Halton sample of the travel
    box, 40 poses per node of the longest table, at least 6000 and at most 40000."""
    n_fit = int(min(40000, max(6000, 40 * max(len(v) for v in nodes.values()))))
    return workspace_sample(field.lower, field.upper, n_fit, skip=3)
