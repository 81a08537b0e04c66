"""Run a compiled export from Python (ctypes): for tests, and for users who want its speed.

>>> from volcal.outputs.codegen import load
>>> solver = load("export_dir")                    # after `make` (or build_it=True)
>>> res = solver.identify_table("measurements.csv")
>>> res.converged, res.parameters().head()

The loader reads the export's ``manifest.json`` for the sizes and names, and calls the C
API of ``lib<name>.so`` exactly as a C program would (see the export's header).
"""

from __future__ import annotations

import ctypes
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from volcal.base.exceptions import InputError

_DP = ctypes.POINTER(ctypes.c_double)


def _ptr(a: np.ndarray | None):
    return None if a is None else a.ctypes.data_as(_DP)


def _arr(a, shape, name) -> np.ndarray:
    v = np.ascontiguousarray(np.asarray(a, dtype=float))
    try:
        return np.ascontiguousarray(np.broadcast_to(v, shape))
    except ValueError:
        raise InputError(f"{name}: expected shape {shape}, got {v.shape}") from None


class _Options(ctypes.Structure):
    _fields_ = [
        ("max_iter", ctypes.c_int),
        ("tol_kkt", ctypes.c_double),
        ("tol_step", ctypes.c_double),
        ("tol_constraint", ctypes.c_double),
        ("max_chi2", ctypes.c_double),
        ("max_station_rms", ctypes.c_double),
    ]


def _result_type(n_params: int, n_stations: int, n_readings: int):
    class _Result(ctypes.Structure):
        _fields_ = [
            ("converged", ctypes.c_int),
            ("status", ctypes.c_int),
            ("phase", ctypes.c_int),
            ("iterations", ctypes.c_int),
            ("kkt", ctypes.c_double),
            ("kkt_rel", ctypes.c_double),
            ("step", ctypes.c_double),
            ("constraint_violation", ctypes.c_double),
            ("cost", ctypes.c_double),
            ("chi2_per_dof", ctypes.c_double),
            ("dof", ctypes.c_int),
            ("theta", ctypes.c_double * n_params),
            ("stations", ctypes.c_double * (4 * n_stations)),
            ("frame", ctypes.c_double * 6),
            ("residual_mm", ctypes.c_double * n_readings),
            ("sigma_mm", ctypes.c_double * n_readings),
        ]

    return _Result


@dataclass
class CResult:
    """What the compiled solver returned (values in mm / rad, as the C API).

    converged: every convergence check passed (see the export's README); status, status_text:
    the C status code and its text (not converged: after the iteration limit, a failed line
    search or a NaN after a finite iterate, the values are those of the best iterate, with
    its own kkt, step and chi2_per_dof; NaN when nothing was computed, e.g. for bad input);
    phase, iterations; kkt: final KKT stationarity residual;
    kkt_rel: its relative form; step: final Gauss-Newton step (um / urad); constraint_violation;
    cost; chi2_per_dof; dof; theta (n_params,); stations (DataFrame station, x_mm, y_mm,
    z_mm, dead_length_mm); frame (6,); residual_mm, sigma_mm (N,); seconds: wall time of
    the C call.
    """

    converged: bool
    status: int
    status_text: str
    phase: int
    iterations: int
    kkt: float
    kkt_rel: float
    step: float
    constraint_violation: float
    cost: float
    chi2_per_dof: float
    dof: int
    theta: np.ndarray
    stations: pd.DataFrame
    frame: np.ndarray
    residual_mm: np.ndarray
    sigma_mm: np.ndarray
    seconds: float
    param_names: list[str] = field(repr=False, default_factory=list)
    param_units: list[str] = field(repr=False, default_factory=list)

    def parameters(self) -> pd.DataFrame:
        """name, value, unit (um / urad), as volcal's parameter tables."""
        f = np.array([1e3 if u == "mm" else 1e6 for u in self.param_units])
        return pd.DataFrame(
            {
                "name": self.param_names,
                "value": self.theta * f,
                "unit": ["um" if u == "mm" else "urad" for u in self.param_units],
            }
        )


class _Compiled:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        mf = self.path / "manifest.json"
        if not mf.is_file():
            raise InputError("not a volcal export (no manifest.json)", source=str(self.path))
        self.manifest = json.loads(mf.read_text())
        self.name = self.manifest["name"]
        lib = self.path / f"lib{self.name}.so"
        if not lib.is_file():
            raise InputError(
                f"lib{self.name}.so not built; run make in the export folder "
                "or export with build_it=True",
                source=str(self.path),
            )
        self.lib = ctypes.CDLL(str(lib.resolve()))
        sz = self.manifest["sizes"]
        self.n_axes, self.n_params = int(sz["n_axes"]), int(sz["n_theta"])
        self.n_errors = int(sz["n_errors"])
        self.param_names = list(self.manifest["parameters"]["names"])
        self.param_units = list(self.manifest["parameters"]["units"])
        self.error_names = list(self.manifest["errors"])
        self.axis_names = list(self.manifest["model"]["axes"])
        f = getattr(self.lib, f"{self.name}_volumetric")
        f.restype = ctypes.c_int
        f.argtypes = [_DP] * 7
        self._vol = f
        f = getattr(self.lib, f"{self.name}_error_values")
        f.restype = ctypes.c_int
        f.argtypes = [_DP] * 3
        self._ev = f

    def volumetric(self, q, tool=None, theta=None, *, jacobians: bool = False):
        """Volumetric error at poses q (M, n_axes; mm / deg) with tools (M, 3) or (3,) mm
        for parameters theta (mm / rad).  Returns (p, dp) in mm, shapes (M, 3), and with
        ``jacobians`` also dp_dtheta (M, 3, n_params) and dp_dq (M, 3, n_axes)."""
        q = np.atleast_2d(np.asarray(q, float))
        M = q.shape[0]
        q = _arr(q, (M, self.n_axes), "q")
        tool = _arr(np.zeros(3) if tool is None else tool, (M, 3), "tool")
        theta = _arr(theta, (self.n_params,), "theta")
        p, dp = np.zeros((M, 3)), np.zeros((M, 3))
        Jt = np.zeros((M, 3, self.n_params)) if jacobians else None
        Jq = np.zeros((M, 3, self.n_axes)) if jacobians else None
        for i in range(M):
            flag = self._vol(
                _ptr(q[i]),
                _ptr(tool[i]),
                _ptr(theta),
                _ptr(p[i]),
                _ptr(dp[i]),
                _ptr(Jt[i]) if Jt is not None else None,
                _ptr(Jq[i]) if Jq is not None else None,
            )
            if flag:
                raise RuntimeError("the C model function failed")
        return (p, dp, Jt, Jq) if jacobians else (p, dp)

    def error_values(self, q, theta) -> np.ndarray:
        """Error motions (M, n_errors), mm / rad, at poses q (M, n_axes; mm / deg)."""
        q = np.atleast_2d(np.asarray(q, float))
        q = _arr(q, (q.shape[0], self.n_axes), "q")
        theta = _arr(theta, (self.n_params,), "theta")
        e = np.zeros((q.shape[0], self.n_errors))
        for i in range(q.shape[0]):
            if self._ev(_ptr(q[i]), _ptr(theta), _ptr(e[i])):
                raise RuntimeError("the C model function failed")
        return e


class CompiledModel(_Compiled):
    """A compiled model export (volumetric error and error motions only)."""


class CompiledSolver(_Compiled):
    """A compiled solver export."""

    def __init__(self, path: str | Path):
        super().__init__(path)
        if self.manifest.get("kind") != "solver":
            raise InputError("this export holds a model only, not a solver", source=str(self.path))
        plan = self.manifest["plan"]
        self.n_readings, self.n_stations = int(plan["n_readings"]), int(plan["n_stations"])
        self.station_ids = list(plan["station_ids"])
        self.plan = pd.read_csv(self.path / "plan.csv", dtype={"station": str, "point": str})
        self._Result = _result_type(self.n_params, self.n_stations, self.n_readings)
        n = self.name
        self._identify = getattr(self.lib, f"{n}_identify")
        self._identify.restype = ctypes.c_int
        self._identify.argtypes = [_DP] * 6 + [
            ctypes.POINTER(_Options),
            ctypes.c_void_p,
            ctypes.POINTER(self._Result),
        ]
        self._defaults = getattr(self.lib, f"{n}_default_options")
        self._defaults.argtypes = [ctypes.POINTER(_Options)]
        self._defaults.restype = None
        self._status = getattr(self.lib, f"{n}_status_string")
        self._status.restype = ctypes.c_char_p
        self._status.argtypes = [ctypes.c_int]
        self._start = getattr(self.lib, f"{n}_start_stations")
        self._start.restype = ctypes.c_int
        self._start.argtypes = [_DP] * 5
        self._work_size = getattr(self.lib, f"{n}_work_size")
        self._work_size.restype = ctypes.c_size_t
        self._work_size.argtypes = []

    def default_options(self) -> dict:
        o = _Options()
        self._defaults(ctypes.byref(o))
        return {f[0]: getattr(o, f[0]) for f in _Options._fields_}

    def work_size(self) -> int:
        return int(self._work_size())

    def start_stations(self, q, tool, length) -> tuple[np.ndarray, np.ndarray]:
        """Start stations (K, 4) and their residual RMS (K,) as the C solver computes them."""
        N = self.n_readings
        q = _arr(q, (N, self.n_axes), "q")
        tool = _arr(np.zeros(3) if tool is None else tool, (N, 3), "tool")
        length = _arr(length, (N,), "length")
        S, rms = np.zeros((self.n_stations, 4)), np.zeros(self.n_stations)
        st = self._start(_ptr(q), _ptr(tool), _ptr(length), _ptr(S), _ptr(rms))
        if st:
            raise RuntimeError(f"start stations failed: {self._status(st).decode()}")
        return S, rms

    def identify(
        self, q, tool=None, length=None, sigma=None, *, stations0=None, theta0=None, **options
    ) -> CResult:
        """Run the C solver on arrays in plan order (see the export's header): q (N, n_axes)
        mm / deg, tool (N, 3) or (3,) mm, length (N,) mm, sigma (N,) mm or None (NaN:
        budget, inf: dropped), stations0 (K, 4) or None, theta0 (n_params,) or None;
        options override the exported defaults (max_iter, tol_kkt, tol_step,
        tol_constraint, max_chi2, max_station_rms)."""
        N, K = self.n_readings, self.n_stations
        q = _arr(q, (N, self.n_axes), "q")
        tool = _arr(np.zeros(3) if tool is None else tool, (N, 3), "tool")
        length = _arr(length, (N,), "length")
        sigma = None if sigma is None else _arr(sigma, (N,), "sigma")
        stations0 = None if stations0 is None else _arr(stations0, (K, 4), "stations0")
        theta0 = None if theta0 is None else _arr(theta0, (self.n_params,), "theta0")
        opt = _Options()
        self._defaults(ctypes.byref(opt))
        for k, v in options.items():
            names = [f[0] for f in _Options._fields_]
            if k not in names:
                raise InputError(f"unknown option {k!r}; options: {names}")
            setattr(opt, k, v)
        res = self._Result()
        t0 = time.perf_counter()
        self._identify(
            _ptr(q),
            _ptr(tool),
            _ptr(length),
            _ptr(sigma),
            _ptr(stations0),
            _ptr(theta0),
            ctypes.byref(opt),
            None,
            ctypes.byref(res),
        )
        dt = time.perf_counter() - t0
        st = np.ctypeslib.as_array(res.stations).reshape(K, 4).copy()
        return CResult(
            converged=bool(res.converged),
            status=int(res.status),
            status_text=self._status(res.status).decode(),
            phase=int(res.phase),
            iterations=int(res.iterations),
            kkt=res.kkt,
            kkt_rel=res.kkt_rel,
            step=res.step,
            constraint_violation=res.constraint_violation,
            cost=res.cost,
            chi2_per_dof=res.chi2_per_dof,
            dof=int(res.dof),
            theta=np.ctypeslib.as_array(res.theta).copy(),
            stations=pd.DataFrame(
                {
                    "station": self.station_ids,
                    "x_mm": st[:, 0],
                    "y_mm": st[:, 1],
                    "z_mm": st[:, 2],
                    "dead_length_mm": st[:, 3],
                }
            ),
            frame=np.ctypeslib.as_array(res.frame).copy(),
            residual_mm=np.ctypeslib.as_array(res.residual_mm).copy(),
            sigma_mm=np.ctypeslib.as_array(res.sigma_mm).copy(),
            seconds=dt,
            param_names=self.param_names,
            param_units=self.param_units,
        )

    def arrays_from_table(self, data) -> dict:
        """q, tool, length, sigma in plan order from a measurement table (CSV path or
        DataFrame in volcal's format), matched to the plan by (station, point)."""
        df = (
            data
            if isinstance(data, pd.DataFrame)
            else pd.read_csv(data, dtype={"station": str, "point": str}, skipinitialspace=True)
        )
        ren = {
            f"{a}_{'deg' if r else 'mm'}": a
            for a, r in zip(self.axis_names, self.manifest["model"]["rotary"])
        }
        ren.update(
            {
                "tool_x_mm": "tool_x",
                "tool_y_mm": "tool_y",
                "tool_z_mm": "tool_z",
                "length_mm": "length",
                "sigma_mm": "sigma",
            }
        )
        df = df.rename(columns={k: v for k, v in ren.items() if k in df.columns})
        key = pd.MultiIndex.from_arrays([df["station"].astype(str), df["point"].astype(str)])
        plan_key = pd.MultiIndex.from_arrays([self.plan["station"], self.plan["point"]])
        if len(df) != self.n_readings or not key.is_unique:
            raise InputError(
                f"expected {self.n_readings} readings with distinct (station, point), got {len(df)}"
            )
        pos = key.get_indexer(plan_key)
        if (pos < 0).any():
            i = int(np.flatnonzero(pos < 0)[0])
            raise InputError(f"reading {plan_key[i]} of the plan is missing from the data")
        d = df.iloc[pos]
        tool = np.column_stack(
            [
                d[c].to_numpy(float) if c in d else np.zeros(len(d))
                for c in ("tool_x", "tool_y", "tool_z")
            ]
        )
        return {
            "q": d[self.axis_names].to_numpy(float),
            "tool": tool,
            "length": d["length"].to_numpy(float),
            "sigma": d["sigma"].to_numpy(float) if "sigma" in d else None,
        }

    def identify_table(self, data, **kwargs) -> CResult:
        """:meth:`identify` on a measurement table (see :meth:`arrays_from_table`)."""
        a = self.arrays_from_table(data)
        return self.identify(a["q"], a["tool"], a["length"], a["sigma"], **kwargs)


def load(path: str | Path) -> CompiledSolver | CompiledModel:
    """The compiled export in ``path`` (a solver or a model export)."""
    man = (
        json.loads((Path(path) / "manifest.json").read_text())
        if (Path(path) / "manifest.json").is_file()
        else {}
    )
    return CompiledSolver(path) if man.get("kind") == "solver" else CompiledModel(path)
