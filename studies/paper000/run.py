"""Paper 000 study: station calibration and point multilateration by each method.

On the simulated MCV 754 (paper 000's machine and the six station positions of its
Table 5, paper 002's budget), for every trial:

1. self-calibrate every station on the nominal points with each method of paper 000
   (Case A sqrt residual eq. 7, squared residual eq. 8, Case B linear normal equations
   eq. 9-11, Case B + Taylor refinement eq. 12-14) and paper 002's linear start (eq. 12-20);
   compare them with the true stations (truth-based measure) and, as the paper does in its
   Tables 6-9, with a reference self-calibration (the paper's Trac-Cal; here an unweighted
   sqrt self-calibration: another implementation of Case A);
2. multilaterate every point with each method from the stations of the same family and
   compare with the true actual points and with the reference's points;
3. identify the same data with volcal's one-step joint NLP (stations, dead lengths and
   cubic Legendre error motions together);
4. record the condition numbers of Case B's systems.

Two truths: ``model`` (the bundled cubic-Legendre error set: the joint NLP fits the family
that generated the data, exactly) and ``nonrep`` (error motions drawn by the independent
rigid-body simulator tests/indep_sim.py from sines of non-integer periods, smooth steps and
piecewise-linear tables, scaled to the same maximum volumetric error: outside the
identified basis).

Station subsets: Case B point multilateration with every 4 of the 6 stations (and all 6),
from the true stations and from the Case B stations, next to the singular values of the
stations' spread (the paper used four or six stations; its Fig. 6 shows Case B points up
to 0.5 mm off).

    python studies/paper000/run.py [--smoke] [--trials N] [--out DIR] [--update-readme]

``--smoke`` without ``--out`` writes into a new temporary folder.  Every table printed is
also in <out>/tables.md; ``--update-readme`` copies them into README.md's marked tables.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))
import readme_tables as rt  # noqa: E402

REF = "reference"            # the stand-in for Trac-Cal

# one reflector position is the paper's set-up; volcal warns about it at every load
warnings.filterwarnings("ignore", message=".*the tool offset is the same in every row.*")


def _rms(v) -> float:
    v = np.asarray(v, float)
    return float(np.sqrt(np.mean(v ** 2)))


# --------------------------------------------------------------------------------------
# truths


class NonRepTruth:
    """Error motions from tests/indep_sim.py's ``nonrep`` family (not cubic, no datum),
    evaluated by its exact rigid-body chain, scaled to ``max_um`` over the plan."""

    def __init__(self, ex, seed: int, max_um: float, tool: np.ndarray):
        sys.path.insert(0, str(ROOT / "tests"))
        import indep_sim as ind

        self.ind = ind
        self.geom = ind.load_geometry(ex.model)
        tr = ind.draw_truth(self.geom, np.random.default_rng(seed), "nonrep",
                            tool_orientation=False)
        plan = ex.plan[self.geom.axis_names].to_numpy(float)
        e = self._field(tr, plan, tool)
        self.truth = tr.scaled(max_um * 1e-3 / float(np.max(np.linalg.norm(e, axis=1))))
        self.families = sorted(set(tr.families.values()))

    def _field(self, truth, poses_file, tool):
        q = self.geom.to_internal(np.asarray(poses_file, float))
        t = np.broadcast_to(np.asarray(tool, float), (len(q), 3))
        return (self.ind.tool_points(self.geom, q, t, truth)
                - self.ind.tool_points(self.geom, q, t))

    def error_mm(self, poses_file, tool) -> np.ndarray:
        """(N, 3) volumetric error (actual - nominal) mm at commanded poses (file units)."""
        return self._field(self.truth, poses_file, tool)


def _max_volumetric_um(ex, tool) -> float:
    """Largest volumetric error (um) of the model truth over the plan (commanded poses)."""
    m = ex.machine
    q = _internal(m, ex.plan)
    t = np.broadcast_to(tool, (len(q), 3))
    p0 = m.evaluate(q, t, np.zeros(m.n_errors))[0]
    p1 = m.evaluate(q, t, ex.error_model.values(q, ex.theta_true), exact=True)[0]
    return 1e3 * float(np.max(np.linalg.norm(p1 - p0, axis=1)))


def _internal(m, plan: pd.DataFrame) -> np.ndarray:
    """Commanded poses of a plan (file units) in the model's internal units."""
    from volcal.measurement.tables import load_measurements

    df = plan.copy()
    df.insert(0, "point", [f"p{i}" for i in range(len(df))])
    df.insert(0, "station", "S")
    df["length"] = 1.0
    return load_measurements(df, m.spec).q_internal


def representation_floor_um(ex, cfg: dict, truth: NonRepTruth | None) -> float:
    """RMS (um) over the plan's poses of what the identified model cannot represent of the
    truth's error field: the residual of the least-squares fit of the true field (actual -
    nominal tool point) by the model's first-order field G theta plus a rigid motion (no
    multilateration sees the rigid motion), theta unconstrained.  0 up to second-order
    terms for the `model` truth."""
    from volcal.analysis.identifiability import rigid_columns

    m = ex.machine
    tool = np.asarray(cfg["tool"], float)
    q = _internal(m, ex.plan)
    t = np.broadcast_to(tool, (len(q), 3))
    p0, _, Je = m.evaluate(q, t, np.zeros(m.n_errors))
    if truth is None:
        e = m.evaluate(q, t, ex.error_model.values(q, ex.theta_true), exact=True)[0] - p0
    else:
        e = truth.error_mm(ex.plan[truth.geom.axis_names].to_numpy(float), tool)
    G = np.einsum("nik,nkp->nip", Je, ex.error_model.basis(q)).reshape(-1, ex.error_model.n_params)
    A = np.hstack([G, rigid_columns(p0)])
    A = A / np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    r = e.ravel() - A @ np.linalg.lstsq(A, e.ravel(), rcond=None)[0]
    return 1e3 * float(np.sqrt(np.mean(np.sum(r.reshape(-1, 3) ** 2, axis=1))))


# --------------------------------------------------------------------------------------
# one trial


def reading_layout(meas, stations):
    """The true stations of ``meas`` and the layout of its readings: true positions (K, 3)
    mm and dead lengths (K,) mm in the order of ``meas.station_ids`` (from ``stations``),
    the station id of every reading, the index of every point's first reading and the
    point x station matrix of the lengths (mm, NaN where a station did not measure)."""
    true_st = stations.set_index("station").loc[meas.station_ids]
    S_true = true_st[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    d_true = true_st["dead_length_mm"].to_numpy(float)
    ids = np.asarray(meas.station_ids, dtype=object)[meas.station_index]
    n_pts = len(meas.point_ids)
    first = np.zeros(n_pts, int)
    first[meas.point_index[::-1]] = np.arange(len(meas))[::-1]
    L = np.full((n_pts, len(meas.station_ids)), np.nan)
    L[meas.point_index, meas.station_index] = meas.length
    return S_true, d_true, ids, first, L


def one_trial(ex, seed: int, cfg: dict, truth: NonRepTruth | None = None):
    from volcal.analysis.identify import identify, rigid_fit
    from volcal.measurement.multilateration import calibrate_stations, multilaterate
    from volcal.measurement.simulate import simulate
    from volcal.measurement.tables import load_measurements

    tool = np.asarray(cfg["tool"], float)[None, :]
    m = ex.machine
    sim = simulate(m, ex.error_model, ex.theta_true, ex.stations, ex.plan, tool, ex.budget,
                   seed)
    table = sim.measurements.copy()
    if truth is not None:
        # the same readings (noise, repeatability) with the model's exact tool point
        # replaced by the other truth's: length += |S - p_new| - |S - p_old|
        meas0 = load_measurements(table, m.spec)
        St = ex.stations.set_index("station").loc[table["station"]]
        S = St[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        q = meas0.q_internal
        p_old = m.evaluate(q, meas0.tool, ex.error_model.values(q, ex.theta_true), exact=True)[0]
        p_nom = m.evaluate(q, meas0.tool, np.zeros(m.n_errors))[0]
        poses = table[truth.geom.axis_names].to_numpy(float)
        p_new = p_nom + truth.error_mm(poses, tool[0])
        table["length"] = (table["length"] + np.linalg.norm(S - p_new, axis=1)
                           - np.linalg.norm(S - p_old, axis=1))
    meas = load_measurements(table, m.spec)
    zeros = np.zeros(m.n_errors)
    p_nom, _, _ = m.evaluate(meas.q_internal, meas.tool, zeros)
    S_true, d_true, ids, first, L = reading_layout(meas, ex.stations)
    # true actual points at the commanded axes (the repeatability is noise)
    q_pts = meas.q_internal[first]
    if truth is None:
        p_true, _, _ = m.evaluate(q_pts, tool[0], ex.error_model.values(q_pts, ex.theta_true),
                                  exact=True)
    else:
        p_true = p_nom[first] + truth.error_mm(table[truth.geom.axis_names].to_numpy(float)
                                               [first], tool[0])

    st_rows, pt_rows = [], []
    cal_by_method = {}
    methods = [REF] + list(cfg["station_methods"])
    for method in methods:
        t0 = time.perf_counter()
        if method == REF:
            cal = calibrate_stations(ids, p_nom, meas.length, method="sqrt", sigma=None)
        else:
            cal = calibrate_stations(ids, p_nom, meas.length, method=method, sigma=meas.sigma)
        dt = time.perf_counter() - t0
        order = [list(map(str, cal.stations)).index(s) for s in meas.station_ids]
        S, d = cal.positions[order], cal.dead_lengths[order]
        cal_by_method[method] = (S, d)
        S_ref = cal_by_method[REF][0]
        _, S_rig = rigid_fit(S_true, S - S_true)
        for k, sid in enumerate(meas.station_ids):
            st_rows.append(dict(seed=seed, method=method, station=sid,
                                error_um=1e3 * float(np.linalg.norm(S[k] - S_true[k])),
                                error_rigid_removed_um=1e3 * float(np.linalg.norm(S_rig[k])),
                                dead_length_error_um=1e3 * float(d[k] - d_true[k]),
                                vs_reference_um=1e3 * float(np.linalg.norm(S[k] - S_ref[k])),
                                vs_reference_maxcomp_um=1e3 * float(np.max(np.abs(S[k]
                                                                                  - S_ref[k]))),
                                condition=float(cal.condition[order][k]),
                                condition_lower_bound=float(cal.condition_lower_bound[order][k]),
                                condition_scaled=float(cal.condition_scaled[order][k]),
                                converged=bool(cal.converged[order][k]), seconds=dt))
    pts_by_method = {}
    for method in [REF] + list(cfg["point_methods"]):
        S, d = cal_by_method[method]
        mmethod = "sqrt" if method == REF else method
        ml = multilaterate(S, d, L, method=mmethod, initial=p_nom[first])
        pts_by_method[method] = ml.points
        pt_rows.append(_point_row(seed, method, ml.points, p_true, pts_by_method[REF],
                                  rigid_fit, float(np.median(ml.condition)),
                                  float(np.max(ml.condition)), float(np.mean(ml.converged))))
    # volcal's one-step identification (stations, dead lengths and errors together)
    res = identify(m, meas, error_model=ex.error_model, budget=ex.budget)
    S = res.stations[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
    S_ref = cal_by_method[REF][0]
    _, S_rig = rigid_fit(S_true, S - S_true)
    for k, sid in enumerate(meas.station_ids):
        st_rows.append(dict(seed=seed, method="volcal joint", station=sid,
                            error_um=1e3 * float(np.linalg.norm(S[k] - S_true[k])),
                            error_rigid_removed_um=1e3 * float(np.linalg.norm(S_rig[k])),
                            dead_length_error_um=1e3 * float(res.stations["dead_length_mm"][k]
                                                             - d_true[k]),
                            vs_reference_um=1e3 * float(np.linalg.norm(S[k] - S_ref[k])),
                            vs_reference_maxcomp_um=1e3 * float(np.max(np.abs(S[k] - S_ref[k]))),
                            condition=res.conditions["jacobian_unscaled"],
                            condition_lower_bound=np.nan,
                            condition_scaled=res.conditions["jacobian_scaled"],
                            converged=res.success, seconds=res.seconds))
    # joint identification: the tool point of the identified model at the commanded pose
    pred = res.predict(q_pts, tool, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]] \
        .to_numpy() * 1e-3
    p0 = m.evaluate(q_pts, tool[0], zeros)[0]
    pt_rows.append(_point_row(seed, "volcal joint", p0 + pred, p_true, pts_by_method[REF],
                              rigid_fit, np.nan, np.nan, float(res.success)))
    return st_rows, pt_rows


def _point_row(seed, method, P, p_true, p_ref, rigid_fit, cmed, cmax, conv):
    err = np.linalg.norm(P - p_true, axis=1) * 1e3
    _, rig = rigid_fit(p_true, P - p_true)
    err_r = np.linalg.norm(rig, axis=1) * 1e3
    dref = np.linalg.norm(P - p_ref, axis=1) * 1e3
    return dict(seed=seed, method=method, rms_um=_rms(err), max_um=float(np.max(err)),
                rms_rigid_removed_um=_rms(err_r), max_rigid_removed_um=float(np.max(err_r)),
                vs_reference_rms_um=_rms(dref), condition_median=cmed, condition_max=cmax,
                converged=conv)


# --------------------------------------------------------------------------------------
# station subsets (4 of 6) for Case B points


def subsets(ex, cfg: dict, n_seeds: int) -> pd.DataFrame:
    """Case B (and sqrt) point multilateration with every subset of the stations of the
    sizes in cfg['subsets']['sizes'], on ``n_seeds`` simulated data sets (model truth)."""
    from volcal.measurement.multilateration import calibrate_stations, multilaterate
    from volcal.measurement.simulate import simulate
    from volcal.measurement.tables import load_measurements

    sc = cfg["subsets"]
    tool = np.asarray(cfg["tool"], float)[None, :]
    m = ex.machine
    rows = []
    for i in range(n_seeds):
        seed = int(sc.get("seed0", cfg["seed0"])) + i
        sim = simulate(m, ex.error_model, ex.theta_true, ex.stations, ex.plan, tool,
                       ex.budget, seed)
        meas = load_measurements(sim.measurements, m.spec)
        p_nom = m.evaluate(meas.q_internal, meas.tool, np.zeros(m.n_errors))[0]
        S_true, d_true, ids, first, L = reading_layout(meas, ex.stations)
        q_pts = meas.q_internal[first]
        p_true = m.evaluate(q_pts, tool[0], ex.error_model.values(q_pts, ex.theta_true),
                            exact=True)[0]
        cal = calibrate_stations(ids, p_nom, meas.length, method="linear", sigma=meas.sigma)
        order = [list(map(str, cal.stations)).index(s) for s in meas.station_ids]
        S_b, d_b = cal.positions[order], cal.dead_lengths[order]
        K = len(meas.station_ids)
        for size in sc["sizes"]:
            for combo in itertools.combinations(range(K), int(size)):
                c = list(combo)
                name = "+".join(str(meas.station_ids[j]) for j in c)
                sv = np.linalg.svd(S_true[c] - S_true[c].mean(axis=0), compute_uv=False)
                row = dict(seed=seed, stations=name, n_stations=len(c), sv1_mm=sv[0],
                           sv2_mm=sv[1], sv3_mm=sv[2])
                for label, S, d, meth in (("linear_true", S_true, d_true, "linear"),
                                          ("linear_caseB", S_b, d_b, "linear"),
                                          ("sqrt_true", S_true, d_true, "sqrt")):
                    ml = multilaterate(S[c], d[c], L[:, c], method=meth,
                                       initial=p_nom[first] if meth == "sqrt" else None,
                                       max_residual_rms=None)
                    e = np.linalg.norm(ml.points - p_true, axis=1) * 1e3
                    row[f"{label}_rms_um"] = _rms(e)
                    row[f"{label}_max_um"] = float(np.nanmax(e))
                    if label == "linear_true":
                        row["condition_median"] = float(np.median(ml.condition))
                rows.append(row)
    return pd.DataFrame(rows)


def subsets_table(df: pd.DataFrame) -> str:
    g = (df.groupby(["n_stations", "stations"], sort=False)
         .agg(sv3=("sv3_mm", "first"), sv2=("sv2_mm", "first"),
              lt_rms_lo=("linear_true_rms_um", "min"), lt_rms_hi=("linear_true_rms_um", "max"),
              lt_max=("linear_true_max_um", "max"),
              lb_rms_hi=("linear_caseB_rms_um", "max"), lb_max=("linear_caseB_max_um", "max"),
              sq_rms_hi=("sqrt_true_rms_um", "max"), cond=("condition_median", "median"))
         .reset_index())
    rows = []
    for _, r in g.iterrows():
        rows.append({"stations": r["stations"], "sv": f"{r['sv2']:.0f} / {r['sv3']:.2f}",
                     "lt": f"{rt._fmt(r['lt_rms_lo'])} - {rt._fmt(r['lt_rms_hi'])}",
                     "ltm": r["lt_max"], "lb": r["lb_rms_hi"], "lbm": r["lb_max"],
                     "sq": r["sq_rms_hi"], "cond": r["cond"]})
    return rt.markdown(rows, ["stations", "sv", "lt", "ltm", "lb", "lbm", "sq", "cond"],
                       ["stations", "singular values 2 / 3 of the spread (mm)",
                        "Case B points, true stations: RMS um (range over seeds)",
                        "max um", "Case B points, Case B stations: RMS um (worst seed)",
                        "max um", "sqrt points, true stations: RMS um (worst seed)",
                        "Case B condition (median)"])


def subsets_summary(df: pd.DataFrame) -> str:
    rows = []
    for n, d in df.groupby("n_stations"):
        rows.append({"n": int(n), "combos": d["stations"].nunique(),
                     "seeds": d["seed"].nunique(),
                     "lt": f"{rt._fmt(d['linear_true_rms_um'].min())} - "
                           f"{rt._fmt(d['linear_true_rms_um'].max())}",
                     "ltm": f"{rt._fmt(d['linear_true_max_um'].min())} - "
                            f"{rt._fmt(d['linear_true_max_um'].max())}",
                     "lb": f"{rt._fmt(d['linear_caseB_rms_um'].min())} - "
                           f"{rt._fmt(d['linear_caseB_rms_um'].max())}",
                     "sq": f"{rt._fmt(d['sqrt_true_rms_um'].min())} - "
                           f"{rt._fmt(d['sqrt_true_rms_um'].max())}",
                     "sv3": f"{rt._fmt(d['sv3_mm'].min())} - {rt._fmt(d['sv3_mm'].max())}"})
    return rt.markdown(rows, ["n", "combos", "seeds", "sv3", "lt", "ltm", "lb", "sq"],
                       ["stations used", "combinations", "seeds",
                        "3rd singular value of the spread (mm)",
                        "Case B points, true stations: RMS um", "max um",
                        "Case B points, Case B stations: RMS um",
                        "sqrt points, true stations: RMS um"])


# --------------------------------------------------------------------------------------
# the trial loop and its tables


def run(ex, trials: int, cfg: dict, truth: NonRepTruth | None, progress: bool, desc: str):
    st, pt = [], []
    for i in tqdm(range(trials), disable=not progress, desc=desc, file=sys.stderr):
        a, b = one_trial(ex, cfg["seed0"] + i, cfg, truth)
        st += a
        pt += b
    return pd.DataFrame(st), pd.DataFrame(pt)


def summaries(st: pd.DataFrame, pt: pd.DataFrame, cfg: dict):
    order = {m: i for i, m in enumerate([REF] + cfg["station_methods"] + ["volcal joint"])}
    rms = lambda v: float(np.sqrt(np.mean(v ** 2)))  # noqa: E731
    st_sum = (st.groupby("method")
              .agg(station_error_rms_um=("error_um", rms),
                   station_error_max_um=("error_um", "max"),
                   rigid_removed_rms_um=("error_rigid_removed_um", rms),
                   dead_length_error_rms_um=("dead_length_error_um", rms),
                   vs_reference_rms_um=("vs_reference_um", rms),
                   vs_reference_maxcomp_um=("vs_reference_maxcomp_um", "max"),
                   condition_median=("condition", "median"),
                   condition_lower_bound_median=("condition_lower_bound", "median"),
                   condition_scaled_median=("condition_scaled", "median"),
                   converged=("converged", "mean"))
              .reset_index().sort_values("method", key=lambda c: c.map(order)))
    # standard error of the RMS figures over trials (per-trial RMS, delta method)
    for col, src in (("rigid_removed_rms_se_um", "error_rigid_removed_um"),
                     ("vs_reference_rms_se_um", "vs_reference_um")):
        st_sum[col] = st_sum["method"].map(_rms_se(st, src))
    pt_sum = (pt.groupby("method")
              .agg(point_error_rms_um=("rms_um", rms),
                   point_error_max_um=("max_um", "max"),
                   rigid_removed_rms_um=("rms_rigid_removed_um", rms),
                   rigid_removed_max_um=("max_rigid_removed_um", "max"),
                   vs_reference_rms_um=("vs_reference_rms_um", rms),
                   condition_median=("condition_median", "median"),
                   condition_max=("condition_max", "max"),
                   converged=("converged", "mean"))
              .reset_index().sort_values("method", key=lambda c: c.map(order)))
    pt_sum["rigid_removed_rms_se_um"] = pt_sum["method"].map(_rms_se(pt, "rms_rigid_removed_um"))
    return st_sum, pt_sum


def _rms_se(df: pd.DataFrame, col: str) -> dict:
    """Standard error of an RMS figure, trials (seeds) the independent units: the per-trial
    mean square of ``col`` has standard error s / sqrt(n); RMS = sqrt(mean square), so
    SE(RMS) = SE(mean square) / (2 RMS)."""
    out = {}
    ms_all = df.assign(ms=df[col] ** 2).groupby(["method", "seed"])["ms"].mean()
    for meth, ms in ms_all.groupby(level=0):
        n = len(ms)
        r = float(np.sqrt(ms.mean()))
        out[meth] = float(ms.std(ddof=1) / np.sqrt(n) / (2 * r)) if n > 1 and r > 0 else np.nan
    return out


def _pm(v, se):
    return rt._fmt(v) if not np.isfinite(se) else f"{rt._fmt(v)} ± {rt._fmt(se)}"


def stations_table(s: pd.DataFrame) -> str:
    rows = [{"m": r.method, "e": r.station_error_rms_um, "emax": r.station_error_max_um,
             "rr": _pm(r.rigid_removed_rms_um, r.rigid_removed_rms_se_um),
             "dl": r.dead_length_error_rms_um,
             "ref": _pm(r.vs_reference_rms_um, r.vs_reference_rms_se_um),
             "c": r.condition_median, "lb": r.condition_lower_bound_median,
             "cs": r.condition_scaled_median} for r in s.itertuples()]
    return rt.markdown(rows, ["m", "e", "emax", "rr", "dl", "ref", "c", "lb", "cs"],
                       ["method", "error RMS um", "error max um",
                        "rigid removed RMS ± SE um", "dead length error RMS um",
                        "vs reference RMS ± SE um", "condition (median)",
                        "Theorem-1 lower bound", "condition, scaled columns"])


def points_table(p: pd.DataFrame) -> str:
    rows = [{"m": r.method, "e": r.point_error_rms_um, "emax": r.point_error_max_um,
             "rr": _pm(r.rigid_removed_rms_um, r.rigid_removed_rms_se_um),
             "rrm": r.rigid_removed_max_um, "ref": r.vs_reference_rms_um,
             "c": r.condition_median} for r in p.itertuples()]
    return rt.markdown(rows, ["m", "e", "emax", "rr", "rrm", "ref", "c"],
                       ["method", "error RMS um", "error max um",
                        "rigid removed RMS ± SE um", "rigid removed max um",
                        "vs reference RMS um", "condition (median)"])


PAPER_TABLES = {"sqrt": "table6", "squared": "table7", "linear": "table8",
                "linear_taylor": "table9"}


def paper_measure_table(s: pd.DataFrame, cfg: dict) -> str:
    """The paper's measure (each method vs a reference self-calibration; Tables 6-9, mm in
    the paper) next to ours and to the truth-based one."""
    paper = cfg.get("paper", {})
    ours = s.set_index("method")
    rows = []
    for meth, tab in PAPER_TABLES.items():
        D = 1e3 * np.abs(np.asarray(paper[tab], float))       # mm -> um, (6, 3)
        r = ours.loc[meth]
        rows.append({"m": meth, "tab": tab.replace("table", "Table "),
                     "prms": _rms(np.linalg.norm(D, axis=1)), "pmax": float(D.max()),
                     "orms": _pm(r.vs_reference_rms_um, r.vs_reference_rms_se_um),
                     "omax": r.vs_reference_maxcomp_um,
                     "truth": _pm(r.rigid_removed_rms_um, r.rigid_removed_rms_se_um)})
    for key, col in (("prank", "prms"), ("orank", "vs_reference_rms_um"),
                     ("trank", "rigid_removed_rms_um")):
        vals = [x[col] if col == "prms" else ours.loc[x["m"], col] for x in rows]
        for x, rk in zip(rows, np.argsort(np.argsort(vals)) + 1):
            x[key] = int(rk)
    return rt.markdown(rows, ["m", "tab", "prms", "pmax", "prank", "orms", "omax", "orank",
                              "truth", "trank"],
                       ["method", "paper", "paper: vs Trac-Cal RMS um",
                        "paper: largest component um", "paper rank",
                        "ours: vs reference RMS ± SE um", "ours: largest component um",
                        "rank", "ours: vs truth, rigid removed RMS ± SE um", "rank"])


def per_station_table(st: pd.DataFrame, cfg: dict) -> str:
    """Station by station: the paper's difference from Trac-Cal (Tables 6-9, the norm of each
    station's row, um) next to ours from the reference self-calibration (RMS over trials,
    um), and where each is largest: the pattern, not only the size."""
    paper = cfg.get("paper", {})
    ids = sorted(st["station"].unique())
    ours = (st.groupby(["method", "station"])["vs_reference_um"]
            .apply(lambda v: float(np.sqrt(np.mean(np.asarray(v) ** 2)))).unstack())
    rows = []
    for meth, tab in PAPER_TABLES.items():
        D = 1e3 * np.linalg.norm(np.asarray(paper[tab], float), axis=1)
        o = ours.loc[meth, ids].to_numpy(float)
        for who, v in ((f"paper, {tab.replace('table', 'Table ')}", D), ("ours", o)):
            rows.append({"m": meth, "who": who, **{k: f"{x:.3g}" for k, x in zip(ids, v)},
                         "top": " ".join(ids[i] for i in np.argsort(v)[::-1][:2])})
    return rt.markdown(rows, ["m", "who", *ids, "top"],
                       ["method", "source", *(f"{k} um" for k in ids),
                        "two largest"])


def per_station_from(csv: Path, cfg: dict) -> str:
    """:func:`per_station_table` from a finished run's stations_per_trial.csv."""
    return per_station_table(pd.read_csv(csv), cfg)


def advantage_table(sums: dict, floors: dict) -> str:
    rows = []
    for truth, (s, p) in sums.items():
        s2 = s.set_index("method")
        p2 = p.set_index("method")
        two = [m for m in s2.index if m not in ("volcal joint", REF)]
        twop = [m for m in p2.index if m not in ("volcal joint", REF)]
        bs = s2.loc[two, "rigid_removed_rms_um"].idxmin()
        bp = p2.loc[twop, "rigid_removed_rms_um"].idxmin()
        js, jp = s2.loc["volcal joint"], p2.loc["volcal joint"]
        rows.append({"truth": truth,
                     "bs": f"{rt._fmt(s2.loc[bs, 'rigid_removed_rms_um'])} ({bs})",
                     "js": _pm(js.rigid_removed_rms_um, js.rigid_removed_rms_se_um),
                     "rs": s2.loc[bs, "rigid_removed_rms_um"] / js.rigid_removed_rms_um,
                     "bp": f"{rt._fmt(p2.loc[bp, 'rigid_removed_rms_um'])} ({bp})",
                     "jp": _pm(jp.rigid_removed_rms_um, jp.rigid_removed_rms_se_um),
                     "rp": p2.loc[bp, "rigid_removed_rms_um"] / jp.rigid_removed_rms_um,
                     "floor": floors[truth]})
    return rt.markdown(rows, ["truth", "bs", "js", "rs", "bp", "jp", "rp", "floor"],
                       ["truth", "stations: best two-step RMS um", "stations: joint RMS ± SE um",
                        "ratio", "points: best two-step RMS um", "points: joint RMS ± SE um",
                        "ratio", "points: part of the truth the model cannot represent, RMS um"])


def bias_table(ex, cfg: dict, trials: int, progress: bool) -> str:
    """Do the two-step stations absorb the machine's errors?  The same simulated readings
    (same seeds: same noise and repeatability) with the truth's error parameters scaled by
    each of ``cfg["bias"]["scales"]`` (0: a machine without errors): the station and point
    errors (rigid motion removed) of the sqrt self-calibration, the best two-step method,
    against the joint identification's.  An error that grows in proportion to the scale
    is carried over from the machine's errors, not from the noise."""
    import dataclasses

    rows = []
    for scale in cfg["bias"]["scales"]:
        exs = dataclasses.replace(ex, theta_true=np.asarray(ex.theta_true) * float(scale))
        st, pt = run(exs, trials, cfg, None, progress, f"paper000 bias x{scale}")
        s_sum, p_sum = summaries(st, pt, cfg)
        s2, p2 = s_sum.set_index("method"), p_sum.set_index("method")
        row = {"scale": f"{float(scale):g}",
               "max": _max_volumetric_um(exs, np.asarray(cfg["tool"], float))}
        for key, m in (("s", "sqrt"), ("j", "volcal joint")):
            row[f"{key}st"] = _pm(s2.loc[m, "rigid_removed_rms_um"],
                                  s2.loc[m, "rigid_removed_rms_se_um"])
            row[f"{key}pt"] = _pm(p2.loc[m, "rigid_removed_rms_um"],
                                  p2.loc[m, "rigid_removed_rms_se_um"])
        rows.append(row)
    return rt.markdown(rows, ["scale", "max", "sst", "spt", "jst", "jpt"],
                       ["error parameters x", "largest volumetric error um",
                        "sqrt stations, rigid removed RMS ± SE um",
                        "sqrt points, rigid removed RMS ± SE um",
                        "joint stations, rigid removed RMS ± SE um",
                        "joint points, rigid removed RMS ± SE um"])


def _plot(st: pd.DataFrame, pt: pd.DataFrame, out: Path, name: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    panels = ((st, "error_rigid_removed_um", "station error (um)",
               "stations vs truth (rigid motion removed)"),
              (pt, "rms_rigid_removed_um", "point error RMS per trial (um)",
               "points vs truth (rigid motion removed)"))
    for a, (df, col, ylabel, title) in zip(ax, panels):
        methods = list(dict.fromkeys(df["method"]))
        a.boxplot([df.loc[df.method == m, col] for m in methods], showfliers=False)
        a.set_xticks(range(1, len(methods) + 1), methods, rotation=30)
        a.set_yscale("log")
        a.set_ylabel(ylabel)
        a.set_title(title)
    fig.tight_layout()
    fig.savefig(out / name, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true",
                    help="a couple of trials (for the tests), into a temporary folder "
                         "unless --out is given")
    ap.add_argument("--trials", type=int, default=None)
    ap.add_argument("--out", type=Path, default=None,
                    help="results folder (default studies/paper000/results)")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the printed tables into README.md's marked tables")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--per-station-from", type=Path, default=None, metavar="CSV",
                    help="print (and with --update-readme write) the per_station table from "
                         "a finished run's stations_per_trial.csv; compute nothing")
    args = ap.parse_args(argv)
    if args.per_station_from is not None:
        tab = per_station_from(args.per_station_from, tomllib.loads(args.config.read_text()))
        print(tab)
        if args.update_readme:
            rt.update_readme(HERE / "README.md", {"per_station": tab})
        return 0
    cfg = tomllib.loads(args.config.read_text())
    from volcal.measurement.simulate import example

    trials = args.trials or (cfg["smoke_trials"] if args.smoke else cfg["trials"])
    out = rt.output_folder(args.out, args.smoke, HERE / "results", "paper000")
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    ex = example(cfg["example"])
    tool = np.asarray(cfg["tool"], float)
    tables: dict[str, str] = {}
    sums = {}
    floors = {}
    runinfo = []
    for truth_name in cfg["truths"]:
        t0 = time.perf_counter()
        truth = None
        if truth_name == "nonrep":
            nr = cfg["nonrep"]
            truth = NonRepTruth(ex, int(nr["seed"]), _max_volumetric_um(ex, tool), tool)
        elif truth_name != "model":
            raise SystemExit(f"unknown truth {truth_name!r}: 'model' or 'nonrep'")
        floors[truth_name] = representation_floor_um(ex, cfg, truth)
        st, pt = run(ex, trials, cfg, truth, not args.no_progress, f"paper000 {truth_name}")
        s_sum, p_sum = summaries(st, pt, cfg)
        sums[truth_name] = (s_sum, p_sum)
        sfx = "" if truth_name == "model" else f"_{truth_name}"
        st.to_csv(out / f"stations_per_trial{sfx}.csv", index=False)
        pt.to_csv(out / f"points_per_trial{sfx}.csv", index=False)
        s_sum.to_csv(out / f"stations_summary{sfx}.csv", index=False)
        p_sum.to_csv(out / f"points_summary{sfx}.csv", index=False)
        _plot(st, pt, out, f"paper000_methods{sfx}.png")
        tables[f"stations_{truth_name}"] = stations_table(s_sum)
        tables[f"points_{truth_name}"] = points_table(p_sum)
        if truth_name == "model":
            tables["paper_measure"] = paper_measure_table(s_sum, cfg)
            tables["per_station"] = per_station_table(st, cfg)
        runinfo.append({"part": f"trials, truth {truth_name}", "n": trials,
                        "seconds": time.perf_counter() - t0})
    tables["advantage"] = advantage_table(sums, floors)
    t0 = time.perf_counter()
    n_bias = int(cfg["bias"]["smoke_trials" if args.smoke else "trials"])
    tables["bias"] = bias_table(ex, cfg, n_bias, not args.no_progress)
    runinfo.append({"part": "trials per scale, truth model scaled (bias)", "n": n_bias,
                    "seconds": time.perf_counter() - t0})
    t0 = time.perf_counter()
    n_seeds = int(cfg["subsets"]["smoke_seeds" if args.smoke else "seeds"])
    sub = subsets(ex, cfg, n_seeds)
    sub.to_csv(out / "subsets.csv", index=False)
    tables["subsets_summary"] = subsets_summary(sub)
    tables["subsets"] = subsets_table(sub)
    runinfo.append({"part": "station subsets (seeds)", "n": n_seeds,
                    "seconds": time.perf_counter() - t0})
    tables["runinfo"] = rt.markdown(runinfo, ["part", "n", "seconds"],
                                    ["part", "trials / seeds", "seconds"])
    rt.write_tables(out, tables)
    rt.print_and_publish(tables, f"\n{trials} trials per truth in "
                         f"{time.perf_counter() - t_all:.1f} s; results in {out}",
                         HERE / "README.md", args.update_readme, args.smoke)
    return 0


if __name__ == "__main__":
    sys.exit(main())
