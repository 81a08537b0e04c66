"""The error field of an identified model, evaluated fast enough to tabulate it.

:class:`ErrorField` wraps (machine, error model, theta) into CasADi functions with the
parameters built in as constants, mapped over many poses at once:

* :meth:`ErrorField.errors`: every error quantity (mm / rad) at internal poses q;
* :meth:`ErrorField.volumetric`: the first-order volumetric error dp (actual - nominal tool
  point, workpiece frame, mm), the quantity ``predict`` reports;
* :meth:`ErrorField.affine`: dp(q, t) = a(q) + B(q) t, exact for the first-order model (the
  error of the tool point is affine in the tool offset), so any number of tool offsets
  cost one evaluation;
* :meth:`ErrorField.volumetric_from_errors`: dp for given error values (a controller's
  interpolated tables);
* :meth:`ErrorField.axis_jacobian`: d p_nominal / d q, what an axis correction does to the
  tool point.

Units inside: mm and rad; positions in files and tables: mm and deg
(:meth:`AxisInfo.to_file`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from volcal.base.exceptions import InputError

__all__ = ["AxisInfo", "ErrorField", "as_field_input", "plan_tools"]

#: poses per mapped call (bounded memory, the map is built once per size)
_CHUNK = 20000


@dataclass(frozen=True)
class AxisInfo:
    """One axis of the model as the compensation sees it (internal units: mm / rad)."""

    name: str
    index: int  # position in the model's axis order
    rotary: bool
    full_turn: bool  # periodic: a full turn with periodic error motions (tables modulo 360)
    lo: float
    hi: float
    reference: float
    dir_index: int  # 0, 1, 2: x, y, z
    dir_sign: int
    branch: str
    center: tuple[float, float, float]

    @property
    def length(self) -> float:
        return self.hi - self.lo

    @property
    def unit(self) -> str:
        """File unit of the axis position."""
        return "deg" if self.rotary else "mm"

    def to_file(self, x):
        """Internal position(s) -> file units (mm / deg)."""
        return np.rad2deg(x) if self.rotary else np.asarray(x, float)

    def to_internal(self, x):
        return np.deg2rad(x) if self.rotary else np.asarray(x, float)

    def wrap(self, x: np.ndarray) -> np.ndarray:
        """Positions of a full-turn axis brought into [lo, lo + 2 pi) (modulo); others as
        given."""
        x = np.asarray(x, float)
        if not self.full_turn:
            return x
        return self.lo + np.mod(x - self.lo, 2 * np.pi)


def as_field_input(result: Any):
    """(machine, error_model, theta, source path or None, plan tool offsets or None) of an
    :class:`~volcal.analysis.identify.IdentificationResult`, a
    :class:`~volcal.outputs.results.LoadedResult`, a result folder (path), or any object with
    ``machine``, ``error_model`` and ``theta``."""
    from pathlib import Path

    src = None
    if isinstance(result, (str, Path)):
        from volcal.outputs.results import load_result

        src = Path(result)
        result = load_result(result)
    for attr in ("machine", "error_model", "theta"):
        if not hasattr(result, attr):
            raise InputError(
                f"expected an identification result (or its folder), got "
                f"{type(result).__name__} without '{attr}'"
            )
    theta = np.asarray(result.theta, float)
    if theta.shape != (result.error_model.n_params,) or not np.all(np.isfinite(theta)):
        raise InputError(
            "the result's parameters are inconsistent with its error model or not finite"
        )
    if src is None and getattr(result, "path", None) is not None:
        src = Path(result.path)
    return result.machine, result.error_model, theta, src, plan_tools(result, src)


def plan_tools(result: Any, folder=None) -> np.ndarray | None:
    """The distinct tool offsets (K, 3) mm of the readings an identification used (its
    residuals table, or residuals.csv of its folder); None when unknown."""
    from pathlib import Path

    import pandas as pd

    df = getattr(result, "residuals", None)
    if df is None and folder is not None:
        f = Path(folder) / "residuals.csv"
        if f.is_file():
            try:
                df = pd.read_csv(f, usecols=lambda c: c.startswith("tool_"))
            except (OSError, ValueError):
                df = None
    if df is None or len(df) == 0:
        return None
    cols = []
    for c in "xyz":
        name = next((n for n in (f"tool_{c}", f"tool_{c}_mm") if n in df.columns), None)
        cols.append(df[name].to_numpy(float) if name else np.zeros(len(df)))
    tools = np.unique(np.round(np.column_stack(cols), 9), axis=0)
    return tools if len(tools) else None


class ErrorField:
    """Fast evaluation of an identified model's errors (see the module docstring)."""

    def __init__(self, machine, error_model, theta: np.ndarray):
        self.machine = machine
        self.error_model = error_model
        self.spec = machine.spec
        self.theta = np.asarray(theta, float)
        self.errors_list = list(error_model.errors)
        if [s.name for s in self.errors_list] != machine.error_names:
            raise InputError("the error model does not belong to this machine")
        self.axes: list[AxisInfo] = []
        for k, a in enumerate(self.spec.axes):
            conv = np.deg2rad if a.is_rotary else float
            lo, hi = float(conv(a.travel[0])), float(conv(a.travel[1]))
            # periodic: a full turn whose error motions are periodic functions of the angle
            # (Fourier series, constants); its tables then span one turn from the lower end
            kinds = {
                f.kind
                for s, f in zip(error_model.errors, error_model.forms)
                if s.kind == "component" and s.axis == a.name
            }
            periodic = a.full_turn and kinds <= {"fourier", "constant"}
            if periodic:
                hi = lo + 2 * np.pi
            self.axes.append(
                AxisInfo(
                    a.name,
                    k,
                    a.is_rotary,
                    periodic,
                    lo,
                    hi,
                    float(conv(a.reference)),
                    a.dir_index,
                    a.dir_sign,
                    a.branch,
                    (float(a.center[0]), float(a.center[1]), float(a.center[2])),
                )
            )
        n, ne = len(self.axes), len(self.errors_list)
        q = ca.SX.sym("q", n)
        t = ca.SX.sym("t", 3)
        es = ca.SX.sym("e", ne)
        e = error_model.values_function()(q, ca.DM(self.theta))
        tp = machine["tool_point"]
        dp = tp(q, t, e)[1]
        B = ca.jacobian(dp, t)
        zero = ca.DM.zeros(3)
        a0 = ca.substitute(dp, t, zero)
        B0 = ca.substitute(B, t, zero)
        self._fn = {
            "e": ca.Function("e", [q], [e]),
            "ab": ca.Function("ab", [q], [a0, ca.reshape(B0, 9, 1)]),
            "dpe": ca.Function("dpe", [q, t, es], [tp(q, t, es)[1]]),
            "P": ca.Function("P", [q, t], [machine["nominal"](q, t)]),
            "M": ca.Function(
                "M", [q, t], [ca.reshape(ca.jacobian(machine["nominal"](q, t), q), 3 * n, 1)]
            ),
        }
        self._maps: dict[tuple[str, int], ca.Function] = {}

    # ---- helpers -----------------------------------------------------------------------
    @property
    def n_axes(self) -> int:
        return len(self.axes)

    def axis(self, name: str) -> AxisInfo:
        return next(a for a in self.axes if a.name == name)

    @property
    def reference(self) -> np.ndarray:
        return np.array([a.reference for a in self.axes])

    @property
    def lower(self) -> np.ndarray:
        return np.array([a.lo for a in self.axes])

    @property
    def upper(self) -> np.ndarray:
        return np.array([a.hi for a in self.axes])

    def _map(self, name: str, *args: np.ndarray) -> list[np.ndarray]:
        """Evaluate function ``name`` column-wise over the rows of the arguments."""
        n = len(args[0])
        outs: list[list[np.ndarray]] = []
        for i in range(0, n, _CHUNK):
            m = min(_CHUNK, n - i)
            key = (name, m)
            if key not in self._maps:
                self._maps[key] = self._fn[name].map(m)
            res = self._maps[key](*[np.ascontiguousarray(a[i : i + m].T) for a in args])
            res = res if isinstance(res, (list, tuple)) else [res]
            outs.append([np.asarray(r.full()).T for r in res])
        if not outs:
            return [
                np.zeros((0, self._fn[name].size1_out(k))) for k in range(self._fn[name].n_out())
            ]
        return [np.vstack([o[k] for o in outs]) for k in range(len(outs[0]))]

    @staticmethod
    def _tools(tools, n: int) -> np.ndarray:
        t = np.zeros(3) if tools is None else np.asarray(tools, float)
        return np.ascontiguousarray(np.broadcast_to(t, (n, 3)), dtype=float)

    # ---- evaluations -------------------------------------------------------------------
    def errors(self, q: np.ndarray) -> np.ndarray:
        """Every error quantity (N, n_errors), mm / rad, at internal poses q (N, n_axes)."""
        q = np.atleast_2d(np.asarray(q, float))
        return self._map("e", q)[0]

    def axis_errors(self, axis: str, x: np.ndarray) -> np.ndarray:
        """Every error quantity (N, n_errors) with axis ``axis`` at x (internal) and the
        others at their reference (the columns of that axis' errors depend on x only)."""
        x = np.asarray(x, float)
        q = np.tile(self.reference, (len(x), 1))
        q[:, self.axis(axis).index] = x
        return self.errors(q)

    def affine(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(a (N, 3), B (N, 3, 3)) mm with dp(q, t) = a + B t."""
        q = np.atleast_2d(np.asarray(q, float))
        a, b = self._map("ab", q)
        return a, b.reshape(len(q), 3, 3, order="F")

    def volumetric(self, q: np.ndarray, tools=None) -> np.ndarray:
        """First-order volumetric error (N, 3) mm at poses q with tool offsets (N, 3) or
        (3,) mm (default 0)."""
        a, B = self.affine(q)
        t = self._tools(tools, len(a))
        return a + np.einsum("nij,nj->ni", B, t)

    def volumetric_from_errors(self, q: np.ndarray, tools, e: np.ndarray) -> np.ndarray:
        """First-order volumetric error (N, 3) mm for error values e (N, n_errors)."""
        q = np.atleast_2d(np.asarray(q, float))
        return self._map(
            "dpe", q, self._tools(tools, len(q)), np.ascontiguousarray(e, dtype=float)
        )[0]

    def nominal(self, q: np.ndarray, tools=None) -> np.ndarray:
        """Nominal tool points (N, 3) mm in the workpiece frame at poses q."""
        q = np.atleast_2d(np.asarray(q, float))
        return self._map("P", q, self._tools(tools, len(q)))[0]

    def axis_jacobian(self, q: np.ndarray, tools=None) -> np.ndarray:
        """d p_nominal / d q (N, 3, n_axes): mm per mm (linear axes), mm per rad (rotary)."""
        q = np.atleast_2d(np.asarray(q, float))
        M = self._map("M", q, self._tools(tools, len(q)))[0]
        return M.reshape(len(q), 3, self.n_axes, order="F")

    def error_jacobian(self, q: np.ndarray, tools=None) -> np.ndarray:
        """d dp / d e (N, 3, n_errors): the first-order effect of each error quantity."""
        q = np.atleast_2d(np.asarray(q, float))
        t = self._tools(tools, len(q))
        out = np.empty((len(q), 3, len(self.errors_list)))
        for i in range(0, len(q), 2000):
            _, _, J = self.machine.evaluate(
                q[i : i + 2000], t[i : i + 2000], np.zeros(len(self.errors_list))
            )
            out[i : i + 2000] = J
        return out
