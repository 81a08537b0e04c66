"""Dual matrices A0 + eps*A1 with eps^2 = 0: first-order truncation done algebraically.

Composing a chain this way keeps the error part linear in the error symbols at every step,
which is what makes building a 5-axis model take milliseconds instead of the minutes that
expanding and truncating (or differentiating) the exact product takes.
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp


@dataclass(frozen=True)
class Dual:
    """A dual matrix ``real + eps * dual`` (both SymPy matrices of the same shape)."""

    real: sp.Matrix
    dual: sp.Matrix

    def __matmul__(self, other: Dual) -> Dual:
        # (A0 + eps A1)(B0 + eps B1) = A0 B0 + eps (A0 B1 + A1 B0): the eps^2 term vanishes.
        return Dual(self.real * other.real, self.real * other.dual + self.dual * other.real)

    def rigid_inverse(self) -> Dual:
        """Inverse of a dual homogeneous transform whose real part is rigid.

        (A0 + eps A1)^-1 = A0^-1 - eps A0^-1 A1 A0^-1, with A0^-1 = [R^T, -R^T t].
        """
        inv0 = rigid_inverse(self.real)
        return Dual(inv0, -inv0 * self.dual * inv0)


def rigid_inverse(T: sp.Matrix) -> sp.Matrix:
    """Exact inverse of a 4x4 rigid homogeneous transform."""
    R = T[:3, :3]
    t = T[:3, 3]
    out = sp.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T * t
    return out
