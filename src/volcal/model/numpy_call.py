"""Evaluating a CasADi Function on numpy arrays without the DM conversions.

``Function.call`` returns DM matrices, and ``DM.full()`` builds a Python list of every
element before numpy sees it: for the outputs of a function mapped over thousands of
points that costs several times the evaluation.  :class:`NumpyCall` binds numpy arrays to
the function's raw input and output buffers instead (the same numbers, bit for bit).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

__all__ = ["NumpyCall"]


class NumpyCall:
    """Evaluate a CasADi Function on numpy arrays through its raw buffers, returning dense
    numpy outputs.  Converting the DM outputs of an ordinary call costs more than the
    evaluation for a large sparse Jacobian (DM.full() walks the nonzeros one by one); here
    the nonzeros land in a numpy array and are scattered once.  Not thread-safe: one
    object per thread."""

    def __init__(self, f: ca.Function, *, mapped_from: ca.Function | None = None):
        """``mapped_from``: the function f is ``mapped_from.map(n)`` of, whose output
        patterns, repeated side by side, are f's: read from it instead of from f's
        (CasADi hands a pattern over as Python lists, which for a Jacobian mapped over a
        few thousand points took longer than the map's evaluation)."""
        self.f = f
        # CasADi's stub of FunctionBuffer lists a size argument the binding does not take
        self._buf: Any
        self._buf, self._eval = f.buffer()
        self._nz = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        # per output: rows, columns, scatter rows and columns (None when dense), dense
        self._where: list[tuple[int, int, np.ndarray | None, np.ndarray | None, bool]] = []
        for i in range(f.n_out()):
            sp = f.sparsity_out(i)
            if sp.is_dense():  # reshaped, never scattered: no pattern needed
                self._where.append((sp.size1(), sp.size2(), None, None, True))
                continue
            base, reps = sp, 1
            if mapped_from is not None:
                base = mapped_from.sparsity_out(i)
                reps = sp.size2() // max(base.size2(), 1)
                # a map's output: the blocks of its calls side by side (compared in CasADi)
                if not sp.is_equal(ca.repmat(base, 1, reps)):
                    raise ValueError("mapped_from: f's outputs are not its outputs side by side")
            colind = np.asarray(base.colind(), int)
            rows = np.tile(np.asarray(base.row(), int), reps)
            cols = np.repeat(np.arange(base.size2()), np.diff(colind))
            cols = (cols[None, :] + base.size2() * np.arange(reps)[:, None]).ravel()
            self._where.append((sp.size1(), sp.size2(), rows, cols, False))
        for i, nz in enumerate(self._nz):
            self._buf.set_res(i, nz.data)

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        keep = [np.ascontiguousarray(np.asarray(a, float).ravel(order="F")) for a in args]
        for i, a in enumerate(keep):
            self._buf.set_arg(i, a.data)
        self._eval()
        out = []
        for nz, (m, n, rows, cols, dense) in zip(self._nz, self._where):
            if dense:
                out.append(nz.reshape(n, m).T.copy() if n > 1 else nz.copy())
            else:
                full = np.zeros((m, n))
                full[rows, cols] = nz
                out.append(full)
        return out
