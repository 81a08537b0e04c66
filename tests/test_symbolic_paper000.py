"""The bundled model ``mcv754_wxyzt`` reproduces paper 000's first-order model, term by term.

Paper 000 (Holub et al., Machines 2022, 10, 833), section 2: the chain W-X-Y-Z-T

    X_a = L_x + T_x (L_y + T_y (L_z + T_z X_p))                                   (1)

with T_j = I + iota [eps_j]x and iota^2 = 0, written out as eqs. (2)-(4).  The text
extraction lost every minus sign (plus signs survived), so the signs below are restored:
wherever two symbols stand side by side without an operator, or a parenthesis opens on a
symbol that must be negative, a minus was lost.  Two independent checks:

* ``test_eq1_expands_to_eqs_2_to_4``: eq. (1) built from the paper's matrices and vectors,
  truncated at iota^2 = 0, equals eqs. (2)-(4) as transcribed (guards the transcription);
* ``test_volcal_first_order_equals_eqs_2_to_4``: volcal's dual-number chain of the bundled
  model equals eqs. (2)-(4) with the symbol map of docs/conventions.md.
"""
from __future__ import annotations

import dataclasses

import sympy as sp

from volcal.model.spec import error_symbols, resolve_model
from volcal.model.symbolic import build_chain

x, y, z = sp.symbols("q_X q_Y q_Z", real=True)
xp, yp, zp = sp.symbols("t_x t_y t_z", real=True)
E = {name: sp.Symbol(name, real=True) for name in (
    "EXX EYX EZX EAX EBX ECX EXY EYY EZY EAY EBY ECY EXZ EYZ EZZ EAZ EBZ ECZ "
    "EC0Y EB0Z EA0Z").split()}

# paper 000 symbol -> volcal symbol (docs/conventions.md)
AX = {"x": "X", "y": "Y", "z": "Z"}
ROT = {"x": "A", "y": "B", "z": "C"}


def delta(i: str, j: str) -> sp.Symbol:
    """delta_ij: translational error of axis j in direction i -> E{I}{J}."""
    return E[f"E{AX[i]}{AX[j]}"]


def eps(i: str, j: str) -> sp.Symbol:
    """epsilon_ij: rotation of axis j about direction i -> E{A|B|C}{J}."""
    return E[f"E{ROT[i]}{AX[j]}"]


S_xy = E["EC0Y"]
S_xz = -E["EB0Z"]
S_yz = E["EA0Z"]


def paper_eqs_2_to_4() -> list[sp.Expr]:
    """Eqs. (2)-(4) of paper 000 with the lost minus signs restored."""
    dx = (delta("x", "x") + delta("x", "y") + delta("x", "z")
          - y * (eps("z", "x") + S_xy)
          + z * (-S_xz + eps("y", "x") + eps("y", "y"))
          - yp * (eps("z", "x") + eps("z", "y") + eps("z", "z"))
          + zp * (eps("y", "x") + eps("y", "y") + eps("y", "z")))
    dy = (delta("y", "x") + delta("y", "y") + delta("y", "z")
          - z * (S_yz + eps("x", "x") + eps("x", "y"))
          + xp * (eps("z", "x") + eps("z", "y") + eps("z", "z"))
          - zp * (eps("x", "x") + eps("x", "y") + eps("x", "z")))
    dz = (delta("z", "x") + delta("z", "y") + delta("z", "z")
          + y * eps("x", "x")
          - xp * (eps("y", "x") + eps("y", "y") + eps("y", "z"))
          + yp * (eps("x", "x") + eps("x", "y") + eps("x", "z")))
    return [dx, dy, dz]


def test_eq1_expands_to_eqs_2_to_4():
    """Eq. (1) with the paper's T and L (iota^2 = 0) gives eqs. (2)-(4) as transcribed."""
    io = sp.Symbol("iota")

    def T(j):
        ex, ey, ez = (eps(i, j) * io for i in "xyz")
        return sp.Matrix([[1, -ez, ey], [ez, 1, -ex], [-ey, ex, 1]])

    L_x = sp.Matrix([x + delta("x", "x") * io, delta("y", "x") * io, delta("z", "x") * io])
    L_y = sp.Matrix([delta("x", "y") * io - S_xy * y * io, y + delta("y", "y") * io,
                     delta("z", "y") * io])
    L_z = sp.Matrix([delta("x", "z") * io - S_xz * z * io, delta("y", "z") * io - S_yz * z * io,
                     z + delta("z", "z") * io])
    Xp = sp.Matrix([xp, yp, zp])
    Xa = L_x + T("x") * (L_y + T("y") * (L_z + T("z") * Xp))
    nominal = sp.Matrix([x + xp, y + yp, z + zp])
    for k, expected in enumerate(paper_eqs_2_to_4()):
        full = sp.expand(Xa[k])
        assert sp.expand(full.coeff(io, 0) - nominal[k]) == 0
        assert sp.expand(full.coeff(io, 1) - expected) == 0


def test_volcal_first_order_equals_eqs_2_to_4():
    # paper 000 has no tool zero position or orientation errors
    spec = dataclasses.replace(resolve_model("mcv754_wxyzt"), tool_errors="none")
    ch = build_chain(spec)
    assert ch.q == (x, y, z)
    assert ch.t == (xp, yp, zp)
    # the model has exactly the paper's 18 component errors and 3 squareness errors
    assert {s.name for s in error_symbols(spec)} == set(E)
    assert set(ch.e) == set(E.values())
    for k, expected in enumerate(paper_eqs_2_to_4()):
        assert sp.expand(ch.first_order[k] - expected) == 0, "xyz"[k]
    assert [sp.expand(c) for c in ch.nominal] == [x + xp, y + yp, z + zp]


def test_a_sign_change_is_detected():
    """The comparison is sharp: flipping the sign of one squareness term breaks it."""
    ch = build_chain(resolve_model("mcv754_wxyzt"))
    dx = paper_eqs_2_to_4()[0]
    wrong = dx.subs(E["EB0Z"], -E["EB0Z"])
    assert sp.expand(ch.first_order[0] - wrong) != 0
