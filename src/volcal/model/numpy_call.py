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

    def __init__(self, f: ca.Function):
        self.f = f
        # CasADi's stub of FunctionBuffer lists a size argument the binding does not take
        self._buf: Any
        self._buf, self._eval = f.buffer()
        self._nz = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._where = []
        for i in range(f.n_out()):
            sp = f.sparsity_out(i)
            colind = np.asarray(sp.colind(), int)
            rows = np.asarray(sp.row(), int)
            cols = np.repeat(np.arange(sp.size2()), np.diff(colind))
            self._where.append((sp.size1(), sp.size2(), rows, cols, sp.is_dense()))
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
