"""From a topology to tool-point expressions: first order (dual numbers) and exact.

Conventions (documented in docs/conventions.md):

* The chain runs workpiece -> workpiece-branch axes -> frame -> tool-branch axes -> tool.
  The tool point is expressed in the workpiece frame, which coincides with the machine
  frame when every axis is at zero.
* A positive command moves the tool in the +direction relative to the workpiece whatever
  the branch: a workpiece-branch axis moves the table by -q (ISO 841's primed axes).
* Error motions are those of the moving component (table or carriage) relative to the
  component that carries it, expressed in the carrier's orientation (ISO 230-1).  The
  reference point of the angular errors is the carriage position for a linear axis and the
  nominal centre of a rotary axis.  Errors of a workpiece-branch axis therefore act on the
  tool point with the opposite sign.
* Location errors of a linear axis tilt its direction of travel only (squareness); those of
  a rotary axis shift and tilt its average line (ISO 230-7) and leave the carried part
  undisplaced at zero angle.
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from volcal.model.spec import MachineSpec, error_symbols
from volcal.model.symbolic.dual import Dual, rigid_inverse
from volcal.model.symbolic.transforms import (
    Factor,
    Rotate,
    SmallRotate,
    Translate,
    as_dual,
    as_exact,
)

_0 = sp.Integer(0)


@dataclass(frozen=True)
class ChainExpressions:
    """Symbols and expressions of a machine's tool point (all SymPy).

    q: axis position symbols (mm, rad) in chain order; t: tool offset (mm, tool frame);
    e: error symbols in :func:`volcal.model.spec.error_symbols` order (mm, rad).
    nominal: tool point with zero errors; first_order: its first-order error part (linear in
    e); exact: the exact tool point.  All 3-vectors in the workpiece frame, mm.
    """

    q: tuple[sp.Symbol, ...]
    t: tuple[sp.Symbol, ...]
    e: tuple[sp.Symbol, ...]
    nominal: tuple[sp.Expr, ...]
    first_order: tuple[sp.Expr, ...]
    exact: tuple[sp.Expr, ...]


def _unit(i: int, scale: sp.Expr) -> tuple[sp.Expr, sp.Expr, sp.Expr]:
    v = [_0, _0, _0]
    v[i] = scale
    return tuple(v)  # type: ignore[return-value]


def _axis_factors(axis, q: sp.Symbol, err: dict[str, sp.Expr]) -> list[Factor]:
    """Factors of the moving component's pose relative to its carrier."""
    n = axis.name
    g = lambda name: err.get(name, _0)  # noqa: E731 - unselected errors are zero
    delta = (g(f"EX{n}"), g(f"EY{n}"), g(f"EZ{n}"))
    eps = (g(f"EA{n}"), g(f"EB{n}"), g(f"EC{n}"))
    i = axis.dir_index
    sign = axis.dir_sign if axis.branch == "tool" else -axis.dir_sign
    if axis.kind == "linear":
        omega = (g(f"EA0{n}"), g(f"EB0{n}"), g(f"EC0{n}"))
        return [
            SmallRotate(omega),
            Translate(_unit(i, sign * q)),
            SmallRotate(omega, inverse=True),
            Translate((_0, _0, _0), delta),
            SmallRotate(eps),
        ]
    c = tuple(sp.nsimplify(v) for v in axis.center)
    minus_c = tuple(-v for v in c)
    loc_t = (g(f"EX0{n}"), g(f"EY0{n}"), g(f"EZ0{n}"))
    loc_r = (g(f"EA0{n}"), g(f"EB0{n}"), g(f"EC0{n}"))
    neg_loc_t = tuple(-v for v in loc_t)
    return [
        # component error motion at the nominal centre, in the carrier's orientation
        Translate(c),
        Translate((_0, _0, _0), delta),
        SmallRotate(eps),
        Translate(minus_c),
        # nominal rotation about the actual average line (location errors)
        Translate(c, loc_t),
        SmallRotate(loc_r),
        Rotate(i, sign * q),
        SmallRotate(loc_r, inverse=True),
        Translate(minus_c, neg_loc_t),
    ]


def build_chain(spec: MachineSpec) -> ChainExpressions:
    """Tool-point expressions of a topology, first order and exact."""
    q = tuple(sp.Symbol(f"q_{a.name}", real=True) for a in spec.axes)
    t = tuple(sp.Symbol(f"t_{c}", real=True) for c in "xyz")
    names = [s.name for s in error_symbols(spec)]
    e = tuple(sp.Symbol(nm, real=True) for nm in names)
    err = dict(zip(names, e))

    dual_chain = Dual(sp.eye(4), sp.zeros(4))
    exact_chain = sp.eye(4)
    for axis, qa in zip(spec.axes, q):
        factors = _axis_factors(axis, qa, err)
        d = Dual(sp.eye(4), sp.zeros(4))
        x = sp.eye(4)
        for f in factors:
            d = d @ as_dual(f)
            x = x * as_exact(f)
        if axis.branch == "workpiece":
            # the workpiece sits on this axis: the chain passes through it backwards
            d = d.rigid_inverse()
            x = rigid_inverse(x)
        dual_chain = dual_chain @ d
        exact_chain = exact_chain * x
    # the tool's zero position and orientation relative to the last axis of the chain
    g = lambda name: err.get(name, _0)  # noqa: E731 - unselected errors are zero
    for f in (
        Translate((_0, _0, _0), (g("EX0T"), g("EY0T"), g("EZ0T"))),
        SmallRotate((g("EA0T"), g("EB0T"), g("EC0T"))),
    ):
        dual_chain = dual_chain @ as_dual(f)
        exact_chain = exact_chain * as_exact(f)
    tool = sp.Matrix([*t, 1])
    p0 = dual_chain.real * tool
    p1 = dual_chain.dual * tool
    px = exact_chain * tool
    return ChainExpressions(q, t, e, tuple(p0[:3]), tuple(p1[:3]), tuple(px[:3]))
