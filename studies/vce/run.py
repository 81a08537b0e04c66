"""Study: are the variance components' 95 % intervals and the per-table verdicts true?
(issue 32: ``volcal identify --data ... --variance-components``.)

Data come from the independent rigid-body simulator of the test suite (tests/indep_sim.py:
exact transforms, a cubic truth that satisfies no datum, paper 002's noise for the
tracker) with laser interferometer lines read on the same true machine
(tests/fusion_sim.py: 0.05 um per reading, misaligned beams, unknown dead paths): a
tracker table of 4 stations x 4x4x4 poses x 2 tool offsets (512 readings) and an
interferometer table of 3 lines (X, Y, Z) x 11 targets (33 readings), the set-up of
tests/test_fusion.py.  Every seed draws a new truth, new station positions and new noise.

Three budget scenarios per seed, each identified with ``variance_components=True``
(degree 3):

* ``correct``: both tables' sigma as simulated (true scale factors 1 and 1);
* ``interferometer 2x``: the interferometer's table claims twice its real precision
  (sigma halved: its true scale factor is 2);
* ``tracker 2x``: the same for the tracker's table.

Measured per table and scenario: how often the 95 % interval of the scale factor holds
the true factor (coverage, with its 95 % binomial interval, Clopper-Pearson), for the
interval volcal reports (chi2 with Satterthwaite's degrees of freedom from REML's
information, ``dof_vce``) and for the one it reported before (chi2 with the table's
redundancy number r_i, ``dof``: ``factor * sqrt(r / chi2_q(r))``, recomputed here from the
same fits); the mean estimated factor; and the rate at which the per-table check with the
budgets as given (``verdict_given``, 99.9 % interval: nominal 0.1 % false alarms) says
``too large`` / not ``fits``, with the interval volcal uses (Satterthwaite, ``dof_check``)
and the one before (chi2 with r_i).

``python studies/vce/run.py`` (full: 200 seeds; ``--update-readme`` copies the table into
this study's README) or ``--smoke`` (1 seed, into a temporary folder).  Writes
results.csv (one row per seed, scenario and table) and tables.md next to this file (or to
``--out``); ``--table-from results.csv`` prints the table of a finished run.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import beta, chi2

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests"))
sys.path.insert(0, str(HERE.parent))

import fusion_sim as fs  # noqa: E402  (the independent simulators live with the tests)
import indep_sim as ind  # noqa: E402
from volcal.base.progress import counter  # noqa: E402
from volcal.measurement.tables import DataWarning  # noqa: E402
from volcal.model.machine import Machine  # noqa: E402
from volcal.model.spec import resolve_model  # noqa: E402
from volcal.workflow import identify  # noqa: E402

MODEL = "mcv754_wxyzt"
TOOLS = np.array([[0.0, 0.0, 100.0], [0.0, 80.0, 150.0]])
LINES = [
    ("X", {"Y": 250.0, "Z": -275.0}),
    ("Y", {"X": 377.0, "Z": -275.0}),
    ("Z", {"X": 377.0, "Y": 250.0}),
]
#: scenario: (the table whose sigma is halved, or None)
SCENARIOS = {"correct": None, "interferometer 2x": "interferometer", "tracker 2x": "tracker"}


def tables(seed: int) -> dict[str, pd.DataFrame]:
    """The tracker's and the interferometer's tables of one seed (correct sigma)."""
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(seed)
    truth = ind.draw_truth(geom, rng, "representable")
    trk = fs.tracker_readings(geom, truth, TOOLS, rng, n_stations=4)
    ifm = fs.interferometer_lines(geom, truth, LINES, rng)
    return {"tracker": trk, "interferometer": ifm}


def one(seed: int, machine: Machine) -> list[dict]:
    """Every scenario of one seed: one row per table."""
    d = tables(seed)
    rows = []
    for scenario, wrong in SCENARIOS.items():
        trk, ifm = d["tracker"].copy(), d["interferometer"].copy()
        if wrong == "tracker":
            trk["sigma"] = trk["sigma"] / 2
        elif wrong == "interferometer":
            ifm["sigma_um"] = ifm["sigma_um"] / 2
        data = [("tracker", trk, None, "tracker"), ("interferometer", ifm, None, "interferometer")]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            res = identify(machine, data, degree=3, variance_components=True)
        fit = res.instruments
        for _, r in fit.iterrows():
            rows.append(
                {
                    "seed": seed,
                    "scenario": scenario,
                    "table": r["instrument"],
                    "true_scale": 2.0 if r["instrument"] == wrong else 1.0,
                    "n_readings": int(r["n_readings"]),
                    "dof": r["dof"],
                    "dof_check": r["dof_check"],
                    "dof_vce": r["dof_vce"],
                    "chi2_per_dof_given": r["chi2_per_dof_given"],
                    "verdict_given": r["verdict_given"],
                    "scale_factor": r["scale_factor"],
                    "scale_low_95": r["scale_low_95"],
                    "scale_high_95": r["scale_high_95"],
                    "success": bool(res.success),
                }
            )
    return rows


def _binomial(k: int, n: int) -> tuple[float, float]:
    """Clopper-Pearson 95 % interval of a rate k/n."""
    lo = beta.ppf(0.025, k, n - k + 1) if k > 0 else 0.0
    hi = beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return float(lo), float(hi)


def _rate(hits: np.ndarray) -> str:
    k, n = int(np.sum(hits)), len(hits)
    lo, hi = _binomial(k, n)
    return f"{k / n:.3f} ({lo:.3f}-{hi:.3f})"


def summary(res: pd.DataFrame) -> pd.DataFrame:
    """Per scenario and table: coverage of the 95 % intervals (volcal's and the one
    before), the mean factor, and the rates of the per-table check with the budgets as
    given (volcal's interval and chi2 with r_i)."""
    out = []
    for (scenario, table), g in res.groupby(["scenario", "table"], sort=False):
        s, f = g["true_scale"].to_numpy(float), g["scale_factor"].to_numpy(float)
        r = g["dof"].to_numpy(float)
        # the interval volcal reported before: chi2 with the redundancy number r_i
        lo_r = f * np.sqrt(r / chi2.ppf(0.975, r))
        hi_r = f * np.sqrt(r / chi2.ppf(0.025, r))
        lo, hi = g["scale_low_95"].to_numpy(float), g["scale_high_95"].to_numpy(float)
        c = g["chi2_per_dof_given"].to_numpy(float)
        flag = (g["verdict_given"] != "fits").to_numpy()
        flag_r = (c < chi2.ppf(0.0005, r) / r) | (c > chi2.ppf(0.9995, r) / r)
        out.append(
            {
                "scenario": scenario,
                "table": table,
                "seeds": len(g),
                "readings": int(g["n_readings"].iloc[0]),
                "r": float(np.mean(r)),
                "nu": float(g["dof_vce"].mean()),
                "true": float(s[0]),
                "mean factor": float(np.mean(f)),
                "coverage": _rate((lo <= s) & (s <= hi)),
                "coverage (chi2 on r)": _rate((lo_r <= s) & (s <= hi_r)),
                "check flags": _rate(flag),
                "check flags (chi2 on r)": _rate(flag_r),
            }
        )
    return pd.DataFrame(out)


def results_table(res: pd.DataFrame) -> str:
    """The README's ``vce`` table from results.csv."""
    from readme_tables import markdown

    summ = summary(res)
    cols = list(summ.columns)
    heads = [
        "scenario",
        "table",
        "seeds",
        "readings",
        "r_i (mean)",
        "nu_i (mean)",
        "true factor",
        "mean factor",
        "coverage of the 95 % interval (95 % CI)",
        "same, chi2 on r_i (before)",
        "check not `fits` (99.9 %)",
        "same, chi2 on r_i (before)",
    ]
    return markdown(summ.to_dict(orient="records"), cols, heads)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="1 seed")
    ap.add_argument("--seeds", type=int, default=200, help="number of seeds (default 200)")
    ap.add_argument("--first-seed", type=int, default=1, help="first seed (default 1)")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: this folder; --smoke: a temporary folder)",
    )
    ap.add_argument(
        "--update-readme", action="store_true", help="copy the table into this study's README"
    )
    ap.add_argument(
        "--table-from",
        type=Path,
        default=None,
        help="print the table of a finished run's results.csv and compute nothing",
    )
    a = ap.parse_args(argv)
    from readme_tables import output_folder, update_readme, write_tables

    if a.table_from is not None:
        print(results_table(pd.read_csv(a.table_from)))
        return 0
    out = output_folder(a.out, a.smoke, HERE, "vce")
    n = 1 if a.smoke else a.seeds
    seeds = list(range(a.first_seed, a.first_seed + n))
    machine = Machine.from_model(resolve_model(MODEL))
    t0 = time.perf_counter()
    rows = []
    with counter(len(seeds), "seeds", "seed", on=True) as bar:
        for s in seeds:
            rows += one(s, machine)
            bar.update(1)
    res = pd.DataFrame(rows)
    out.mkdir(parents=True, exist_ok=True)
    res.to_csv(out / "results.csv", index=False)
    table = results_table(res)
    write_tables(out, {"vce": table})
    if a.update_readme and not a.smoke:
        update_readme(HERE / "README.md", {"vce": table})
    print(f"\n{len(seeds)} seed(s), {time.perf_counter() - t0:.0f} s:\n{table}\nresults in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
