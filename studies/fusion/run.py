"""Study: what each instrument adds to a tracker measurement at equal measuring time
(issue 32: tracker, laser interferometer and ballbar identified as one problem).

Data come from the independent rigid-body simulator of the test suite (tests/indep_sim.py:
exact transforms, a cubic truth that satisfies no datum, paper 002's noise for the
tracker) with interferometer lines and ballbar circles read on the same true machine
(tests/fusion_sim.py: 0.05 um per interferometer reading, 0.5 um per ballbar reading,
misaligned beams, off-centre balls).  Measuring time is counted in set-ups: a tracker
station (64 poses x 2 tool offsets), an interferometer set-up (lines along X, Y and Z,
11 targets each) and a ballbar set-up (circles in XY, YZ and ZX, 24 angles each) each cost
one unit, five units per combination:

* tracker only: 5 stations;
* tracker + interferometer: 4 stations and the lines;
* tracker + ballbar: 4 stations and the circles;
* all three: 3 stations, the lines and the circles.

Reported per combination (mean over the seeds): the field error (identified minus true
volumetric error, RMS over the tracker's poses after removing the rigid motion no
multilateration sees), the field uncertainty (RMS of the predicted standard uncertainty
of the volumetric error, |u| over dx, dy, dz), the positioning error and its uncertainty
along the interferometer's lines (each line's mean removed, relative to its first target),
the number of unidentifiable parameters and chi2/dof.  Run ``python studies/fusion/run.py``
(full: 3 seeds; ``--update-readme`` copies the table into this study's README and the
project README) or ``--smoke`` (one seed).  Writes results.csv and tables.md next to this
file (or to ``--out``).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests"))
sys.path.insert(0, str(HERE.parent))

import fusion_sim as fs  # noqa: E402  (the independent simulators live with the tests)
import indep_sim as ind  # noqa: E402
from volcal.analysis.identify import field_jacobian  # noqa: E402
from volcal.measurement.tables import DataWarning  # noqa: E402
from volcal.workflow import identify  # noqa: E402

MODEL = "mcv754_wxyzt"
TOOLS = np.array([[0.0, 0.0, 100.0], [0.0, 80.0, 150.0]])
CENTRE = {"X": 377.0, "Y": 250.0, "Z": -275.0}
LINES = [
    ("X", {"Y": 250.0, "Z": -275.0}),
    ("Y", {"X": 377.0, "Z": -275.0}),
    ("Z", {"X": 377.0, "Y": 250.0}),
]
CIRCLES = [("XY", CENTRE, 150.0), ("YZ", CENTRE, 150.0), ("ZX", CENTRE, 150.0)]
COMBOS = {
    "tracker only": (5, False, False),
    "tracker + interferometer": (4, True, False),
    "tracker + ballbar": (4, False, True),
    "all three": (3, True, True),
}


def _line_figures(res, geom, truth, ifm) -> tuple[float, float]:
    """(error, uncertainty) um of the positioning along the interferometer's lines."""
    axes = [f"{a.name}_mm" for a in geom.axes]
    q = geom.to_internal(ifm[axes].to_numpy(float))
    t = ifm[["tool_x_mm", "tool_y_mm", "tool_z_mm"]].to_numpy(float)
    pred = res.predict(q, t, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    true = ind.true_error_um(geom, truth, q, t)
    P0, _, G = field_jacobian(res.machine, res.error_model, res.theta, q, t)
    C = np.nan_to_num(res.cov_theta)
    err, var = [], []
    for _, rows in ifm.groupby("setup").indices.items():
        u = P0[rows[-1]] - P0[rows[0]]
        u = u / np.linalg.norm(u)
        d = (pred[rows] - true[rows]) @ u
        err.append(d - d.mean())
        g = np.einsum("i,nij->nj", u, G[rows] - G[rows[0]])
        var.append(np.einsum("nj,jk,nk->n", g, C, g))
    return (
        float(np.sqrt(np.mean(np.concatenate(err) ** 2))),
        float(np.sqrt(np.mean(np.concatenate(var)))) * 1e3,
    )


def one(seed: int) -> list[dict]:
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(seed)
    truth = ind.draw_truth(geom, rng, "representable")
    trk = fs.tracker_readings(geom, truth, TOOLS, rng, n_stations=5)
    ifm = fs.interferometer_lines(geom, truth, LINES, rng)
    bb = fs.ballbar_circles(geom, truth, CIRCLES, rng)
    q, t = ind.measurement_arrays(geom, trk)
    true = ind.true_error_um(geom, truth, q, t)
    P0 = ind.tool_points(geom, q, t)
    rows = []
    for name, (n_st, with_ifm, with_bb) in COMBOS.items():
        keep = trk["station"].isin([f"S{k + 1}" for k in range(n_st)])
        data: list = [trk.loc[keep].reset_index(drop=True)]
        if with_ifm:
            data.append(("interferometer", ifm))
        if with_bb:
            data.append(("ballbar", bb))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DataWarning)
            res = identify(MODEL, data, degree=3)
        pred = res.predict(q, t)
        field = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
        u = pred[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()
        line_err, line_u = _line_figures(res, geom, truth, ifm)
        rows.append(
            {
                "seed": seed,
                "combination": name,
                "readings": len(res.residuals),
                "field_error_um": ind.field_error_modulo_gauge(field, true, P0),
                "field_u_um": float(np.sqrt(np.nanmean(np.sum(u**2, axis=1)))),
                "line_error_um": line_err,
                "line_u_um": line_u,
                "unidentifiable": int((~np.asarray(res.identifiable)).sum()),
                "chi2_per_dof": res.conditions["chi2_per_dof"],
                "success": res.success,
            }
        )
        figures = list(rows[-1].items())[2:-1]
        print(f"seed {seed} {name}: " + ", ".join(f"{k} {v:.3g}" for k, v in figures))
    return rows


def results_table(res: pd.DataFrame) -> str:
    """The README's fusion_gain table: per combination, the mean over the seeds of
    ``res`` (results.csv)."""
    from readme_tables import markdown

    cols = [
        "readings",
        "field_error_um",
        "field_u_um",
        "line_error_um",
        "line_u_um",
        "unidentifiable",
        "chi2_per_dof",
    ]
    mean = res.groupby("combination", sort=False)[cols].mean().reset_index()
    mean["readings"] = mean["readings"].round().astype(int)
    mean["unidentifiable"] = mean["unidentifiable"].round().astype(int)
    table = markdown(
        mean.to_dict(orient="records"),
        ["combination", *cols],
        [
            "combination (5 set-ups)",
            "readings",
            "field error (um)",
            "field u (um)",
            "line error (um)",
            "line u (um)",
            "unidentifiable",
            "chi2/dof",
        ],
    )
    return table


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="one seed")
    ap.add_argument("--seeds", type=int, default=3, help="number of seeds (default 3)")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: this folder; --smoke: a temporary folder)",
    )
    ap.add_argument(
        "--update-readme",
        action="store_true",
        help="copy the table into this study's README and the project README",
    )
    a = ap.parse_args(argv)
    from readme_tables import output_folder, update_readme, write_tables

    out = output_folder(a.out, a.smoke, HERE, "fusion")
    seeds = [1] if a.smoke else list(range(1, a.seeds + 1))
    res = pd.DataFrame([r for s in seeds for r in one(s)])
    out.mkdir(parents=True, exist_ok=True)
    res.to_csv(out / "results.csv", index=False)
    table = results_table(res)
    write_tables(out, {"fusion_gain": table})
    if a.update_readme and not a.smoke:
        for readme in (HERE / "README.md", HERE.parents[1] / "README.md"):
            update_readme(readme, {"fusion_gain": table})
    print(f"\nmean over {len(seeds)} seed(s):\n{table}\nresults in {out}")
    return res


if __name__ == "__main__":
    main()
