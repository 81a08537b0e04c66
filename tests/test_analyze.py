"""``volcal analyze``: rank, conditioning, named unidentifiable directions with tested
explanations, covariance and correlations, for plans and for identification results."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from volcal.base.threads import blas_threads
from volcal.outputs.analysis_report import analyze_plan, analyze_result


@pytest.fixture(scope="module")
def ex():
    from volcal.measurement.simulate import example
    return example("mcv754")


def _plan(ex, tools, plan=None):
    with blas_threads(1):
        return analyze_plan(ex.machine, ex.plan if plan is None else plan, ex.stations,
                            tools, ex.budget, error_model=ex.error_model)


def test_single_tool_offset_names_the_unseen_error_motions(ex):
    rep = _plan(ex, np.zeros((1, 3)))
    gauge = [d for d in rep.null if d.kind == "gauge"]
    assert len(gauge) == 1 and gauge[0].dimension == 6
    unid = rep.unidentifiable_errors
    assert len(unid) == 1, [d.line() for d in unid]
    d = unid[0]
    # with the reflector always at the spindle reference point: the angular motions of Z
    # and the yaw of Y have no lever arm (3 free coefficients each after the datum)
    assert d.kind == "error" and d.text.startswith("ECY, EAZ, EBZ, ECZ")
    assert d.dimension == 12
    assert "no tool offset variation" in d.explanation
    assert rep.rank == 81 - 6 - 12
    text = rep.summary()
    assert "ECY, EAZ, EBZ, ECZ (whole error motions): no tool offset variation" in text
    par = rep.parameters()
    unseen = par.loc[~par["identifiable"] & (par["kind"] == "error"), "name"]
    assert sorted({n.split("_")[0] for n in unseen}) == ["EAZ", "EBZ", "ECY", "ECZ"]


def test_single_offset_along_z_leaves_named_combinations(ex):
    rep = _plan(ex, np.array([[0.0, 0.0, -100.0]]))
    unid = rep.unidentifiable_errors
    whole = [d for d in unid if d.kind == "error"]
    assert len(whole) == 1 and whole[0].text.startswith("ECY, ECZ")
    combos = [d for d in unid if d.kind == "combination"]
    # 12 directions before the tool's zero orientation was a parameter; two of them (EAZ and
    # EBZ at the reference, which a 100 mm offset along z turns into a tool orientation)
    # are now removed by the datum
    assert sum(d.dimension for d in unid) == 10
    # a 100 mm offset along z makes EAZ act like EYZ x 100 mm: "EAZ_k ... 0.1 EYZ_k"
    assert any("EAZ" in d.text and "0.1 EYZ" in d.text for d in combos), \
        [d.text for d in combos]
    assert all("no tool offset variation" in d.explanation for d in combos)


def test_enough_offsets_identify_everything(ex):
    rep = _plan(ex, ex.tools)
    assert rep.unidentifiable_errors == []
    assert rep.identifiable[:rep.n_theta].all()
    # 75 before the tool's zero orientation was a parameter: the tool offsets see it (3)
    assert rep.rank == 78
    assert 10 < rep.condition < 1e3 and rep.condition_unscaled > rep.condition
    assert rep.tol == pytest.approx(max(3576, 105) * np.finfo(float).eps *
                                    rep.singular_values[0])
    # pairs tied by the datum alone (straightness coefficients 0 and 2) are not listed
    pairs = rep.strongest_pairs(10)
    tied = {("EYX_0", "EYX_2"), ("EZX_1", "EZX_3")}
    assert not any((a, b) in tied or (b, a) in tied for a, b in zip(pairs["a"], pairs["b"]))
    assert (pairs["rho"].abs() < 1 - 1e-6).all()
    vol = rep.volumetric
    assert (vol["u_total_um"] >= 0).all() and vol["u_total_um"].max() < 2.0
    assert len(rep.weak) == 8 and all(s > rep.tol for s, _ in rep.weak)


def test_too_few_positions_for_the_polynomial_degree(ex):
    from volcal.measurement.plans import grid_plan

    plan = grid_plan(ex.machine.spec, {"X": 3, "Y": 5, "Z": 5})
    rep = _plan(ex, ex.tools, plan)
    unid = rep.unidentifiable_errors
    assert unid, "a cubic in X from 3 positions cannot be identified"
    assert all("only 3 distinct positions of axis X" in d.explanation for d in unid)
    assert all(all(n.endswith("X") or "X_" in n or n in ("EC0Y", "EB0Z") for n in d.names)
               for d in unid)


def test_result_analysis_and_residual_scaling(ex):
    from volcal.analysis.identify import identify
    from volcal.measurement.tables import load_measurements

    sim = ex.simulate(3)
    meas = load_measurements(sim.measurements, ex.machine.spec)
    with blas_threads(1):
        res = identify(ex.machine, meas, error_model=ex.error_model, budget=ex.budget)
        rep = analyze_result(res, meas, budget=ex.budget)
        rep2 = analyze_result(res, meas, budget=ex.budget, scale_covariance=True)
    nt = rep.n_theta
    # the report's covariance is the identification's
    assert np.allclose(rep.cov[:nt, :nt], res.cov_theta, rtol=1e-8, atol=1e-20)
    chi2 = res.conditions["chi2_per_dof"]
    assert rep2.cov_scale == pytest.approx(chi2)
    assert np.allclose(rep2.cov[:nt, :nt], chi2 * res.cov_theta, rtol=1e-8, atol=1e-20)
    assert rep.unidentifiable_errors == []
    # at a real solution the volumetric error is large: |d| gets its own uncertainty
    assert rep.volumetric["u_norm_um"].notna().sum() > 50


def test_analyze_command(tmp_path, capsys):
    from volcal.cli.main import main

    out = tmp_path / "an"
    assert main(["analyze", "--example", "mcv754", "--tools", "0,0,0", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ECY, EAZ, EBZ, ECZ (whole error motions): no tool offset variation" in text
    assert "condition number" in text and "numerical rank" in text
    for f in ("summary.txt", "report.md", "null_space.csv", "singular_values.csv",
              "covariance.csv", "correlation.csv", "strongest_pairs.csv",
              "volumetric_uncertainty.csv", "singular_values.png", "correlation.png",
              "uncertainty_map.png", "analysis.json"):
        assert (out / f).is_file(), f
    meta = json.loads((out / "analysis.json").read_text())
    assert meta["rank"] == 63
    ns = pd.read_csv(out / "null_space.csv")
    assert set(ns["kind"]) == {"gauge", "error"}
    # a second run replaces the previous analysis; a foreign folder is refused
    assert main(["analyze", "--example", "mcv754", "--no-plots", "--out", str(out)]) == 2
    assert main(["analyze", "--example", "mcv754", "--no-plots", "--out", str(out),
                 "--force"]) == 0
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["analyze", "--example", "mcv754", "--out", str(tmp_path / "other")]) == 2


def test_analyze_a_result_folder(ex, tmp_path, capsys):
    from volcal.cli.main import main
    from volcal.measurement.simulate import save_simulation

    save_simulation(ex.simulate(5), tmp_path / "sim")
    assert main(["identify", "--model", "mcv754_wxyzt", "--data",
                 str(tmp_path / "sim" / "measurements.csv"), "--no-plots",
                 "--out", str(tmp_path / "res")]) == 0
    capsys.readouterr()
    assert main(["analyze", "--result", str(tmp_path / "res"), "--scale-covariance",
                 "--no-plots", "--out", str(tmp_path / "an")]) == 0
    text = capsys.readouterr().out
    assert "analyze (result)" in text and "residual variance factor" in text
    # the re-identification reproduces the saved result
    assert "largest difference from the saved estimate 0 " in text
    assert "unidentifiable        none" in text
