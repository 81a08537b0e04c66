"""A machine: its topology plus compiled CasADi functions of the tool point.

Building runs the symbolic layer once and lowers it; the resulting functions are
serialised to an on-disk cache keyed on the topology's content hash and the versions of
volcal and CasADi, so that a second run loads them without touching SymPy.

Function signatures (all inputs column vectors; lengths mm, angles rad):

``tool_point(q[n_axes], t[3], e[n_errors]) -> (p[3], dp[3], J[3 x n_errors])``
    first-order model: actual tool point, volumetric error p - p_nominal, and dp/de.
``tool_point_exact(q, t, e) -> (p, dp, J)``
    the same with exact rotations (no truncation); used by the simulator.
``nominal(q, t) -> p0[3]``
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from volcal import __version__
from volcal.base.linalg import unique_rows
from volcal.model.numpy_call import NumpyCall
from volcal.model.spec import ErrorSymbol, MachineSpec, error_symbols, resolve_model

log = logging.getLogger(__name__)

_FUNCTIONS = ("tool_point", "tool_point_exact", "nominal")
#: the most points a machine function is mapped over: longer batches are evaluated in
#: slices of this many, a shorter rest on the map of the next power of two (padded).  A
#: map per batch length cost more to build (about 6 us a point with its numpy buffers)
#: than to evaluate (1 us a point), and an identification asks for several lengths
MAP_POINTS = 512


# Bumped whenever the symbolic chain changes what a built function computes, so that a
# cache entry of an older chain is never loaded (2: tool zero position and orientation).
CHAIN_SCHEMA = 2


def cache_dir() -> Path:
    """Folder of the build cache: ``$VOLCAL_CACHE_DIR`` or ``$XDG_CACHE_HOME/volcal``."""
    env = os.environ.get("VOLCAL_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "volcal"


def _build_functions(spec: MachineSpec) -> dict[str, ca.Function]:
    # SymPy is imported here only: a cached machine never loads it.
    from volcal.model.lowering import to_casadi
    from volcal.model.symbolic import build_chain

    ch = build_chain(spec)
    q = ca.SX.sym("q", len(ch.q))
    t = ca.SX.sym("t", 3)
    e = ca.SX.sym("e", len(ch.e))
    symmap = {s: q[k] for k, s in enumerate(ch.q)}
    symmap.update({s: t[k] for k, s in enumerate(ch.t)})
    symmap.update({s: e[k] for k, s in enumerate(ch.e)})
    p0 = ca.vertcat(*to_casadi(ch.nominal, symmap))
    d1 = ca.vertcat(*to_casadi(ch.first_order, symmap))
    px = ca.vertcat(*to_casadi(ch.exact, symmap))
    opts = {"cse": True}
    names_in = ["q", "t", "e"]
    names_out = ["p", "dp", "J"]
    return {
        "tool_point": ca.Function(
            "tool_point", [q, t, e], [p0 + d1, d1, ca.jacobian(d1, e)], names_in, names_out, opts
        ),
        "tool_point_exact": ca.Function(
            "tool_point_exact",
            [q, t, e],
            [px, px - p0, ca.jacobian(px, e)],
            names_in,
            names_out,
            opts,
        ),
        "nominal": ca.Function("nominal", [q, t], [p0], ["q", "t"], ["p"], opts),
    }


@dataclass(repr=False)
class Machine:
    """A topology with its compiled tool-point functions (see the module docstring)."""

    spec: MachineSpec
    functions: dict[str, ca.Function] = field(repr=False)
    errors: list[ErrorSymbol] = field(repr=False)
    build_seconds: float = 0.0
    from_cache: bool = False

    def __repr__(self) -> str:
        return (
            f"Machine({self.spec.name!r}: {' '.join(self.spec.axis_names)}, "
            f"{len(self.errors)} error quantities)"
        )

    def _repr_html_(self) -> str:
        return self.spec._repr_html_() + f"<p>{len(self.errors)} error quantities</p>"

    @classmethod
    def from_model(cls, model: str | Path | MachineSpec, *, use_cache: bool = True) -> Machine:
        """Build (or load from the cache) the machine of a bundled name, file or spec."""
        spec = resolve_model(model)
        t0 = time.perf_counter()
        # the name only makes the entry readable; the content hash is the key
        safe = "".join(c if c.isalnum() or c in "_-" else "_" for c in spec.name)[:40]
        key = (
            f"{safe}-{spec.fingerprint()}-v{__version__}-s{CHAIN_SCHEMA}"
            f"-ca{ca.CasadiMeta.version()}"
        )
        path = cache_dir() / f"{key}.casadi"
        funcs = None
        if use_cache and path.exists():
            try:
                funcs = _load(path)
            except Exception as exc:  # a corrupt cache entry is rebuilt, never trusted
                log.warning("ignoring unreadable cache entry %s: %s", path, exc)
        from_cache = funcs is not None
        if funcs is None:
            funcs = _build_functions(spec)
            if use_cache:
                try:
                    _save(path, funcs)
                except OSError as exc:  # a read-only or full cache costs speed, not the run
                    log.warning(
                        "could not write the model cache entry %s: %s", path, exc.strerror or exc
                    )
        return cls(spec, funcs, error_symbols(spec), time.perf_counter() - t0, from_cache)

    # ---- convenience -------------------------------------------------------------------
    @property
    def axis_names(self) -> list[str]:
        return self.spec.axis_names

    @property
    def error_names(self) -> list[str]:
        return [s.name for s in self.errors]

    @property
    def n_axes(self) -> int:
        return len(self.spec.axes)

    @property
    def n_errors(self) -> int:
        return len(self.errors)

    def __getitem__(self, name: str) -> ca.Function:
        return self.functions[name]

    def _call(self, name: str, n: int) -> NumpyCall:
        """Function ``name`` mapped over n points, called through numpy buffers (see
        :mod:`volcal.model.numpy_call`); the last few kept, per thread."""
        import threading

        calls = self.__dict__.setdefault("_calls", {})
        key = (name, n, threading.get_ident())
        call = calls.pop(key, None)
        if call is None:
            f = self.functions[name]
            call = NumpyCall(f.map(n), mapped_from=f)
        calls[key] = call  # most recent last
        while len(calls) > 8:
            calls.pop(next(iter(calls)))
        return call

    def _mapped(self, name: str, *args: np.ndarray) -> list[np.ndarray]:
        """Function ``name`` at n points, args (rows, n) each: every output (rows_i, n,
        cols_i), point by point the function's own (rows_i, cols_i), evaluated on maps of
        at most :data:`MAP_POINTS` points (each point on its own: the numbers do not
        depend on the slicing)."""
        n = args[0].shape[1]
        f = self.functions[name]
        shapes = [(f.size1_out(i), f.size2_out(i)) for i in range(f.n_out())]
        outs = [np.empty((r, n, c)) for r, c in shapes]  # filled slice by slice
        for a in range(0, n, MAP_POINTS):
            m = min(MAP_POINTS, n - a)
            size = MAP_POINTS if m == MAP_POINTS else 1 << max(m - 1, 0).bit_length()
            sl = [x[:, a : a + m] for x in args]
            if size > m:  # a padded slice: copies of its last point, dropped after
                sl = [np.concatenate([x, np.repeat(x[:, -1:], size - m, axis=1)], 1) for x in sl]
            for o, v, (r, c) in zip(outs, self._call(name, size)(*sl), shapes):
                o[:, a : a + m] = np.reshape(v, (r, size, c))[:, :m]
        return outs

    def __getstate__(self):
        d = dict(self.__dict__)
        d.pop("_calls", None)  # buffers bound to this process
        return d

    def axis_to_internal(self, q: np.ndarray) -> np.ndarray:
        """File units (mm, deg) -> internal units (mm, rad), along the last dimension."""
        q = np.array(q, dtype=float, copy=True)
        for k, a in enumerate(self.spec.axes):
            if a.is_rotary:
                q[..., k] = np.deg2rad(q[..., k])
        return q

    def nominal_points(self, q: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Nominal tool points (N, 3) mm at axis positions q (N, n_axes; mm, rad) with tool
        offsets t (N, 3) or (3,) mm.  The chain is evaluated once per distinct pose (a
        measurement repeats each pose once per station) and without the error Jacobian
        that :meth:`evaluate` returns, which at 3 x 10^4 readings is 20 MB per call."""
        q = np.atleast_2d(np.asarray(q, float))
        n = q.shape[0]
        t = np.broadcast_to(np.asarray(t, float), (n, 3))
        uniq, inv = unique_rows(np.hstack([q, t]))
        (p,) = self._mapped("nominal", uniq[:, : self.n_axes].T, uniq[:, self.n_axes :].T)
        return p[:, :, 0].T[inv]

    def evaluate(self, q: np.ndarray, t: np.ndarray, e: np.ndarray, *, exact: bool = False):
        """Batch evaluation. q: (N, n_axes) internal units; t: (N, 3) or (3,); e: (N, n_err)
        or (n_err,). Returns (p, dp, J) as arrays (N, 3), (N, 3), (N, 3, n_err)."""
        q = np.atleast_2d(np.asarray(q, float))
        n = q.shape[0]
        t = np.broadcast_to(np.asarray(t, float), (n, 3))
        e = np.broadcast_to(np.asarray(e, float), (n, self.n_errors))
        name = "tool_point_exact" if exact else "tool_point"
        p, dp, J = self._mapped(name, q.T, t.T, e.T)
        J = J.transpose(1, 0, 2) if self.n_errors else np.zeros((n, 3, 0))
        return p[:, :, 0].T, dp[:, :, 0].T, J


def _save(path: Path, funcs: dict[str, ca.Function]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ser = ca.StringSerializer()
    for name in _FUNCTIONS:
        ser.pack(funcs[name])
    # write-then-rename: a concurrent reader never sees a half-written entry
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(ser.encode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _load(path: Path) -> dict[str, ca.Function]:
    de = ca.StringDeserializer(path.read_text())
    return {name: de.unpack() for name in _FUNCTIONS}
