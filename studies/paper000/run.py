"""Paper 000 study: station calibration and point multilateration by each method.

On the simulated MCV 754 (paper 000's machine and the six station positions of its
Table 5, a realistic error set of ~64 um maximum, paper 002's budget), for every trial:

1. self-calibrate every station on the nominal points with each method of paper 000
   (Case A sqrt residual eq. 7, squared residual eq. 8, Case B linear normal equations
   eq. 9-11, Case B + Taylor refinement eq. 12-14) and paper 002's linear start (eq. 12-20),
   and compare with the true stations (paper 000 Tables 6-9 compare with Trac-Cal);
2. multilaterate every point with each method from the stations of the same family
   (sqrt stations for sqrt points, ...) and compare with the true actual points
   (paper 000 Fig. 5-6 compare volumetric errors with Trac-Cal);
3. identify the same data with volcal's one-step joint NLP for reference;
4. record the condition numbers of Case B's systems.

    python studies/paper000/run.py [--smoke] [--trials N] [--out DIR]
"""
from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

HERE = Path(__file__).parent


def one_trial(ex, seed: int, cfg: dict) -> tuple[list[dict], list[dict]]:
    from volcal.measurement.tables import load_measurements
    from volcal.analysis.identify import identify, rigid_fit
    from volcal.measurement.multilateration import calibrate_stations, multilaterate
    from volcal.measurement.simulate import simulate

    tool = np.asarray(cfg["tool"], float)[None, :]
    sim = simulate(ex.machine, ex.error_model, ex.theta_true, ex.stations, ex.plan, tool,
                   ex.budget, seed)
    meas = load_measurements(sim.measurements, ex.machine.spec)
    m = ex.machine
    zeros = np.zeros(m.n_errors)
    p_nom, _, _ = m.evaluate(meas.q_internal, meas.tool, zeros)
    true_st = ex.stations.set_index("station").loc[meas.station_ids]
    S_true = true_st[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    d_true = true_st["dead_length_mm"].to_numpy(float)
    ids = np.asarray(meas.station_ids, dtype=object)[meas.station_index]
    # true actual points (exact model, commanded axes: the repeatability is noise)
    n_pts = len(meas.point_ids)
    first = np.zeros(n_pts, int)
    first[meas.point_index[::-1]] = np.arange(len(meas))[::-1]
    q_pts = meas.q_internal[first]
    p_true, _, _ = m.evaluate(q_pts, tool[0], ex.error_model.values(q_pts, ex.theta_true),
                              exact=True)
    L = np.full((n_pts, len(meas.station_ids)), np.nan)
    L[meas.point_index, meas.station_index] = meas.length

    st_rows, pt_rows = [], []
    cal_by_method = {}
    for method in cfg["station_methods"]:
        t0 = time.perf_counter()
        cal = calibrate_stations(ids, p_nom, meas.length, method=method, sigma=meas.sigma)
        dt = time.perf_counter() - t0
        order = [list(map(str, cal.stations)).index(s) for s in meas.station_ids]
        S, d = cal.positions[order], cal.dead_lengths[order]
        cal_by_method[method] = (S, d)
        _, S_rig = rigid_fit(S_true, S - S_true)
        for k, sid in enumerate(meas.station_ids):
            st_rows.append(dict(seed=seed, method=method, station=sid,
                                error_um=1e3 * float(np.linalg.norm(S[k] - S_true[k])),
                                error_rigid_removed_um=1e3 * float(np.linalg.norm(S_rig[k])),
                                dead_length_error_um=1e3 * float(d[k] - d_true[k]),
                                condition=float(cal.condition[order][k]),
                                condition_lower_bound=float(cal.condition_lower_bound[order][k]),
                                condition_scaled=float(cal.condition_scaled[order][k]),
                                converged=bool(cal.converged[order][k]), seconds=dt))
    for method in cfg["point_methods"]:
        S, d = cal_by_method[method]
        ml = multilaterate(S, d, L, method=method, initial=p_nom[first])
        err = np.linalg.norm(ml.points - p_true, axis=1) * 1e3
        _, rig = rigid_fit(p_true, ml.points - p_true)
        err_r = np.linalg.norm(rig, axis=1) * 1e3
        pt_rows.append(dict(seed=seed, method=method, rms_um=float(np.sqrt(np.mean(err ** 2))),
                            max_um=float(np.max(err)),
                            rms_rigid_removed_um=float(np.sqrt(np.mean(err_r ** 2))),
                            max_rigid_removed_um=float(np.max(err_r)),
                            condition_median=float(np.median(ml.condition)),
                            condition_max=float(np.max(ml.condition)),
                            converged=float(np.mean(ml.converged))))
    # reference: volcal's one-step identification (stations and errors together)
    res = identify(m, meas, error_model=ex.error_model, budget=ex.budget)
    S = res.stations[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    _, S_rig = rigid_fit(S_true, S - S_true)
    for k, sid in enumerate(meas.station_ids):
        st_rows.append(dict(seed=seed, method="volcal joint", station=sid,
                            error_um=1e3 * float(np.linalg.norm(S[k] - S_true[k])),
                            error_rigid_removed_um=1e3 * float(np.linalg.norm(S_rig[k])),
                            dead_length_error_um=1e3 * float(res.stations["dead_length_mm"][k]
                                                             - d_true[k]),
                            condition=res.conditions["jacobian_unscaled"],
                            condition_lower_bound=np.nan,
                            condition_scaled=res.conditions["jacobian_scaled"],
                            converged=res.success, seconds=res.seconds))
    # joint identification: the tool point of the identified model at the commanded pose
    pred = res.predict(q_pts, tool, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy() * 1e-3
    p0 = m.evaluate(q_pts, tool[0], zeros)[0]
    err = np.linalg.norm(p0 + pred - p_true, axis=1) * 1e3
    _, rig = rigid_fit(p_true, p0 + pred - p_true)
    err_r = np.linalg.norm(rig, axis=1) * 1e3
    pt_rows.append(dict(seed=seed, method="volcal joint", rms_um=float(np.sqrt(np.mean(err ** 2))),
                        max_um=float(np.max(err)),
                        rms_rigid_removed_um=float(np.sqrt(np.mean(err_r ** 2))),
                        max_rigid_removed_um=float(np.max(err_r)), condition_median=np.nan,
                        condition_max=np.nan, converged=float(res.success)))
    return st_rows, pt_rows


def run(trials: int, out: Path, cfg: dict, progress: bool = True) -> dict[str, pd.DataFrame]:
    from volcal.measurement.simulate import example

    ex = example(cfg["example"])
    st, pt = [], []
    for i in tqdm(range(trials), disable=not progress, desc="paper000 trials"):
        a, b = one_trial(ex, cfg["seed0"] + i, cfg)
        st += a
        pt += b
    st, pt = pd.DataFrame(st), pd.DataFrame(pt)
    order = {m: i for i, m in enumerate(cfg["station_methods"] + ["volcal joint"])}
    st_sum = (st.groupby("method")
              .agg(station_error_rms_um=("error_um", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                   station_error_max_um=("error_um", "max"),
                   rigid_removed_rms_um=("error_rigid_removed_um",
                                         lambda v: float(np.sqrt(np.mean(v ** 2)))),
                   dead_length_error_rms_um=("dead_length_error_um",
                                             lambda v: float(np.sqrt(np.mean(v ** 2)))),
                   condition_median=("condition", "median"),
                   condition_lower_bound_median=("condition_lower_bound", "median"),
                   condition_scaled_median=("condition_scaled", "median"),
                   converged=("converged", "mean"))
              .reset_index().sort_values("method", key=lambda c: c.map(order)))
    pt_sum = (pt.groupby("method")
              .agg(point_error_rms_um=("rms_um", lambda v: float(np.sqrt(np.mean(v ** 2)))),
                   point_error_max_um=("max_um", "max"),
                   rigid_removed_rms_um=("rms_rigid_removed_um",
                                         lambda v: float(np.sqrt(np.mean(v ** 2)))),
                   rigid_removed_max_um=("max_rigid_removed_um", "max"),
                   condition_median=("condition_median", "median"),
                   condition_max=("condition_max", "max"),
                   converged=("converged", "mean"))
              .reset_index().sort_values("method", key=lambda c: c.map(order)))
    out.mkdir(parents=True, exist_ok=True)
    st.to_csv(out / "stations_per_trial.csv", index=False)
    pt.to_csv(out / "points_per_trial.csv", index=False)
    st_sum.to_csv(out / "stations_summary.csv", index=False)
    pt_sum.to_csv(out / "points_summary.csv", index=False)
    _plot(st, pt, out)
    return {"stations": st_sum, "points": pt_sum}


def _plot(st: pd.DataFrame, pt: pd.DataFrame, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    methods = list(dict.fromkeys(st["method"]))
    ax[0].boxplot([st.loc[st.method == m, "error_rigid_removed_um"] for m in methods],
                  showfliers=False)
    ax[0].set_xticks(range(1, len(methods) + 1), methods, rotation=30)
    ax[0].set_yscale("log")
    ax[0].set_ylabel("station error (um)")
    ax[0].set_title("stations vs truth (rigid motion removed)")
    methods = list(dict.fromkeys(pt["method"]))
    ax[1].boxplot([pt.loc[pt.method == m, "rms_rigid_removed_um"] for m in methods],
                  showfliers=False)
    ax[1].set_xticks(range(1, len(methods) + 1), methods, rotation=30)
    ax[1].set_yscale("log")
    ax[1].set_ylabel("point error RMS per trial (um)")
    ax[1].set_title("points vs truth (rigid motion removed)")
    fig.tight_layout()
    fig.savefig(out / "paper000_methods.png", dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="a couple of trials (for the tests)")
    ap.add_argument("--trials", type=int, default=None)
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    cfg = tomllib.loads(args.config.read_text())
    trials = args.trials or (cfg["smoke_trials"] if args.smoke else cfg["trials"])
    t0 = time.perf_counter()
    tables = run(trials, args.out, cfg, progress=not args.no_progress)
    pd.set_option("display.width", 200)
    for name, tab in tables.items():
        print(f"\n{name} ({trials} trials)")
        print(tab.to_markdown(index=False, floatfmt=".3g"))
    print(f"\n{trials} trials in {time.perf_counter() - t0:.1f} s; results in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
