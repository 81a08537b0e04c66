"""Study: what the datum does to the identified error field, before and after the minimal
datum (issue: "the identified error field must be right on data volcal did not generate").

Data come from the independent rigid-body simulator of the test suite (tests/indep_sim.py:
exact homogeneous transforms, error motions that satisfy no datum, paper 002's noise), on
the MCV 754 travel with one and with four tool offsets.  For every datum option the field
error (identified minus true volumetric error, RMS over a grid at the measured tool offsets,
after removing the rigid motion no multilateration sees) is reported for

* ``impose-all``: every ISO 230 condition imposed regardless of the data (the behaviour
  before the minimal datum), and
* ``minimal``: only the candidate conditions that remove a null direction of the full
  Jacobian (the default),

together with chi2/dof, how many conditions were imposed, and the plain scipy
least-squares reference fit.  Run ``python studies/datum/run.py`` (full: 5 seeds) or
``--smoke`` (one seed, used by the tests).  Writes results.csv next to this file (or to
``--out``) and the README's table (:func:`results_table`) as tables.json / tables.md beside
it; ``--update-readme`` copies the table into README.md, ``--table-from CSV`` prints it from
a finished run's results.csv without computing.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests"))

import indep_sim as ind  # noqa: E402  (the independent simulator lives with the tests)
from volcal.analysis.identify import identify  # noqa: E402
from volcal.model.errors import ErrorForm, ErrorModel  # noqa: E402
from volcal.model.machine import Machine  # noqa: E402

TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0], [0.0, 80.0, 60.0]])
MODEL = "mcv754_wxyzt"


def one(seed: int, n_tools: int) -> list[dict]:
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(seed)
    truth = ind.draw_truth(geom, rng, "representable")
    tools = TOOLS[:n_tools]
    plan = np.vstack([ind.grid(geom, {"X": 4, "Y": 4, "Z": 4}), ind.diagonals(geom, 6)])
    sim = ind.simulate(geom, truth, plan, tools, rng)
    q = geom.to_internal(ind.grid(geom, {"X": 5, "Y": 5, "Z": 5}))
    Q, T = np.repeat(q, len(tools), axis=0), np.tile(tools, (len(q), 1))
    true_um = ind.true_error_um(geom, truth, Q, T)
    nominal = ind.tool_points(geom, Q, T)
    machine = Machine.from_model(MODEL)
    rows = []
    ref = ind.reference_fit(machine, ErrorModel(machine.spec), sim.measurements,
                            sim.stations_start, sim.sigma_mm)
    ref_field = ind.field_error_modulo_gauge(
        ind.reference_field_um(machine, ErrorModel(machine.spec), ref.theta, Q, T),
        true_um, nominal)
    for datum in ("iso230", "reference", "none"):
        for mode in ("impose-all", "minimal"):
            if datum == "none" and mode == "impose-all":
                continue
            em = ErrorModel(machine.spec, default=ErrorForm("poly", 3), datum=datum)
            res = identify(machine, sim.measurements, sim.stations_start, error_model=em,
                           datum_mode=mode)
            pred = res.predict(Q, T, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]]
            rows.append({
                "seed": seed, "tool_offsets": n_tools, "datum": datum, "mode": mode,
                "field_error_um": ind.field_error_modulo_gauge(pred.to_numpy(), true_um,
                                                               nominal),
                "residual_rms_um": res.residual_rms_um,
                "chi2_per_dof": res.conditions["chi2_per_dof"],
                "conditions_imposed": int(res.datum["imposed"].sum()) if len(res.datum) else 0,
                "conditions_candidates": int(len(res.datum)),
                "null_directions_gauge": res.null_space.n_gauge,
                "null_directions_unidentifiable": res.null_space.n_unidentifiable,
                "reference_fit_field_error_um": ref_field,
                "reference_fit_chi2_per_dof": ref.chi2_per_dof,
            })
    return rows


def results_table(df: pd.DataFrame) -> str:
    """The README's table: per tool offsets, datum and mode, the field error (mean / max
    over the seeds, um), chi2/dof (mean, max), the conditions imposed / candidates and the
    reference fit's field error (mean, um)."""
    import readme_tables as rt

    rows = []
    for (n, datum, mode), g in df.groupby(["tool_offsets", "datum", "mode"], sort=False):
        imp = sorted(set(g["conditions_imposed"]))
        cand = sorted(set(g["conditions_candidates"]))
        rows.append({
            "n": int(n), "datum": datum, "mode": mode,
            "field": f"{g['field_error_um'].mean():.3g} / {g['field_error_um'].max():.3g}",
            "chi2": f"{g['chi2_per_dof'].mean():.3g} (max {g['chi2_per_dof'].max():.3g})",
            "cond": f"{'-'.join(map(str, imp))} / {'-'.join(map(str, cand))}",
            "ref": f"{g['reference_fit_field_error_um'].mean():.3g}",
            "seeds": g["seed"].nunique()})
    return rt.markdown(rows, ["n", "datum", "mode", "field", "chi2", "cond", "ref", "seeds"],
                       ["tool offsets", "datum", "mode", "field error um, mean / max",
                        "chi2/dof, mean (max)", "conditions imposed / candidates",
                        "reference fit um, mean", "seeds"])


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="one seed (for the tests)")
    ap.add_argument("--seeds", type=int, default=5, help="number of seeds (default 5)")
    ap.add_argument("--out", type=Path, default=None,
                    help="CSV to write (default results.csv here; --smoke: a temporary folder)")
    ap.add_argument("--update-readme", action="store_true",
                    help="copy the results table into README.md (not with --smoke)")
    ap.add_argument("--table-from", type=Path, default=None, metavar="CSV",
                    help="print (with --update-readme: write) the table of a finished run's "
                         "results.csv; compute nothing")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(HERE.parent))
    import readme_tables as rt
    from readme_tables import output_folder

    if a.table_from is not None:
        df = pd.read_csv(a.table_from)
        tab = results_table(df)
        print(tab)
        if a.update_readme:
            rt.update_readme(HERE / "README.md", {"results": tab})
        return df
    if a.update_readme and a.smoke:
        raise SystemExit("--update-readme with --smoke would put smoke figures in the README")

    if a.out is None:   # a smoke run never writes into the repository
        a.out = (output_folder(None, True, HERE, "datum") / "results.csv" if a.smoke
                 else HERE / "results.csv")
    seeds = [1] if a.smoke else list(range(1, a.seeds + 1))
    rows = [r for s in seeds for n in (1, 4) for r in one(s, n)]
    df = pd.DataFrame(rows)
    summary = (df.groupby(["tool_offsets", "datum", "mode"], sort=False)
               [["field_error_um", "chi2_per_dof", "conditions_imposed",
                 "reference_fit_field_error_um"]].mean())
    print(summary.to_string(float_format=lambda v: f"{v:.3g}"))
    tmp = a.out.with_suffix(".tmp")
    df.to_csv(tmp, index=False)
    tmp.replace(a.out)
    tab = results_table(df)
    rt.write_tables(a.out.parent, {"results": tab})
    print(f"\n{tab}\nresults in {a.out}")
    if a.update_readme:
        rt.update_readme(HERE / "README.md", {"results": tab})
    return df


if __name__ == "__main__":
    main()
