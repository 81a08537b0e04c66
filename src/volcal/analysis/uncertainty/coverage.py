"""Coverage check: do the quoted 95 % intervals hold the truth 95 % of the time?

One *experiment*: draw a true error set (seeded), simulate the measurement with the
budget's noise (the simulator's own noise model, independent of volcal's uncertainty
code), identify it with :func:`volcal.analysis.identify.identify`, and check at fixed poses
whether the true volumetric error lies inside

* the linearised interval ``estimate +- 1.96 u`` (u from the identification's covariance),
* the Monte Carlo 95 % coverage interval (GUM S1, probabilistically symmetric) of a run
  around that identification;

and whether the true error parameters lie inside ``estimate +- 1.96 u``.

The volumetric errors and the parameters are compared directly with the truth: the datum
constraints (ISO 230 convention) define the error parameters and hence the volumetric
error in the machine frame; the identification's gauge freedom (the rigid motion of the
station set) is carried by the station and frame variables, not by the errors (see
:mod:`volcal.outputs.analysis_report`).  The truth is drawn satisfying the same datum.
Weights equal the simulator's noise: the simulated table carries each reading's
standard uncertainty from the same budget.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from volcal.base.units import report_factors
from volcal.measurement.budget import Budget
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine

__all__ = ["CoverageSetup", "coverage_experiment", "run_coverage", "summarise_coverage", "Z95"]

#: two-sided 95 % quantile of the normal distribution
Z95 = 1.959963984540054


@dataclass
class CoverageSetup:
    """The fixed part of the experiments: machine, error model, stations, plan, tools,
    budget, the check poses (M, n_axes; file units) and the size of the drawn errors."""

    machine: Machine
    error_model: ErrorModel
    stations: pd.DataFrame
    plan: pd.DataFrame
    tools: np.ndarray
    budget: Budget
    check_poses: pd.DataFrame
    max_volumetric_um: float = 60.0
    mc_trials: int = 1000
    draw_truth: bool = True  # a new truth per experiment (else the example's)
    theta_fixed: np.ndarray | None = None

    @classmethod
    def from_example(
        cls,
        name: str = "mcv754",
        *,
        grid: dict | int | None = None,
        mc_trials: int = 1000,
        n_check: int = 3,
        draw_truth: bool = True,
    ) -> CoverageSetup:
        from volcal.measurement.plans import grid_plan
        from volcal.measurement.simulate import _clear_plan, example

        ex = example(name)
        plan = ex.plan
        if grid is not None:
            plan = _clear_plan(
                ex.machine, grid_plan(ex.machine.spec, grid), ex.tools, ex.stations, 50.0
            )
        check = grid_plan(ex.machine.spec, n_check)
        return cls(
            ex.machine,
            ex.error_model,
            ex.stations,
            plan,
            ex.tools,
            ex.budget,
            check,
            60.0,
            mc_trials,
            draw_truth,
            ex.theta_true,
        )


def coverage_experiment(setup: CoverageSetup, k: int, *, seed: int = 0, mc: bool = True) -> dict:
    """Experiment k (see the module docstring).  Returns per check pose and component the
    truth, the estimate, the linearised u and inside flags, the MC interval and inside
    flags, and per parameter the z-score (estimate - truth) / u."""
    from volcal.analysis.identify import Identifier, identify
    from volcal.analysis.uncertainty.montecarlo import (
        build_kernel,
        fixed_mask,
        identification_data,
        run_trials,
    )
    from volcal.measurement.simulate import draw_true_parameters, simulate
    from volcal.measurement.tables import load_measurements
    from volcal.problem.residuals import Layout

    t0 = time.perf_counter()
    m, em = setup.machine, setup.error_model
    ss = np.random.SeedSequence(seed, spawn_key=(k,))
    s_truth, s_noise, s_mc = (int(c.generate_state(1)[0]) for c in ss.spawn(3))
    if setup.draw_truth:
        theta = draw_true_parameters(m, em, np.random.default_rng(s_truth), setup.max_volumetric_um)
    else:
        theta = np.asarray(setup.theta_fixed, float)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim = simulate(m, em, theta, setup.stations, setup.plan, setup.tools, setup.budget, s_noise)
        meas = load_measurements(sim.measurements, m.spec)
    res = identify(m, meas, error_model=em, budget=setup.budget)
    q = m.axis_to_internal(setup.check_poses[m.axis_names].to_numpy(float))
    _, true_dp, _ = m.evaluate(q, np.zeros(3), em.values(q, theta), exact=True)
    truth = true_dp * 1e3
    pred = res.predict(q)
    est = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
    u = pred[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()
    lin_in = np.abs(est - truth) <= Z95 * u
    par = res.parameters()
    f = report_factors(em.param_units)
    zpar = (par["value"].to_numpy() - theta * f) / par["u"].to_numpy()
    out = {
        "k": k,
        "truth": truth,
        "estimate": est,
        "u_linear": u,
        "linear_inside": lin_in,
        "z_parameters": zpar,
        "status": res.status,
        "success": res.success,
        "chi2": res.conditions.get("chi2_per_dof"),
    }
    if mc:
        layout = Layout.from_measurements(meas)
        ider = Identifier(m, em, layout)
        x_hat, w = identification_data(res, meas, setup.budget)
        p = ider.problem.pack_data(meas.q_internal, meas.tool, meas.length, w)
        kern = build_kernel(
            ider, x_hat, p, fixed_mask(ider, res), setup.budget, eval_q=q, check=False
        )
        smp = run_trials(kern, setup.mc_trials, s_mc, workers=1)
        V = smp.vol * 1e3
        lo, hi = np.quantile(V, [0.025, 0.975], axis=0)
        out.update(
            {
                "mc_low": lo,
                "mc_high": hi,
                "u_mc": V.std(axis=0, ddof=1),
                "mc_inside": (truth >= lo) & (truth <= hi),
                "mc_not_converged": int((~smp.converged).sum()),
            }
        )
    out["seconds"] = time.perf_counter() - t0
    return out


def _worker(args):
    from volcal.base.threads import set_blas_threads

    set_blas_threads(1)
    setup, k, seed, mc = args
    return coverage_experiment(setup, k, seed=seed, mc=mc)


def run_coverage(
    setup: CoverageSetup,
    n: int,
    *,
    seed: int = 0,
    mc: bool = True,
    workers: int = 1,
    progress: bool = False,
) -> list[dict]:
    """n experiments (0 .. n-1), in ``workers`` processes."""
    jobs = [(setup, k, seed, mc) for k in range(n)]
    from volcal.base.progress import counter

    out = []
    # a bar on a terminal, plain lines with the time left in logs
    with counter(n, "coverage", "experiment", on=progress) as bar:
        if workers <= 1:
            from volcal.base.threads import blas_threads

            with blas_threads(1):
                for j in jobs:
                    out.append(coverage_experiment(setup, j[1], seed=seed, mc=mc))
                    bar.update(1)
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            from volcal.analysis.uncertainty.parallel import _start_method

            ctx = mp.get_context(_start_method())
            with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
                for r in pool.map(_worker, jobs):
                    out.append(r)
                    bar.update(1)
    return sorted(out, key=lambda r: r["k"])


def _binom_ci(x: int, n: int) -> tuple[float, float]:
    """Wilson 95 % interval of a proportion."""
    if n == 0:
        return (float("nan"), float("nan"))
    z = Z95
    p = x / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (float(c - h), float(c + h))


def summarise_coverage(results: list[dict]) -> dict:
    """Pooled and per-pose coverage rates (with counts), for the linearised and MC
    intervals and the parameters."""
    ok = [r for r in results if r["success"]]
    out: dict[str, Any] = {"experiments": len(results), "succeeded": len(ok)}
    for key in ("linear_inside", "mc_inside"):
        if not ok or key not in ok[0]:
            continue
        A = np.array([r[key] for r in ok])  # (E, M, 3)
        # poses where the datum fixes a component exactly (u = 0, truth = 0) carry no test
        U = np.array([r["u_linear"] for r in ok])
        valid = U.mean(axis=0) > 1e-6
        Av = A[:, valid]
        x, n = int(Av.sum()), int(Av.size)
        per = Av.mean(axis=0)
        per_exp = Av.mean(axis=1)
        out[key] = {
            "inside": x,
            "checks": n,
            "rate": x / n,
            "per_check_min": float(per.min()),
            "per_check_max": float(per.max()),
            "n_check_quantities": int(valid.sum()),
            "rate_ci95_if_independent": _binom_ci(x, n),
            "experiment_rate_std": float(per_exp.std(ddof=1)) if len(ok) > 1 else 0.0,
        }
    Z = np.array([r["z_parameters"] for r in ok])
    Zf = Z[np.isfinite(Z)]
    inside = np.abs(Zf) <= Z95
    out["parameters"] = {
        "inside": int(inside.sum()),
        "checks": int(Zf.size),
        "rate": float(inside.mean()) if Zf.size else float("nan"),
        "z_std": float(Zf.std()) if Zf.size else float("nan"),
    }
    if ok and "u_mc" in ok[0]:
        r = np.concatenate(
            [x["u_mc"][x["u_linear"] > 1e-6] / x["u_linear"][x["u_linear"] > 1e-6] for x in ok]
        )
        out["u_mc_over_u_linear"] = {
            "median": float(np.median(r)),
            "min": float(r.min()),
            "max": float(r.max()),
        }
    if ok and "mc_not_converged" in ok[0]:
        out["mc_trials_not_converged"] = int(sum(r["mc_not_converged"] for r in ok))
    out["seconds_per_experiment"] = float(np.mean([r["seconds"] for r in results]))
    return out
