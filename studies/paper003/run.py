"""Paper 003 study: the cubic regression of the positional deviation (ISO 230-2 data).

Halaj, Kureková, Palenčár, Loebl, "The positional deviation in two axes": a cubic
polynomial Δ(P) = a + b P + c P² + d P³ (eq. 2) fitted by generalised least squares to the
mean deviations per target with the covariance of eq. 7-10 (type A uncertainty of each mean
plus the instrument's error, common to all readings), its results for the Y axis of a
gantry laser-cutting machine (eq. 11: approach from the right, eq. 12: from the left) and
the two-axis model without interactions (eq. 13).

The paper's readings are not published, so the study simulates data sets whose true mean
deviations are the paper's curves (10 targets, 10 cycles, config.toml) and fits them with
volcal's :mod:`volcal.iso230_2`:

* ``regression``: eq. 11-12 coefficient by coefficient, the paper's value next to volcal's
  fit of one data set with its expanded uncertainty, and the coverage of the k = 2
  intervals over many data sets (type A by GUM-S1 and by the paper's eq. 10);
* ``curves``: the deviation at the ends, the reversal value, the error of the fitted curve
  against the paper's over the travel, the coverage of U(P), and what the printed digits of
  eq. 11-12 leave uncertain;
* ``instrument``: what the common instrument term of eq. 7-9 changes (only the constant);
* ``plane``: eq. 13 on a P x R grid with eq. 11 in P and eq. 12 in R: coefficients
  recovered, and whether the model's lack of interactions is detected when the truth has
  a P R term (chi-square test).

    python studies/paper003/run.py [--smoke] [--out DIR] [--update-readme]

``--smoke`` without ``--out`` writes into a new temporary folder.
"""
from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import readme_tables as rt  # noqa: E402

COEFS = ("a", "b", "c", "d")
UNITS = ("mm", "1", "1/mm", "1/mm²")


def _poly(c, P):
    return np.polynomial.polynomial.polyval(np.asarray(P, float), np.asarray(c, float))


def targets(cfg: dict) -> np.ndarray:
    ax = cfg["axis"]
    return np.linspace(float(ax["first_mm"]), float(ax["last_mm"]), int(ax["targets"]))


def simulate_axis(cfg: dict, rng: np.random.Generator):
    """(up, down) readings (m x n) in mm: the paper's curves + repeatability + one
    instrument error common to every reading of the data set."""
    sm, ax = cfg["simulation"], cfg["axis"]
    P = targets(cfg)
    n = int(ax["cycles"])
    s = 1e-3 * float(sm["repeatability_um"])
    mpe = 1e-3 * float(sm["mpe_um"])
    delta = rng.uniform(-mpe, mpe)
    up = _poly(cfg["paper"]["from_left"], P)[:, None] + rng.normal(0, s, (len(P), n)) + delta
    down = _poly(cfg["paper"]["from_right"], P)[:, None] + rng.normal(0, s, (len(P), n)) + delta
    return P, up, down


def fit(cfg: dict, P, up, down, type_a: str = "gum-s1", with_instrument: bool = True):
    from volcal.iso230_2.model import fit_axis_model

    u_inst = 1e-3 * float(cfg["simulation"]["mpe_um"]) / np.sqrt(3.0) if with_instrument else 0.0
    return fit_axis_model(P, up, down, degree=3, u_instrument=u_inst, type_a=type_a)


CURVES = (("eq. 11", "from_right", "down"), ("eq. 12", "from_left", "up"))


def regression(cfg: dict, reps: int, seed: int) -> tuple[list[dict], dict]:
    rng = np.random.default_rng(seed)
    P, up, down = simulate_axis(cfg, rng)
    one = {t: fit(cfg, P, up, down, t) for t in ("gum-s1", "paper")}
    # coverage of the k = 2 coefficient intervals and of the band U(P) over many data sets
    grid = np.linspace(P[0], P[-1], 101)
    hits = {t: np.zeros((2, 4)) for t in one}
    band = {t: np.zeros(2) for t in one}
    max_err = np.zeros(2)
    for _ in range(reps):
        Pk, u, d = simulate_axis(cfg, rng)
        for t in one:
            mdl = fit(cfg, Pk, u, d, t)
            for c, (_, key, which) in enumerate(CURVES):
                a, cov = mdl.raw(which)
                truth = np.asarray(cfg["paper"][key], float)
                hits[t][c] += np.abs(a - truth) <= 2 * np.sqrt(np.diag(cov))
                e = np.abs(mdl.value(grid, which) - _poly(truth, grid))
                band[t][c] += np.mean(e <= mdl.expanded(grid, which))
                if t == "gum-s1":
                    max_err[c] = max(max_err[c], float(e.max()))
    rows = []
    for c, (eq, key, which) in enumerate(CURVES):
        a, cov = one["gum-s1"].raw(which)
        u = np.sqrt(np.diag(cov))
        for k, name in enumerate(COEFS):
            paper = float(cfg["paper"][key][k])
            rows.append({"key": f"{eq} {name} ({UNITS[k]})", "paper": paper, "fit": a[k],
                         "U": 2 * u[k], "z": (a[k] - paper) / u[k],
                         "cov_gum": 100 * hits["gum-s1"][c, k] / reps,
                         "cov_paper": 100 * hits["paper"][c, k] / reps})
    extra = {"one": one["gum-s1"], "band": {t: 100 * band[t] / reps for t in band},
             "max_err_um": 1e3 * max_err, "P": P}
    return rows, extra


def _g(v) -> str:
    return f"{v:.5g}"


def regression_table(rows: list[dict]) -> str:
    tab = [{"key": r["key"], "paper": _g(r["paper"]), "fit": _g(r["fit"]), "U": _g(r["U"]),
            "z": f"{r['z']:+.2f}", "cg": f"{r['cov_gum']:.1f}", "cp": f"{r['cov_paper']:.1f}"}
           for r in rows]
    return rt.markdown(tab, ["key", "paper", "fit", "U", "z", "cg", "cp"],
                       ["coefficient", "paper", "volcal fit (one data set)", "U (k = 2)",
                        "(fit - paper) / u",
                        "coverage of ±U over the data sets, GUM-S1 type A, %",
                        "coverage, paper's eq. 10, %"])


def rounding_um(coefs, P) -> float:
    """Largest change of the curve over P (um) when every printed coefficient moves by half
    a unit of its last printed digit (worst case, signs aligned)."""
    half = []
    for c in coefs:
        s = f"{c:.10g}"
        mant = s.split("e")[0].lstrip("-")
        digits = len(mant.split(".")[1]) if "." in mant else 0
        exp = int(s.split("e")[1]) if "e" in s else 0
        half.append(0.5 * 10.0 ** (exp - digits))
    k = np.arange(len(coefs))
    return 1e3 * float(np.max(np.abs(P)[:, None] ** k @ np.asarray(half)))


def curves_table(cfg: dict, extra: dict) -> str:
    mdl, P = extra["one"], extra["P"]
    grid = np.linspace(P[0], P[-1], 201)
    right, left = (np.asarray(cfg["paper"][k], float) for k in ("from_right", "from_left"))
    rows = []
    for label, x in (("first target", P[0]), ("last target", P[-1])):
        for eq, coef, which in (("eq. 11 (down)", right, "down"), ("eq. 12 (up)", left, "up")):
            rows.append({"q": f"deviation at the {label}, {eq} (um)",
                         "paper": 1e3 * _poly(coef, x),
                         "fit": f"{1e3 * mdl.value(x, which)[0]:.2f} ± "
                                f"{1e3 * mdl.expanded(x, which)[0]:.2f}"})
        rows.append({"q": f"reversal value up - down at the {label} (um)",
                     "paper": 1e3 * (_poly(left, x) - _poly(right, x)),
                     "fit": f"{1e3 * mdl.value(x, 'reversal')[0]:.2f} ± "
                            f"{1e3 * mdl.expanded(x, 'reversal')[0]:.2f}"})
    for eq, coef, c in (("eq. 11", right, 0), ("eq. 12", left, 1)):
        vals = 1e3 * _poly(coef, grid)
        rows.append({"q": f"range of the curve over the travel, {eq} (um)",
                     "paper": float(vals.max() - vals.min()), "fit": "-"})
        rows.append({"q": f"printed digits of {eq}: worst-case curve change (um)",
                     "paper": rounding_um(coef, grid), "fit": "-"})
        rows.append({"q": f"largest abs(fit - paper's curve) over the travel, {eq}, all data "
                          f"sets (um)", "paper": "-", "fit": f"{extra['max_err_um'][c]:.2f}"})
        rows.append({"q": f"coverage of the band ±U(P), {eq}: GUM-S1 / eq. 10 (%)",
                     "paper": "-", "fit": f"{extra['band']['gum-s1'][c]:.1f} / "
                                          f"{extra['band']['paper'][c]:.1f}"})
    return rt.markdown(rows, ["q", "paper", "fit"],
                       ["quantity", "paper (from eq. 11-12)", "volcal (one data set ± U, k = 2)"])


def instrument_table(cfg: dict, seed: int) -> str:
    rng = np.random.default_rng(seed)
    P, up, down = simulate_axis(cfg, rng)
    w = fit(cfg, P, up, down, with_instrument=True)
    wo = fit(cfg, P, up, down, with_instrument=False)
    grid = np.linspace(P[0], P[-1], 201)
    rows = []
    for name, which in (("eq. 11 (down)", "down"), ("eq. 12 (up)", "up")):
        aw, cw = w.raw(which)
        ao, co = wo.raw(which)
        uw, uo = np.sqrt(np.diag(cw)), np.sqrt(np.diag(co))
        rows.append({"curve": name,
                     "dcurve": 1e3 * float(np.max(np.abs(w.value(grid, which)
                                                          - wo.value(grid, which)))),
                     "ua": f"{1e3 * uo[0]:.3f} / {1e3 * uw[0]:.3f}",
                     "ub": float(np.max(np.abs(uw[1:] / uo[1:] - 1))),
                     "um": f"{1e3 * wo.std(grid, which).max():.3f} / "
                           f"{1e3 * w.std(grid, which).max():.3f}"})
    return rt.markdown(rows, ["curve", "dcurve", "ua", "ub", "um"],
                       ["curve", "largest change of the fitted curve (um)",
                        "u(a) without / with u(δ) (um)",
                        "largest relative change of u(b), u(c), u(d)",
                        "largest u(P) over the travel, without / with (um)"])


# --------------------------------------------------------------------------------------
# eq. 13


def plane_truth(cfg: dict, p, r, interaction_um: float = 0.0):
    pl = cfg["plane"]
    right, left = (np.asarray(cfg["paper"][k], float) for k in ("from_right", "from_left"))
    left = left.copy()
    left[0] = 0.0
    tp = (p - np.mean(pl["p_mm"])) / (0.5 * np.ptp(pl["p_mm"]))
    tr = (r - np.mean(pl["r_mm"])) / (0.5 * np.ptp(pl["r_mm"]))
    return _poly(right, p) + _poly(left, r) + 1e-3 * interaction_um * tp * tr


def plane_data(cfg: dict, rng, interaction_um: float = 0.0, weights: str = "per-point"):
    """(p, r, means, u_means, u_instrument) in mm. ``weights="per-point"``: u of each mean
    from its own readings (GUM-S1 type A, as volcal does by default); ``"pooled"``: one
    standard deviation pooled over every point's readings (their repeatability is the
    same everywhere), u = s_pooled / sqrt(n) with (n - 1) x points degrees of freedom."""
    pl, sm = cfg["plane"], cfg["simulation"]
    pp = np.linspace(*pl["p_mm"], int(pl["grid"][0]))
    rr = np.linspace(*pl["r_mm"], int(pl["grid"][1]))
    p, r = (a.ravel() for a in np.meshgrid(pp, rr, indexing="ij"))
    n = int(pl["cycles"])
    s = 1e-3 * float(sm["repeatability_um"])
    mpe = 1e-3 * float(sm["mpe_um"])
    x = plane_truth(cfg, p, r, interaction_um)[:, None] + rng.normal(0, s, (len(p), n)) \
        + rng.uniform(-mpe, mpe)
    from volcal.iso230_2.model import type_a_uncertainty

    if weights == "pooled":
        s_pool = np.sqrt(np.mean(np.var(x, axis=1, ddof=1)))
        u = np.full(len(p), s_pool / np.sqrt(n))
    else:
        u = type_a_uncertainty(x, 0.0, "gum-s1")
    return p, r, x.mean(axis=1), u, mpe / np.sqrt(3.0)


def plane(cfg: dict, reps: int, seed: int) -> tuple[str, str]:
    from scipy.stats import chi2 as chi2_dist

    from volcal.iso230_2.plane import fit_plane

    pl = cfg["plane"]
    rng = np.random.default_rng(seed)
    p, r, m, u, ui = plane_data(cfg, rng)
    mdl = fit_plane(p, r, m, u, degree_p=3, degree_r=3, u_instrument=ui)
    a, cov = mdl.raw()
    right, left = (np.asarray(cfg["paper"][k], float) for k in ("from_right", "from_left"))
    truth = np.r_[right[0], right[1:], left[1:]]
    names = ["a", "b1", "c1", "d1", "b2", "c2", "d2"]
    units = ["mm", "1", "1/mm", "1/mm²", "1", "1/mm", "1/mm²"]
    su = np.sqrt(np.diag(cov))
    hits = np.zeros(len(truth))
    pooled_hits = np.zeros(len(truth))
    for _ in range(reps):
        state = rng.bit_generator.state
        f = fit_plane(*plane_data(cfg, rng)[:4], degree_p=3, degree_r=3, u_instrument=ui)
        ak, ck = f.raw()
        hits += np.abs(ak - truth) <= 2 * np.sqrt(np.diag(ck))
        # the same readings weighted by one pooled variance: separates the cost of weights
        # estimated point by point from 5 cycles (weights that scatter with the readings)
        # from everything else in the fit
        rng.bit_generator.state = state
        g = fit_plane(*plane_data(cfg, rng, weights="pooled")[:4], degree_p=3, degree_r=3,
                      u_instrument=ui)
        ag, cg = g.raw()
        pooled_hits += np.abs(ag - truth) <= 2 * np.sqrt(np.diag(cg))
    coef_rows = [{"key": f"{n} ({un})", "truth": _g(t), "fit": _g(v), "U": _g(2 * s),
                  "z": f"{(v - t) / s:+.2f}", "cov": f"{100 * h / reps:.1f}",
                  "pool": f"{100 * hp / reps:.1f}"}
                 for n, un, t, v, s, h, hp in zip(names, units, truth, a, su, hits, pooled_hits)]
    coef_tab = rt.markdown(coef_rows, ["key", "truth", "fit", "U", "z", "cov", "pool"],
                           ["eq. 13 coefficient", "truth (eq. 11 in P, eq. 12 in R)",
                            "volcal fit_plane (one data set)", "U (k = 2)", "(fit - truth) / u",
                            "coverage of ±U over the data sets, %",
                            "coverage with one pooled variance for every point, %"])
    # adequacy: chi-square test of the no-interaction model, without / with a P R term
    rows = []
    kappa = float(pl["interaction_um"])
    for label, amp in (("no interaction (eq. 13 holds)", 0.0),
                       (f"P R term of {kappa:g} um at the corners", kappa)):
        rej, c2, err = 0, [], []
        for _ in range(reps):
            p, r, m, u, ui = plane_data(cfg, rng, amp)
            f = fit_plane(p, r, m, u, degree_p=3, degree_r=3, u_instrument=ui)
            c2.append(f.chi2 / f.dof)
            rej += f.chi2 > chi2_dist.ppf(0.95, f.dof)
            e = np.abs(f.value(p, r) - plane_truth(cfg, p, r, amp))
            err.append(float(np.max(e / f.expanded(p, r))))
        rows.append({"case": label, "c2": float(np.mean(c2)), "rej": 100.0 * rej / reps,
                     "cover": 100.0 * float(np.mean(np.asarray(err) <= 1.0))})
    adeq = rt.markdown(rows, ["case", "c2", "rej", "cover"],
                       ["truth", "mean chi2 / dof", "rejected at 5 % (%)",
                        "fit within ±U(P) at every grid point, % of data sets"])
    return coef_tab, adeq


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true",
                    help="fewer repetitions, into a temporary folder unless --out is given")
    ap.add_argument("--out", type=Path, default=None,
                    help="results folder (default studies/paper003/results)")
    ap.add_argument("--config", type=Path, default=HERE / "config.toml")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the printed tables into README.md's marked tables")
    args = ap.parse_args(argv)
    cfg = tomllib.loads(args.config.read_text(encoding="utf-8"))
    out = rt.output_folder(args.out, args.smoke, HERE / "results", "paper003")
    out.mkdir(parents=True, exist_ok=True)
    sm, pl = cfg["simulation"], cfg["plane"]
    reps = int(sm["smoke_repetitions" if args.smoke else "repetitions"])
    preps = int(pl["smoke_repetitions" if args.smoke else "repetitions"])
    seed = int(sm["seed"])
    t0 = time.perf_counter()
    rows, extra = regression(cfg, reps, seed)
    tables = {"regression": regression_table(rows),
              "curves": curves_table(cfg, extra),
              "instrument": instrument_table(cfg, seed)}
    tables["plane"], tables["plane_adequacy"] = plane(cfg, preps, seed + 1)
    tables["runinfo"] = rt.markdown(
        [{"part": "axis data sets (eq. 11-12)", "n": reps},
         {"part": "plane data sets per case (eq. 13)", "n": preps},
         {"part": "seconds", "n": f"{time.perf_counter() - t0:.1f}"}],
        ["part", "n"], ["part", "n"])
    rt.write_tables(out, tables)
    rt.print_and_publish(
        tables, f"\nresults in {out}", HERE / "README.md", args.update_readme, args.smoke
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
