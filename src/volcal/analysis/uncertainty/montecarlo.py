"""Monte Carlo uncertainty of an identification (GUM Supplement 1, JCGM 101:2008).

Plan -> sample -> aggregate:

1. *Kernel* (:class:`MCKernel`, built by :func:`build_kernel` from an identification):
   the structured re-solver of the identification problem
   (:class:`~volcal.analysis.uncertainty.engine.StructuredLSQ`), the input sampler
   (:class:`~volcal.analysis.uncertainty.sampling.InputSampler`) and the volumetric map at the
   evaluation poses.  Built once, given once to every worker.
2. *Sample* (:func:`run_trials`): trials are cut into fixed chunks (``chunk_size``, not
   tied to the number of workers); trial ``i`` draws its inputs from its own random stream
   (seed, i); every chunk re-solves the full nonlinear problem for its trials (or, in
   ``mode="linear"``, applies the linearised map: one factorisation, many right-hand
   sides) and returns parameters, stations and volumetric errors.  With an output folder
   every chunk is saved (``.npz``, written atomically) and an interrupted run resumes from
   the chunks present.  Local worker processes by default (one per further core; this
   process computes chunks too); a Dask scheduler address (or Client) runs the chunks on
   that cluster.  Same seed -> same numbers, whatever ran them.
3. *Aggregate* (:class:`MCResult`): GUM S1 estimate (mean of the trials), standard
   uncertainty (standard deviation), expanded uncertainty U = 2u, the probabilistically
   symmetric 95 % coverage interval, and the linearised standard uncertainty from the same
   input PDFs for comparison; :func:`contributions` repeats the run with one input source
   at a time (paper 002 Fig. 5).

Inputs are centred on the values the identification used (the measured readings, the
commanded axis positions, the given tool offsets): the trials' spread is the
uncertainty of the estimate, their mean the GUM S1 estimate.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from volcal.analysis.uncertainty.engine import StructuredLSQ, VolumetricMap, unpack_data
from volcal.analysis.uncertainty.sampling import InputSampler
from volcal.base.folders import stale_temporaries
from volcal.base.interrupts import raise_if_signalled
from volcal.base.progress import counter

log = logging.getLogger(__name__)

__all__ = [
    "Chunk",
    "MCKernel",
    "MCSamples",
    "MCResult",
    "build_kernel",
    "run_trials",
    "contributions",
    "ipopt_resolve",
    "verify_against_ipopt",
    "fixed_mask",
    "identification_data",
    "monte_carlo",
    "error_motion_rows",
    "quantity_table",
]

DEFAULT_CHUNK = 200


# --------------------------------------------------------------------------------------
# kernel


@dataclass(frozen=True)
class Chunk:
    """Trials ``start .. stop - 1`` of a run (mode ``nonlinear`` or ``linear``; enabled:
    the input sources on, None for all)."""

    index: int
    start: int
    stop: int
    seed: int
    mode: str = "nonlinear"
    enabled: tuple[str, ...] | None = None


@dataclass
class MCKernel:
    """What every worker needs (numpy only; picklable): the re-solver, the sampler, the
    volumetric map, the variable names and units."""

    engine: StructuredLSQ
    sampler: InputSampler
    volmap: VolumetricMap
    units: list[str]
    n_theta: int
    tol: float = 1e-9
    max_iter: int = 50
    _lin: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_lin"] = None
        return d

    @property
    def names(self) -> list[str]:
        return self.engine.names

    @property
    def source_names(self) -> list[str]:
        return self.sampler.names

    def linear(self) -> tuple[np.ndarray, np.ndarray]:
        if self._lin is None:
            self._lin = self.engine.linear_map()
        return self._lin

    def prepare(self, mode: str = "nonlinear") -> None:
        """Compute once what every chunk of ``mode`` uses (the linear map, or the arrays of
        the re-solver), with one BLAS thread as in the workers: local worker processes
        started by ``fork`` inherit it instead of each computing it again."""
        from volcal.base.threads import blas_threads

        with blas_threads(1):
            if mode == "linear":
                self.linear()
            else:
                self.engine.prepare()

    def run_chunk(self, chunk: Chunk) -> dict[str, np.ndarray]:
        trials = range(chunk.start, chunk.stop)
        dM, dX = self.sampler.draw(chunk.seed, trials, chunk.enabled)
        eng = self.engine
        B = dM.shape[0]
        if chunk.mode == "linear":
            Km, Kx = self.linear()
            X = eng.x_hat[None, :] + dM @ Km.T + dX @ Kx.T
            it = np.zeros(B, int)
            conv = np.ones(B, bool)
            step = np.zeros(B)
        elif chunk.mode == "nonlinear":
            X0 = np.tile(eng.x_hat, (B, 1))
            X0[:, eng.fixed] += dX
            sol = eng.solve(eng.m[None, :] + dM, X0, tol=self.tol, max_iter=self.max_iter)
            X, it, conv, step = sol.x, sol.iterations, sol.converged, sol.step
        else:
            raise ValueError(f"unknown mode {chunk.mode!r}")
        return {
            "x": X,
            "vol": self.volumetric(X),
            "iterations": it,
            "converged": conv,
            "step": step,
        }

    def volumetric(self, X: np.ndarray) -> np.ndarray:
        """The volumetric errors (B, M, 3; mm) of trials X (B, n)."""
        return self.volmap(np.ascontiguousarray(X[:, : self.n_theta]))

    def fingerprint(self) -> str:
        """Hash of everything that determines the trials' results."""
        h = hashlib.sha256()
        e, s = self.engine, self.sampler
        for a in (
            e.x_hat,
            e.m,
            e.w,
            e.fixed.astype(np.uint8),
            e.station_index,
            e.G,
            e.P0,
            s.axis_sens,
            s.length_mm,
            s.time_s,
            s.tool_sens,
            self.volmap.G,
        ):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(
            json.dumps(
                [
                    s.names,
                    repr(s.budget),
                    s.tool_sigma_mm,
                    s.station_sigma_mm,
                    self.tol,
                    self.max_iter,
                ]
            ).encode()
        )
        return h.hexdigest()

    def linear_covariance(self, enabled: Iterable[str] | None = None) -> np.ndarray:
        """Linearised covariance (n, n; physical units) of the estimate from the input
        sources (all, or those named), propagated through the same input PDFs' variances."""
        Km, Kx = self.linear()
        names = self.source_names if enabled is None else list(enabled)
        cov = np.zeros((Km.shape[0], Km.shape[0]))
        for nm in names:
            cov += self.sampler.propagate(Km, Kx, nm)
        return cov


def restore_datum(ider, result) -> None:
    """Put in force on ``ider``'s problem the datum conditions the identification imposed
    (``result.datum``); a result without that record keeps every candidate."""
    tab = getattr(result, "datum", None)
    if tab is not None and len(tab) == len(ider.problem.conditions):
        ider.problem.set_datum(np.asarray(tab["imposed"], bool))


def fixed_mask(ider, result) -> np.ndarray:
    """The variables an identification held (reconstructed from its result): the pivots of
    its null space, stations given as fixed, and for the two-step strategies all stations.
    The datum the identification imposed is put in force on ``ider`` as well: the held set
    and the datum belong together."""
    state = getattr(result, "state", None)
    if state is not None and state.matches(ider.problem):
        # the result carries what the identification held and imposed: nothing to guess
        ider.problem.set_datum(np.asarray(state.datum_active, bool))
        return np.asarray(state.fixed, bool).copy()
    restore_datum(ider, result)
    n = ider.problem.n_x
    fixed = np.zeros(n, bool)
    if result.identifiability is not None:
        fixed[list(result.identifiability.pivots)] = True
    fixed |= ider.station_fixed(np.asarray(result.stations["fixed"], bool))
    if result.strategy in ("two-phase", "points-only"):
        fixed[ider.is_station] = True
    return fixed


def identification_data(result, meas, budget=None) -> tuple[np.ndarray, np.ndarray]:
    """(x_hat, weights) of an identification: the solution vector (physical) and the
    weights it used (1/sigma, 0 for rejected readings).  sigma is recovered exactly from
    the saved residuals (residual / normalised residual); readings whose normalised
    residual is 0 fall back on the table or the budget."""
    from volcal.analysis.identify import reading_sigma

    state = getattr(result, "state", None)
    if state is not None and len(state.weights) == len(meas):
        return np.array(state.x, float), np.array(state.weights, float)
    res = result.residuals
    r_um = res["residual_um"].to_numpy(float)
    z = res["normalised_residual"].to_numpy(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = r_um * 1e-3 / z
    bad = ~np.isfinite(sigma) | (sigma <= 0)
    if bad.any():
        alt = np.asarray(meas.sigma, float).copy()
        miss = ~np.isfinite(alt)
        if miss.any():
            if budget is None:
                raise ValueError("cannot recover the weights of some readings without a budget")
            st = result.stations[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
            alt[miss] = reading_sigma(result.machine, budget, meas, st)[miss]
        sigma[bad] = alt[bad]
    w = 1.0 / sigma
    w[np.asarray(res["rejected"], bool)] = 0.0
    st = result.stations[["x_mm", "y_mm", "z_mm", "dead_length_mm"]].to_numpy(float)
    x = np.concatenate([result.theta, st.ravel(), np.asarray(result.frame, float)])
    return x, w


def build_kernel(
    ider,
    x_hat: np.ndarray,
    p: np.ndarray,
    fixed: np.ndarray,
    budget,
    *,
    time_s: np.ndarray | None = None,
    eval_q: np.ndarray | None = None,
    eval_tool: np.ndarray | None = None,
    tool_sigma_mm: float = 0.0,
    station_sigma_mm: float = 0.0,
    tol: float = 1e-9,
    check: bool = True,
) -> MCKernel:
    """The Monte Carlo kernel of an identification (Identifier ``ider``, solution x_hat,
    data vector p, held variables ``fixed``) with a budget.  eval_q (M, n_axes; mm, rad)
    and eval_tool (M, 3) are the poses whose volumetric errors are collected (default: a
    5-per-axis grid over the travel with tool offset (0, 0, 0) mm)."""
    from volcal.measurement.plans import grid_plan

    pr = ider.problem
    machine = pr.machine
    eng = StructuredLSQ.build(pr, x_hat, p, fixed, check=check)
    q, t, m, w = unpack_data(machine.n_axes, p)
    u, length = eng.beam()
    sampler = InputSampler.build(
        machine,
        q,
        t,
        pr.layout.station_index,
        u,
        length,
        budget,
        time_s=time_s,
        fixed=fixed,
        station_slice=pr.station_slice(),
        tool_sigma_mm=tool_sigma_mm,
        station_sigma_mm=station_sigma_mm,
    )
    if eval_q is None:
        eval_q = machine.axis_to_internal(grid_plan(machine.spec, 5).to_numpy(float))
    volmap = VolumetricMap.build(machine, pr.error_model, eval_q, eval_tool)
    return MCKernel(eng, sampler, volmap, list(pr.units), pr.n_theta, tol=tol)


# --------------------------------------------------------------------------------------
# running


@dataclass
class MCSamples:
    """The trials of a run: x (T, n) physical, vol (T, M, 3) mm, iterations (T,),
    converged (T,), step (T,); seed, mode, enabled sources, seconds."""

    x: np.ndarray
    vol: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    step: np.ndarray
    seed: int
    mode: str
    enabled: tuple[str, ...] | None
    seconds: float = 0.0
    resumed_chunks: int = 0

    @property
    def n(self) -> int:
        return int(self.x.shape[0])


def _plan_chunks(
    trials: int, chunk_size: int, seed: int, mode: str, enabled: tuple[str, ...] | None
) -> list[Chunk]:
    out = []
    for c, start in enumerate(range(0, trials, chunk_size)):
        out.append(Chunk(c, start, min(start + chunk_size, trials), seed, mode, enabled))
    return out


def _save_npz(path: Path, arrays: dict[str, np.ndarray], chunk: Chunk) -> None:
    """Save a chunk's trials atomically.  The volumetric errors are left out: they are
    the kernel's linear map of the parameters, recomputed on loading (four times less to
    write)."""
    from volcal.base.folders import uninterrupted

    keep = {k: v for k, v in arrays.items() if k != "vol"}
    # a signal (Ctrl-C, SIGTERM) waits until the chunk is whole or gone: an interrupt inside
    # numpy's zip writer can otherwise leave a temporary file or print a traceback
    with uninterrupted():
        # named with the process id: a rerun removes what a writer killed outright left
        fd, tmp = tempfile.mkstemp(
            dir=path.parent, prefix=f".chunk-{os.getpid()}-", suffix=".tmp.npz"
        )
        os.close(fd)
        try:
            # numpy's stub types **kwargs as allow_pickle; these are arrays
            np.savez(tmp, start=chunk.start, stop=chunk.stop, **keep)  # type: ignore[arg-type]
            os.replace(tmp, path)
        except BaseException:
            if os.path.exists(tmp):
                os.remove(tmp)
            raise


def _load_npz(path: Path, chunk: Chunk, kernel: MCKernel) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path) as z:
            if int(z["start"]) != chunk.start or int(z["stop"]) != chunk.stop:
                return None
            out = {k: z[k] for k in ("x", "iterations", "converged", "step")}
            # files of earlier versions carry the volumetric errors
            out["vol"] = z["vol"] if "vol" in z else kernel.volumetric(out["x"])
            return out
    except Exception:  # a damaged chunk file is recomputed, never trusted
        return None


def run_trials(
    kernel: MCKernel,
    trials: int,
    seed: int,
    *,
    mode: str = "nonlinear",
    enabled: Iterable[str] | None = None,
    chunk_size: int = DEFAULT_CHUNK,
    workers: int | None = None,
    scheduler: Any = None,
    out_dir: str | Path | None = None,
    progress: bool = False,
    label: str | None = None,
    on_start: Callable[[], None] | None = None,
) -> MCSamples:
    """Run ``trials`` Monte Carlo trials (see the module docstring).

    mode: ``nonlinear`` (the exact re-solve) or ``linear``; enabled: input sources on
    (None: all); chunk_size: trials per chunk (part of the run's definition: the same seed
    and chunk size give the same numbers whatever the workers); workers: local worker
    processes (None: every core, this process computing too; 1: this process only);
    scheduler: Dask scheduler address or Client; out_dir: folder for the chunk files
    (resumable); progress: a bar on a terminal, plain lines with the time left otherwise
    (:func:`volcal.base.progress.counter`); on_start: called once the trials are
    under way (see
    :func:`~volcal.analysis.uncertainty.parallel.run_chunks`).
    """
    if trials < 1:
        raise ValueError(f"expected at least one trial, got {trials}")
    if mode not in ("nonlinear", "linear"):
        raise ValueError(f"mode must be 'nonlinear' or 'linear', got {mode!r}")
    en = None if enabled is None else tuple(sorted(set(enabled)))
    if en is not None:
        kernel.sampler._mask(en)  # validates the names
    chunks = _plan_chunks(int(trials), int(chunk_size), int(seed), mode, en)
    t0 = time.perf_counter()
    done: set[int] = set()
    cat: dict[str, np.ndarray] = {}

    def put(c: Chunk, res: dict[str, np.ndarray]) -> None:
        # into the run's arrays as chunks arrive (no concatenation of every chunk at the
        # end, nor all of them held until then)
        if not cat:
            for k, v in res.items():
                cat[k] = np.empty((int(trials),) + v.shape[1:], v.dtype)
        for k, v in res.items():
            cat[k][c.start : c.stop] = v
        done.add(c.index)

    folder = None
    if out_dir is not None:
        key = hashlib.sha256(
            json.dumps([kernel.fingerprint(), int(seed), int(chunk_size), mode, en]).encode()
        ).hexdigest()[:16]
        name = (label or "all") + "-" + key
        folder = Path(out_dir) / "samples" / name
        folder.mkdir(parents=True, exist_ok=True)
        for stale in stale_temporaries(folder, ".chunk-"):  # of a run killed outright
            with contextlib.suppress(OSError):
                stale.unlink()
        meta = {
            "seed": int(seed),
            "chunk_size": int(chunk_size),
            "mode": mode,
            "enabled": list(en) if en else None,
            "key": key,
        }
        (folder / "run.json").write_text(json.dumps(meta, indent=2) + "\n")
        for c in chunks:
            f = folder / f"chunk{c.index:05d}.npz"
            if f.exists():
                got = _load_npz(f, c, kernel)
                if got is not None:
                    put(c, got)
    todo = [c for c in chunks if c.index not in done]
    resumed = len(done)
    if todo and scheduler is None:
        kernel.prepare(mode)  # once here, inherited by forked workers
    # a bar on a terminal, plain lines with the time left in logs (volcal.base.progress)
    with counter(
        int(trials),
        label or mode,
        "trial",
        initial=sum(c.stop - c.start for c in chunks if c.index in done),
        on=bool(progress),
    ) as bar:
        for c, res in _dispatch(kernel, todo, workers, scheduler, on_start):
            put(c, res)
            if folder is not None:
                _save_npz(folder / f"chunk{c.index:05d}.npz", res, c)
            bar.update(c.stop - c.start)
    return MCSamples(
        cat["x"],
        cat["vol"],
        cat["iterations"],
        cat["converged"],
        cat["step"],
        int(seed),
        mode,
        en,
        time.perf_counter() - t0,
        resumed,
    )


def _dispatch(kernel, chunks, workers, scheduler, on_start=None):
    from volcal.analysis.uncertainty.parallel import run_chunks

    return run_chunks(kernel, chunks, workers=workers, scheduler=scheduler, on_start=on_start)


# --------------------------------------------------------------------------------------
# aggregation


def _factor(unit: str) -> tuple[float, str]:
    return (1e3, "um") if unit == "mm" else (1e6, "urad")


def _interval(
    a: np.ndarray, p: float = 0.95, *, overwrite: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Probabilistically symmetric coverage interval (GUM S1 7.7) along axis 0
    (``overwrite``: partition ``a`` itself instead of a copy)."""
    lo, hi = np.quantile(a, [(1 - p) / 2, (1 + p) / 2], axis=0, overwrite_input=overwrite)
    return lo, hi


def _spread(
    a: np.ndarray, *, copy: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mean, u, lo, hi) of samples ``a`` (T, ...) along axis 0: mean, standard deviation
    (ddof 1) and 95 % interval, from one copy in the memory order of ``a`` (so the sums run
    as on ``a`` itself; ``copy=False``: ``a`` is a temporary, used itself).  The interval
    partitions the copy in place, after the moments (order statistics do not depend on
    the order)."""
    c = np.array(a, order="K") if copy else a
    mean = c.mean(axis=0)
    u = c.std(axis=0, ddof=1)
    lo, hi = _interval(c, overwrite=True)
    return mean, u, lo, hi


@dataclass
class MCResult:
    """Summaries of a run (GUM S1 section 7): see :meth:`parameters`, :meth:`volumetric`."""

    kernel: MCKernel
    samples: MCSamples
    cov_linear: np.ndarray
    eval_table: pd.DataFrame | None = None  # axis columns (file units) of the eval poses
    # the summaries below, computed once (the tables, the summary and the plots share them)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_samples(
        cls, kernel: MCKernel, samples: MCSamples, eval_table: pd.DataFrame | None = None
    ) -> MCResult:
        return cls(kernel, samples, kernel.linear_covariance(samples.enabled), eval_table)

    def _cached(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def norm_um(self) -> np.ndarray:
        """|d| (T, M) in um: the norm of the volumetric error of every trial at every
        evaluation pose (computed once; read-only).  ``sqrt(sum d_i^2)`` of the errors in
        um as ``numpy.linalg.norm`` computes it, a block of trials at a time (no
        temporaries the size of all the trials)."""

        def make() -> np.ndarray:
            vol = self.samples.vol
            out = np.empty(vol.shape[:2])
            step = 2048
            for a in range(0, vol.shape[0], step):
                b = vol[a : a + step] * 1e3
                np.sqrt(np.add.reduce(b * b, axis=2), out=out[a : a + step])
            out.flags.writeable = False
            return out

        return self._cached("norm_um", make)

    def norm_u_um(self) -> np.ndarray:
        """u(|d|) (M,) in um: the standard deviation of the norm of the volumetric error
        over the trials at every evaluation pose (computed once)."""
        return self._cached("norm_u_um", lambda: self.norm_um().std(axis=0, ddof=1))

    def estimate_um(self) -> np.ndarray:
        """The volumetric error (M, 3) in um at the identification's estimate."""
        k = self.kernel
        return k.volmap(k.engine.x_hat[: k.n_theta]) * 1e3

    def parameters(self, *, include_stations: bool = True) -> pd.DataFrame:
        """Per variable: name, unit (um / urad), value (the identification), mc_mean, u,
        U (k = 2), ci95_low, ci95_high (95 % coverage interval), u_linear, u_ratio
        (u / u_linear).  Held variables are left out."""
        return self._cached(
            ("parameters", include_stations), lambda: self._parameters(include_stations)
        ).copy()

    def _parameters(self, include_stations: bool) -> pd.DataFrame:
        k = self.kernel
        X = self.samples.x
        keep = ~k.engine.fixed
        if not include_stations:
            keep &= np.arange(k.engine.n) < k.n_theta
        idx = np.flatnonzero(keep)
        f = np.array([_factor(k.units[i])[0] for i in idx])
        mean, u, lo, hi = _spread(X[:, idx], copy=False)  # indexing made a copy
        u = u * f
        ul = np.sqrt(np.clip(np.diag(self.cov_linear)[idx], 0, None)) * f
        return pd.DataFrame(
            {
                "name": [k.names[i] for i in idx],
                "unit": [_factor(k.units[i])[1] for i in idx],
                "value": k.engine.x_hat[idx] * f,
                "mc_mean": mean * f,
                "u": u,
                "U": 2 * u,
                "ci95_low": lo * f,
                "ci95_high": hi * f,
                "u_linear": ul,
                "u_ratio": u / np.where(ul > 0, ul, np.nan),
            }
        )

    def volumetric(self) -> pd.DataFrame:
        """Per evaluation pose: the pose (file units, when known), tool offset, and for
        dx, dy, dz (um) and the norm |d| (um; paper 002 eq. 4): value (at the
        identification's estimate), u, U (k = 2), 95 % interval, and for the components
        u_linear."""
        return self._cached("volumetric", self._volumetric).copy()

    def _volumetric(self) -> pd.DataFrame:
        k = self.kernel
        vol = self.samples.vol  # (T, M, 3) mm
        est = self.estimate_um()  # (M, 3)
        G = k.volmap.G
        nt = k.n_theta
        cov_t = self.cov_linear[:nt, :nt]
        var_l = np.einsum("mip,pq,miq->mi", G, cov_t, G) * 1e6
        out = (
            self.eval_table.copy()
            if self.eval_table is not None
            else pd.DataFrame({f"q{j}": k.volmap.q[:, j] for j in range(k.volmap.q.shape[1])})
        )
        out = out.reset_index(drop=True)
        out[["tool_x", "tool_y", "tool_z"]] = k.volmap.tool
        work = np.empty(vol.shape[:2])  # one component (or |d|) of every trial, um
        for j, c in enumerate(("dx", "dy", "dz")):
            _, u, lo, hi = _spread(np.multiply(vol[:, :, j], 1e3, out=work), copy=False)
            out[f"{c}_um"] = est[:, j]
            out[f"u_{c}_um"] = u
            out[f"U_{c}_um"] = 2 * u
            out[f"{c}_ci95_low_um"] = lo
            out[f"{c}_ci95_high_um"] = hi
            out[f"u_{c}_linear_um"] = np.sqrt(np.clip(var_l[:, j], 0, None))
        np.copyto(work, self.norm_um())
        lo, hi = _interval(work, overwrite=True)
        out["norm_um"] = np.linalg.norm(est, axis=1)
        out["u_norm_um"] = self.norm_u_um()
        out["U_norm_um"] = 2 * out["u_norm_um"]
        out["norm_ci95_low_um"] = lo
        out["norm_ci95_high_um"] = hi
        return out

    def max_volumetric(self) -> dict[str, float]:
        """The largest volumetric error over the evaluation poses: at the estimate, and the
        MC distribution of the per-trial maximum (u, U, interval); plus the uncertainty
        of |d| at the pose of the maximum and the largest U of |d| over the poses (um)."""
        vol = self.volumetric()
        i = int(np.argmax(vol["norm_um"].to_numpy()))
        mx = self.norm_um().max(axis=1)
        lo, hi = _interval(mx)
        return {
            "max_norm_um": float(vol["norm_um"].iloc[i]),
            "pose_index": i,
            "U_norm_at_max_um": float(vol["U_norm_um"].iloc[i]),
            "U_max_trial_um": float(2 * mx.std(ddof=1)),
            "max_ci95_low_um": float(lo),
            "max_ci95_high_um": float(hi),
            "U_norm_largest_um": float(vol["U_norm_um"].max()),
            "U_component_largest_um": float(
                max(vol[f"U_{c}_um"].max() for c in ("dx", "dy", "dz"))
            ),
        }

    def agreement(self) -> dict[str, float]:
        """Largest relative difference of the MC and linearised standard uncertainties
        over the parameters (and stations) and over the volumetric components."""
        par = self.parameters()
        vol = self.volumetric()
        ul = np.concatenate([vol[f"u_{c}_linear_um"] for c in ("dx", "dy", "dz")])
        um = np.concatenate([vol[f"u_{c}_um"] for c in ("dx", "dy", "dz")])
        # poses where the datum fixes a component (u = 0 both ways) carry no comparison
        ok = ul > 1e-6 * max(ul.max(), 1e-300)
        rv = um[ok] / ul[ok]
        return {
            "parameters_max_rel_diff": float(np.nanmax(np.abs(par["u_ratio"] - 1))),
            "parameters_median_ratio": float(np.nanmedian(par["u_ratio"])),
            "volumetric_max_rel_diff": float(np.nanmax(np.abs(rv - 1))),
            "volumetric_median_ratio": float(np.nanmedian(rv)),
        }


def error_motion_rows(
    error_model, quantities: Iterable[str]
) -> tuple[list[str], np.ndarray, list[str]]:
    """Linear functionals of theta for named quantities: a parameter name (``EXX_1``,
    ``EC0Y``) or an error motion at an axis position in file units (``EXX(754)``,
    ``EBX(0)``; mm or deg).  Returns (names, rows (k, n_theta), units mm / rad)."""
    import re

    em = error_model
    pos = {n: i for i, n in enumerate(em.param_names)}
    err = {s.name: k for k, s in enumerate(em.errors)}
    rows, units, names = [], [], []
    for qn in quantities:
        qn = str(qn).strip()
        r = np.zeros(em.n_params)
        if qn in pos:
            r[pos[qn]] = 1.0
            units.append(em.param_units[pos[qn]])
        else:
            m_ = re.fullmatch(r"(E[A-Z0-9]+)\(\s*([-+0-9.eE]+)\s*\)", qn)
            if not m_ or m_.group(1) not in err:
                from volcal.base.exceptions import InputError

                raise InputError(
                    f"unknown quantity {qn!r}; expected a parameter name (e.g. "
                    f"{em.param_names[0]}) or an error motion at a position "
                    f"(e.g. {em.errors[0].name}(100))"
                )
            k = err[m_.group(1)]
            s_ = em.errors[k]
            a = em.spec.axis(s_.axis)
            q = np.zeros((1, len(em.spec.axes)))
            v = float(m_.group(2))
            q[0, em.spec.axis_names.index(a.name)] = np.deg2rad(v) if a.is_rotary else v
            r = em.basis(q, [k])[0, 0]
            units.append(s_.unit)
        rows.append(r)
        names.append(qn)
    return names, np.array(rows).reshape(len(names), em.n_params), units


def quantity_table(mc: MCResult, error_model, quantities: Iterable[str]) -> pd.DataFrame:
    """Summary of named quantities (see :func:`error_motion_rows`): name, unit (um /
    urad), value (at the identification), mc_mean, u, U (k = 2), 95 % interval, u_linear."""
    names, A, units = error_motion_rows(error_model, quantities)
    k = mc.kernel
    nt = k.n_theta
    S = mc.samples.x[:, :nt] @ A.T
    f = np.array([_factor(u)[0] for u in units])
    mean, u, lo, hi = _spread(S, copy=False)
    u = u * f
    ul = np.sqrt(np.clip(np.einsum("kp,pq,kq->k", A, mc.cov_linear[:nt, :nt], A), 0, None)) * f
    return pd.DataFrame(
        {
            "name": names,
            "unit": [_factor(x)[1] for x in units],
            "value": (A @ k.engine.x_hat[:nt]) * f,
            "mc_mean": mean * f,
            "u": u,
            "U": 2 * u,
            "ci95_low": lo * f,
            "ci95_high": hi * f,
            "u_linear": ul,
        }
    )


def contributions(
    kernel: MCKernel,
    trials: int,
    seed: int,
    *,
    sources: Iterable[str] | None = None,
    mode: str = "nonlinear",
    chunk_size: int = DEFAULT_CHUNK,
    workers: int | None = None,
    scheduler: Any = None,
    out_dir: str | Path | None = None,
    progress: bool = False,
) -> tuple[pd.DataFrame, dict[str, MCSamples]]:
    """One input source at a time (paper 002 Fig. 5): for each source a run of ``trials``
    trials with only that source on (the same draws as in the full run).  Returns a long
    table ``quantity, unit, source, u, u_linear`` over the parameters (with stations) and
    the norm of the volumetric error at every evaluation pose (``|d|@i``), and the samples
    per source."""
    names = list(kernel.source_names if sources is None else sources)
    rows = []
    runs = {}
    for nm in names:
        s = run_trials(
            kernel,
            trials,
            seed,
            mode=mode,
            enabled=[nm],
            chunk_size=chunk_size,
            workers=workers,
            scheduler=scheduler,
            out_dir=out_dir,
            progress=progress,
            label=f"only-{nm}",
        )
        runs[nm] = s
        res = MCResult.from_samples(kernel, s)
        par = res.parameters()
        for _, r in par.iterrows():
            rows.append(
                {
                    "quantity": r["name"],
                    "unit": r["unit"],
                    "source": nm,
                    "u": r["u"],
                    "u_linear": r["u_linear"],
                }
            )
        vol = res.volumetric()
        for i, u in enumerate(vol["u_norm_um"]):
            rows.append(
                {"quantity": f"|d|@{i}", "unit": "um", "source": nm, "u": u, "u_linear": np.nan}
            )
    return pd.DataFrame(rows), runs


# --------------------------------------------------------------------------------------
# IPOPT cross-check


def ipopt_resolve(
    ider,
    x_hat: np.ndarray,
    p: np.ndarray,
    fixed: np.ndarray,
    M: np.ndarray,
    *,
    tol: float = 1e-10,
    max_iter: int = 30,
    step_tol: float = 1e-9,
    round_iter: int = 3,
) -> tuple[np.ndarray, list[str]]:
    """Re-solve readings M (B, N) with IPOPT on the Identifier's own NLP (tight tolerance,
    no early "acceptable" stop), from x_hat (n,) or one start per trial (B, n) with the same
    held variables.  Returns (X (B, n) physical, statuses).  Slow (~0.02 s an iteration
    here); for verification.  The solver is built once for the batch, with the problem's
    own gradient function.

    The gradient of the whitened objective cannot fall below its rounding level, so
    ``tol`` is seldom met: IPOPT runs in rounds of ``round_iter`` iterations, each from
    where the last ended, until its last step is below ``step_tol`` (scaled units,
    1 = 1 um / 1 urad: the structured solver's own criterion) or ``max_iter`` iterations
    in all, instead of stepping at the rounding level until ``max_iter``."""
    import casadi as ca

    from volcal.solve.ipopt import NO_PARAMETER_MULTIPLIERS

    pr = ider.problem
    opts = {
        "ipopt.print_level": 0,
        "print_time": False,
        "ipopt.sb": "yes",
        "ipopt.tol": tol,
        "ipopt.acceptable_iter": 0,
        "ipopt.max_iter": min(round_iter, max_iter),
        "ipopt.nlp_scaling_method": "none",
        "hess_lag": pr.hess_lag,
        "grad_f": pr.grad_f,
        "error_on_fail": False,
        **NO_PARAMETER_MULTIPLIERS,
    }
    S = ca.nlpsol("verify", "ipopt", pr.nlp, opts)
    q, t, _, w = unpack_data(pr.machine.n_axes, p)
    M = np.atleast_2d(M)
    X0 = np.broadcast_to(np.asarray(x_hat, float), (M.shape[0], pr.n_x))
    lbg, ubg = pr.g_bounds()
    out: list[np.ndarray] = []
    st: list[str] = []
    for x_start, m in zip(X0, M):
        x0 = pr.to_scaled(x_start)
        lb, ub = np.full(pr.n_x, -np.inf), np.full(pr.n_x, np.inf)
        lb[fixed] = ub[fixed] = x0[fixed]
        bounds = {"lbx": lb, "ubx": ub, "lbg": lbg, "ubg": ubg}
        x, status = _ipopt_rounds(
            S, pr, opts, x0, pr.pack_data(q, t, m, w), bounds, max_iter, round_iter, step_tol
        )
        out.append(pr.from_scaled(x))
        st.append(status)
    return np.array(out), st


def _ipopt_rounds(
    S,
    pr,
    opts: dict,
    x: np.ndarray,
    pm: np.ndarray,
    bounds: dict[str, np.ndarray],
    max_iter: int,
    round_iter: int,
    step_tol: float,
) -> tuple[np.ndarray, str]:
    """IPOPT in rounds of ``round_iter`` iterations from x (scaled) until its last step is
    below ``step_tol`` or ``max_iter`` iterations in all (see :func:`ipopt_resolve`).
    Returns (x scaled, IPOPT's status)."""
    done = 0
    status = "unknown"
    extra: dict[str, Any] = {}
    solver = S
    while True:
        r = solver(x0=x, p=pm, **bounds, **extra)
        raise_if_signalled()  # IPOPT ends early on Ctrl-C / SIGTERM and returns
        stats = solver.stats()
        x = r["x"].full().ravel()
        extra = {"lam_g0": r["lam_g"]}
        status = str(stats.get("return_status", "unknown"))
        n_it = int(stats.get("iter_count", 0))
        done += n_it
        its = stats.get("iterations", {})
        step = (
            float(its["alpha_pr"][-1]) * float(its["d_norm"][-1])
            if n_it and its.get("d_norm")
            else 0.0
        )
        if (
            status != "Maximum_Iterations_Exceeded"
            or step < step_tol
            or n_it == 0
            or done >= max_iter
        ):
            return x, status
        if done + round_iter > max_iter:
            solver = _with_max_iter(pr, opts, max_iter - done)


def _with_max_iter(pr, opts: dict, n: int):
    """The verification solver with another iteration limit (the last round)."""
    import casadi as ca

    return ca.nlpsol("verify", "ipopt", pr.nlp, {**opts, "ipopt.max_iter": n})


def verify_against_ipopt(
    kernel: MCKernel, ider, p: np.ndarray, seed: int, trials: Iterable[int] = (0, 1, 2)
) -> dict[str, float]:
    """Solve a few trials with both the structured solver and IPOPT; the largest
    difference in scaled units (1 = 1 um / 1 urad) and relative to the largest theta."""
    trials = list(trials)
    dM, dX = kernel.sampler.draw(seed, trials)
    eng = kernel.engine
    X0 = np.tile(eng.x_hat, (len(trials), 1))
    X0[:, eng.fixed] += dX
    sol = eng.solve(eng.m[None, :] + dM, X0, tol=kernel.tol)
    Xi, _ = ipopt_resolve(ider, X0, p, eng.fixed, eng.m[None, :] + dM)
    d = np.abs(Xi - sol.x) / eng.scale
    nt = kernel.n_theta
    return {
        "max_abs_scaled": float(d.max()),
        "theta_rel": float(d[:, :nt].max() / np.abs(Xi[:, :nt] / eng.scale[:nt]).max()),
        "trials": len(trials),
    }


# --------------------------------------------------------------------------------------
# front end


class _Background:
    """``fn(*args)`` in a daemon thread; :meth:`result` waits for it and returns its value
    or raises its exception."""

    def __init__(self, fn, *args) -> None:
        import threading

        self._value: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(fn, args), name="volcal-background", daemon=True
        )
        self._thread.start()

    def _run(self, fn, args) -> None:
        try:
            self._value = fn(*args)
        except BaseException as exc:  # handed to the caller by result()
            self._error = exc

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def monte_carlo(*args, **kwargs) -> dict[str, Any]:
    """Identify, then Monte Carlo around the identification (see :func:`_monte_carlo` for
    the arguments); the numerics run with one BLAS thread (see :mod:`volcal.base.threads`)."""
    from volcal.base.threads import blas_threads

    with blas_threads(1):
        return _monte_carlo(*args, **kwargs)


def _monte_carlo(
    model,
    data,
    stations=None,
    *,
    budget="paper002",
    trials: int = 1000,
    seed: int = 0,
    mode: str = "nonlinear",
    workers: int | None = None,
    scheduler: Any = None,
    out_dir: str | Path | None = None,
    chunk_size: int = DEFAULT_CHUNK,
    error_model=None,
    degree: int = 3,
    datum: str = "iso230",
    strategy: str = "joint",
    eval_points: pd.DataFrame | None = None,
    tool_sigma_um: float = 0.0,
    station_sigma_um: float = 0.0,
    with_contributions: bool = False,
    contribution_trials: int | None = None,
    progress: bool = False,
    verify: int = 0,
    stages=None,
) -> dict[str, Any]:
    """Identify, then Monte Carlo around the identification.  Returns a dict with the
    identification ``result``, ``kernel``, ``mc`` (:class:`MCResult`), ``contributions``
    (a table or None) and ``verify`` (IPOPT cross-check of ``verify`` trials, or None).
    stages: a :class:`volcal.base.timing.Stages` that receives the seconds per stage."""
    from volcal.base.timing import Stages

    st = stages if stages is not None else Stages()
    with st("identification"):
        from volcal.analysis.identify import Identifier, identify
        from volcal.measurement.budget import load_budget
        from volcal.measurement.tables import load_measurements, load_stations
        from volcal.model.machine import Machine
        from volcal.problem.residuals import Layout

        machine = model if isinstance(model, Machine) else Machine.from_model(model)
        bud = load_budget(budget)
        # the trials draw every axis' positioning scatter from the budget, whatever sigma
        # the data carry: an axis without a term has none (warned once per run)
        bud.warn_uncovered(machine.spec)
        st_table = (
            load_stations(stations)
            if stations is not None
            and not (isinstance(stations, pd.DataFrame) and "dead_length_given" in stations)
            else stations
        )
        meas = (
            data
            if hasattr(data, "q_internal")
            else load_measurements(data, machine.spec, stations=st_table)
        )
        res = identify(
            machine,
            meas,
            st_table,
            strategy=strategy,
            degree=degree,
            datum=datum,
            error_model=error_model,
            budget=bud,
        )
    with st("Monte Carlo set-up"):
        em = res.error_model
        layout = Layout.from_measurements(meas)
        # the identification's own problem and solvers (the same model, error model and
        # layout), else built again
        ider = res.identifier
        if (
            ider is None
            or ider.machine is not machine
            or ider.error_model is not em
            or ider.problem.exact
            or ider.instrument.name != "tracker"
            or ider.layout.n_stations != layout.n_stations
            or not np.array_equal(ider.layout.station_index, layout.station_index)
            or not np.array_equal(ider.layout.poses[0], layout.poses[0])
        ):
            ider = Identifier(machine, em, layout)
        x_hat, w = identification_data(res, meas, bud)
        p = ider.problem.pack_data(meas.q_internal, meas.tool, meas.length, w)
        fixed = fixed_mask(ider, res)
        if eval_points is None:
            from volcal.measurement.plans import grid_plan

            eval_points = grid_plan(machine.spec, 5)
        eq = machine.axis_to_internal(eval_points[machine.axis_names].to_numpy(float))
        etool = (
            eval_points[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
            if "tool_x" in eval_points
            else None
        )
        kernel = build_kernel(
            ider,
            x_hat,
            p,
            fixed,
            bud,
            time_s=meas.time,
            eval_q=eq,
            eval_tool=etool,
            tool_sigma_mm=tool_sigma_um * 1e-3,
            station_sigma_mm=station_sigma_um * 1e-3,
        )
    background: list[_Background] = []

    def start_verify() -> None:
        # the IPOPT cross-check needs only the kernel: it runs in a thread alongside the
        # trials (in worker processes, or numpy code that releases the interpreter lock),
        # started once the workers are (no fork while it runs)
        if verify:
            kernel.engine.prepare()
            background.append(
                _Background(verify_against_ipopt, kernel, ider, p, seed, range(verify))
            )

    with st("trials"):
        samples = run_trials(
            kernel,
            trials,
            seed,
            mode=mode,
            chunk_size=chunk_size,
            workers=workers,
            scheduler=scheduler,
            out_dir=out_dir,
            progress=progress,
            label="all",
            on_start=start_verify,
        )
    with st("linearised covariance"):
        mc = MCResult.from_samples(
            kernel, samples, eval_points[machine.axis_names].reset_index(drop=True)
        )
    ver = None
    if verify:
        # finished before anything forks again (the contributions' workers)
        with st("IPOPT cross-check (the part after the trials)"):
            if not background:  # on_start not called (cannot happen: one chunk at least)
                start_verify()
            ver = background[0].result()
    contrib = None
    if with_contributions:
        with st("contributions"):
            contrib, _ = contributions(
                kernel,
                contribution_trials or trials,
                seed,
                mode=mode,
                chunk_size=chunk_size,
                workers=workers,
                scheduler=scheduler,
                out_dir=out_dir,
                progress=progress,
            )
    return {
        "result": res,
        "identifier": ider,
        "kernel": kernel,
        "mc": mc,
        "contributions": contrib,
        "verify": ver,
        "p": p,
        "fixed": fixed,
        "measurements": meas,
    }
