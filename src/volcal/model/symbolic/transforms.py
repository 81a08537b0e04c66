"""Elementary homogeneous transforms, each realised two ways from one description:
as a :class:`~volcal.model.symbolic.dual.Dual` (first order in the error symbols) and exactly.

A factor is one of
* ``Translate(nominal, error)``: translation by ``nominal + error`` (3-vectors);
* ``Rotate(axis, angle)``: exact rotation by a nominal angle about machine axis 0/1/2;
* ``SmallRotate(omega)``: rotation by an error vector omega (rad): ``I + [omega]x`` to
  first order, ``Rx(wx) Ry(wy) Rz(wz)`` exactly (they differ at second order only).
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from volcal.model.symbolic.dual import Dual

Vec = tuple[sp.Expr, sp.Expr, sp.Expr]
ZERO3: Vec = (sp.Integer(0), sp.Integer(0), sp.Integer(0))


def skew(w: Vec) -> sp.Matrix:
    return sp.Matrix([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def rot(axis: int, angle: sp.Expr) -> sp.Matrix:
    """Exact 3x3 rotation about machine axis 0 (x), 1 (y) or 2 (z), right-hand rule."""
    c, s = sp.cos(angle), sp.sin(angle)
    if axis == 0:
        return sp.Matrix([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return sp.Matrix([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return sp.Matrix([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def homogeneous(R: sp.Matrix | None = None, t: Vec | sp.Matrix | None = None) -> sp.Matrix:
    T = sp.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = sp.Matrix(t)
    return T


@dataclass(frozen=True)
class Translate:
    nominal: Vec
    error: Vec = ZERO3


@dataclass(frozen=True)
class Rotate:
    axis: int
    angle: sp.Expr


@dataclass(frozen=True)
class SmallRotate:
    omega: Vec
    inverse: bool = False  # the transpose of the rotation (exactly R^T, -[omega]x to first order)


Factor = Translate | Rotate | SmallRotate


def as_dual(f: Factor) -> Dual:
    if isinstance(f, Translate):
        d = sp.zeros(4)
        d[:3, 3] = sp.Matrix(f.error)
        return Dual(homogeneous(t=f.nominal), d)
    if isinstance(f, Rotate):
        return Dual(homogeneous(R=rot(f.axis, f.angle)), sp.zeros(4))
    d = sp.zeros(4)
    d[:3, :3] = -skew(f.omega) if f.inverse else skew(f.omega)
    return Dual(sp.eye(4), d)


def as_exact(f: Factor) -> sp.Matrix:
    if isinstance(f, Translate):
        return homogeneous(t=[a + b for a, b in zip(f.nominal, f.error)])
    if isinstance(f, Rotate):
        return homogeneous(R=rot(f.axis, f.angle))
    R = sp.eye(3)
    for k in range(3):
        if f.omega[k] != 0:
            R = R * rot(k, f.omega[k])
    return homogeneous(R=R.T if f.inverse else R)
