"""A scalar CasADi Function evaluated by numpy on arrays of many evaluations at once, with
its reverse-mode derivative.

CasADi's own evaluation of an SX Function mapped over hundreds of thousands of readings
runs its virtual machine once per reading (here about 1.4 us per tracker reading with its
gradients, a just-in-time compiled map still several times numpy's time on the same
arithmetic).  :class:`NumpyTape` reads the Function's instruction list once (its
*algorithm*: each operation and the values it reads) and replays it with numpy arrays,
each instruction one array operation over all evaluations at once.  The numbers are the
Function's own (the same operations in the same order, IEEE arithmetic).

Broadcasting keeps the instructions that depend only on inputs shared by many evaluations
(a station's position, the frame of a trial: shape ``(B,)`` against the readings'
``(n, B)``) at the small size; :meth:`NumpyTape.vjp` runs the tape backwards (reverse
mode) and sums each adjoint to the shape of its value where it meets such a shared value:
the gradient with respect to a station's parameters is summed over its readings once, at
the few values the station enters through, instead of per reading.

The tape is plain Python and numpy: it pickles, and a worker process replaying it never
imports CasADi.  Work arrays are kept between calls (per thread): fresh megabyte-sized
temporaries cost more than the arithmetic on them.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["NumpyTape"]

_UNARY = {
    "OP_NEG": np.negative,
    "OP_SQRT": np.sqrt,
    "OP_SQ": np.square,
    "OP_EXP": np.exp,
    "OP_LOG": np.log,
    "OP_SIN": np.sin,
    "OP_COS": np.cos,
    "OP_TAN": np.tan,
    "OP_ASIN": np.arcsin,
    "OP_ACOS": np.arccos,
    "OP_ATAN": np.arctan,
    "OP_FABS": np.fabs,
    "OP_SIGN": np.sign,
    "OP_NOT": np.logical_not,
}
_BINARY = {
    "OP_ADD": np.add,
    "OP_SUB": np.subtract,
    "OP_MUL": np.multiply,
    "OP_DIV": np.divide,
    "OP_POW": np.power,
    "OP_CONSTPOW": np.power,
    "OP_ATAN2": np.arctan2,
    "OP_FMIN": np.fmin,
    "OP_FMAX": np.fmax,
    "OP_LT": np.less,
    "OP_LE": np.less_equal,
    "OP_EQ": np.equal,
    "OP_NE": np.not_equal,
    "OP_AND": np.logical_and,
    "OP_OR": np.logical_or,
}
# written out in the replay: constants, inputs, outputs, copies and three more
_OTHER = ("OP_CONST", "OP_INPUT", "OP_OUTPUT", "OP_ASSIGN", "OP_TWICE", "OP_INV", "OP_IF_ELSE_ZERO")
# operations whose derivative is zero wherever it exists
_FLAT = ("OP_SIGN", "OP_NOT", "OP_LT", "OP_LE", "OP_EQ", "OP_NE", "OP_AND", "OP_OR")


class NumpyTape:
    """Replay a scalar (SX) CasADi Function's instructions with numpy arrays.

    Inputs are given per nonzero: ``inputs[i][k]`` is nonzero k of input i for all
    evaluations at once, an array (or float) whose shape broadcasts with the others (e.g.
    readings x trials ``(n, B)`` against trials ``(B,)``).  :meth:`__call__` returns the
    outputs, one list per output with one array (a float where it is constant) per nonzero;
    :meth:`vjp` also the adjoints of the inputs for a seed on one output.  Arrays returned
    live in work arrays the next call of the same thread reuses: use them before calling
    again."""

    def __init__(self, f: Any):
        import casadi as ca

        if not f.is_a("SXFunction"):
            raise TypeError(f"{f.name()}: a NumpyTape replays SX Functions (got {f.class_name()})")
        names = {getattr(ca, n): n for n in dir(ca) if n.startswith("OP_")}
        # single assignment: the value of instruction k is value k (CasADi's instructions
        # reuse work slots; the reverse sweep needs every value)
        last: dict[int, int] = {}
        code: list[tuple[str, tuple[int, ...], tuple[int, ...], float]] = []
        for k in range(f.n_instructions()):
            op = names.get(f.instruction_id(k), str(f.instruction_id(k)))
            if op not in _UNARY and op not in _BINARY and op not in _OTHER:
                raise NotImplementedError(f"{f.name()}: numpy does not replay operation {op}")
            a, r = tuple(f.instruction_input(k)), tuple(f.instruction_output(k))
            const = float(f.instruction_constant(k)) if op == "OP_CONST" else 0.0
            if op == "OP_INPUT":
                code.append((op, a, (), const))  # (input, nonzero)
            elif op == "OP_OUTPUT":
                code.append((op, (last[a[0]],), r, const))  # value; (output, nonzero)
            else:
                code.append((op, tuple(last[s] for s in a), (), const))
            if op != "OP_OUTPUT":
                last[r[0]] = k
        self.name = str(f.name())
        self.code = code
        self.nnz_in = [int(f.nnz_in(i)) for i in range(f.n_in())]
        self.nnz_out = [int(f.nnz_out(i)) for i in range(f.n_out())]
        self._pools: dict[int, dict] = {}

    def __getstate__(self) -> dict:
        d = dict(self.__dict__)
        d["_pools"] = {}  # work arrays are not shipped
        return d

    # ---- forward --------------------------------------------------------------------------
    def __call__(self, *inputs: Any) -> list[list[Any]]:
        """The outputs for ``inputs`` (see the class docstring)."""
        _, out = self._forward(inputs)
        return out

    def _forward(self, inputs: Sequence[Any]) -> tuple[list[Any], list[list[Any]]]:
        if len(inputs) != len(self.nnz_in):
            raise ValueError(f"{self.name}: {len(self.nnz_in)} inputs expected, got {len(inputs)}")
        for i, (a, nnz) in enumerate(zip(inputs, self.nnz_in)):
            if len(a) != nnz:
                raise ValueError(f"{self.name}: input {i} has {len(a)} nonzeros, not {nnz}")
        pool = self._pool()
        v: list[Any] = [0.0] * len(self.code)
        out: list[list[Any]] = [[0.0] * n for n in self.nnz_out]
        for k, (op, a, r, c) in enumerate(self.code):
            if op == "OP_INPUT":
                v[k] = inputs[a[0]][a[1]]
            elif op == "OP_OUTPUT":
                out[r[0]][r[1]] = v[a[0]]
            elif op == "OP_CONST":
                v[k] = c
            elif op == "OP_ASSIGN":
                v[k] = v[a[0]]
            elif op == "OP_IF_ELSE_ZERO":
                v[k] = np.where(np.asarray(v[a[0]]) != 0, v[a[1]], 0.0)
            else:
                x = v[a[0]]
                y = v[a[1]] if len(a) > 1 else x
                fun: Any
                args: tuple[Any, ...]
                if op in _BINARY:
                    fun, args = _BINARY[op], (x, y)
                elif op == "OP_TWICE":
                    fun, args = np.add, (x, x)
                elif op == "OP_INV":
                    fun, args = np.divide, (1.0, x)
                else:
                    fun, args = _UNARY[op], (x,)
                v[k] = _apply(pool, ("f", k), fun, args)
        return v, out

    # ---- reverse ------------------------------------------------------------------------
    def vjp(
        self, inputs: Sequence[Any], seed: Any, output: int = 0
    ) -> tuple[list[list[Any]], list[list[Any]]]:
        """(outputs, adjoints): the outputs as :meth:`__call__` and, per input nonzero, the
        sum over evaluations of ``seed * d output[0] / d input`` reduced to the shape of
        that input nonzero (an input of shape ``(B,)`` shared by ``(n, B)`` evaluations
        gets their sum over n).  ``output`` must be a scalar (one nonzero); ``seed``
        broadcasts with it."""
        if self.nnz_out[output] != 1:
            raise ValueError(f"{self.name}: output {output} is not a scalar")
        v, out = self._forward(inputs)
        pool = self._pool()
        adj: list[Any] = [None] * len(self.code)
        owned = [False] * len(self.code)

        def add(k: int, x: Any) -> None:
            x = _sum_to(x, np.shape(v[k]))
            if adj[k] is None:
                adj[k] = x
            elif owned[k]:
                adj[k] += x
            else:
                buf = pool.get(("a", k))
                if buf is None or buf.shape != np.shape(v[k]) or np.ndim(buf) == 0:
                    adj[k] = np.add(adj[k], x)
                    if np.ndim(adj[k]):
                        pool[("a", k)] = adj[k]
                else:
                    adj[k] = np.add(adj[k], x, out=buf)
                owned[k] = np.ndim(adj[k]) > 0

        for op, a, r, _ in self.code:
            if op == "OP_OUTPUT" and r[0] == output:
                add(a[0], seed)
        grads: list[list[Any]] = [[0.0] * n for n in self.nnz_in]
        for k in range(len(self.code) - 1, -1, -1):
            op, a, r, _ = self.code[k]
            g = adj[k]
            if g is None or op in ("OP_OUTPUT", "OP_CONST") or op in _FLAT:
                continue
            if op == "OP_INPUT":
                grads[a[0]][a[1]] = g
                continue
            x: Any = v[a[0]]
            y: Any = v[a[1]] if len(a) > 1 else None

            def m(tag: str, fun, *args, _k: int = k):  # one operation, in a kept array
                return _apply(pool, ("r", _k, tag), fun, args)

            if op in ("OP_ASSIGN", "OP_ADD"):
                add(a[0], g)
                if op == "OP_ADD":
                    add(a[1], g)
            elif op == "OP_SUB":
                add(a[0], g)
                add(a[1], m("y", np.negative, g))
            elif op == "OP_NEG":
                add(a[0], m("x", np.negative, g))
            elif op == "OP_MUL":
                add(a[0], m("x", np.multiply, g, y))
                add(a[1], m("y", np.multiply, g, x))
            elif op == "OP_DIV":
                gx = m("x", np.divide, g, y)
                add(a[0], gx)
                add(a[1], m("y", np.negative, m("t", np.multiply, gx, v[k])))
            elif op == "OP_SQ":
                add(a[0], m("x", np.multiply, m("t", np.multiply, g, x), 2.0))
            elif op == "OP_TWICE":
                add(a[0], m("x", np.multiply, g, 2.0))
            elif op == "OP_SQRT":
                add(a[0], m("x", np.divide, g, m("t", np.multiply, v[k], 2.0)))
            elif op == "OP_INV":
                add(a[0], m("x", np.negative, m("t", np.multiply, g, np.square(v[k]))))
            elif op == "OP_EXP":
                add(a[0], m("x", np.multiply, g, v[k]))
            elif op == "OP_LOG":
                add(a[0], m("x", np.divide, g, x))
            elif op == "OP_SIN":
                add(a[0], m("x", np.multiply, g, np.cos(x)))
            elif op == "OP_COS":
                add(a[0], m("x", np.negative, m("t", np.multiply, g, np.sin(x))))
            elif op == "OP_TAN":
                add(a[0], m("x", np.multiply, g, 1.0 + np.square(v[k])))
            elif op in ("OP_ASIN", "OP_ACOS"):
                d = 1.0 / np.sqrt(1.0 - np.square(x))
                add(a[0], g * d if op == "OP_ASIN" else -g * d)
            elif op == "OP_ATAN":
                add(a[0], g / (1.0 + np.square(x)))
            elif op == "OP_ATAN2":  # atan2(x, y)
                d = np.square(x) + np.square(y)
                add(a[0], g * y / d)
                add(a[1], -g * x / d)
            elif op == "OP_FABS":
                add(a[0], g * np.sign(x))
            elif op in ("OP_POW", "OP_CONSTPOW"):
                add(a[0], g * y * np.power(x, y - 1.0))
                if op == "OP_POW":
                    add(a[1], g * v[k] * np.log(x))
            elif op in ("OP_FMIN", "OP_FMAX"):
                first = (x <= y) if op == "OP_FMIN" else (x >= y)
                add(a[0], np.where(first, g, 0.0))
                add(a[1], np.where(first, 0.0, g))
            elif op == "OP_IF_ELSE_ZERO":
                add(a[1], np.where(np.asarray(x) != 0, g, 0.0))
            else:  # pragma: no cover - every replayed operation has its rule above
                raise NotImplementedError(f"{self.name}: no derivative of {op}")
        return out, grads

    def _pool(self) -> dict:
        return self._pools.setdefault(threading.get_ident(), {})


def _apply(pool: dict, key: tuple, fun: Any, args: tuple) -> Any:
    """fun(*args) into the array kept under ``key`` (a new one when the shape changed);
    a float when every argument is one."""
    shapes = [x.shape if isinstance(x, np.ndarray) else np.shape(x) for x in args]
    shape = shapes[0] if all(t == shapes[0] for t in shapes) else np.broadcast_shapes(*shapes)
    if not shape:
        return float(fun(*args))
    buf = pool.get(key)
    if buf is None or buf.shape != shape:
        buf = pool[key] = np.empty(shape)
    return fun(*args, out=buf)


def _sum_to(x: Any, shape: tuple[int, ...]) -> Any:
    """``x`` summed over the axes that broadcasting added or stretched to reach ``shape``."""
    sx = np.shape(x)
    if sx == shape:
        return x
    lead = len(sx) - len(shape)
    if lead > 0:
        x = np.sum(x, axis=tuple(range(lead)))
        sx = np.shape(x)
    axes = tuple(i for i, (p, q) in enumerate(zip(sx[-len(shape) :], shape)) if q == 1 and p != 1)
    if axes and shape:
        x = np.sum(x, axis=tuple(len(sx) - len(shape) + i for i in axes), keepdims=True)
    if np.shape(x) != shape:
        x = np.broadcast_to(x, shape) if shape else float(x)
    return x
