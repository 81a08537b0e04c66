"""``volcal compare`` / ``volcal.compare``: strategies side by side.

The first test runs on data from the independent simulator (tests/indep_sim.py: exact
rigid-body chain, no volcal model code, a truth volcal did not draw and that satisfies no
datum, four tool offsets) and checks the figures of the table against that truth with the
simulator's own gauge removal: the joint fit's error against the truth agrees with
``indep_sim.field_error_modulo_gauge``, is as large as the uncertainty the comparison uses
as its unit says (the u computed modulo the gauge), and classic's bias with tool offsets
shows as a difference of many u.  Then the command on the bundled example with --truth
(the true_parameters.csv `volcal simulate` writes) and --trials, the report embedding the
comparison, the same seed giving the same trials serially, in processes and on Dask, a
5-axis model (trunnion_ac) with --truth and --trials, and bad input (exit code 2).
"""

from __future__ import annotations

import functools
import json

import numpy as np
import pandas as pd
import pytest

import indep_sim as ind
from volcal.cli.main import main
from volcal.workflow.comparison import compare, modulo_gauge, run_trials, trial_seed

TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0], [0.0, 80.0, 60.0]])


@functools.cache
def _independent():
    geom = ind.load_geometry("mcv754_wxyzt")
    rng = np.random.default_rng(31)
    truth = ind.draw_truth(geom, rng, "representable")
    plan = np.vstack([ind.grid(geom, {"X": 4, "Y": 4, "Z": 4}), ind.diagonals(geom, 5)])
    sim = ind.simulate(geom, truth, plan, TOOLS, rng)

    def true_field(q, t):
        return ind.true_error_um(geom, truth, q, t)

    cmp = compare("mcv754_wxyzt", sim.measurements, sim.stations_start, truth=true_field)
    return geom, truth, sim, cmp


def test_independent_data_table_against_the_truth():
    geom, truth, sim, cmp = _independent()
    t = cmp.table.set_index("strategy")
    assert list(t.index) == ["joint", "two-phase", "points-only", "classic"]
    assert t["success"].all()
    # the joint fit's field error against the independent truth, recomputed with the
    # independent simulator's own gauge removal (RMS over components there, of the
    # norm here: a factor sqrt(3)) at the comparison's points
    pts = cmp.points
    Q = geom.to_internal(pts[list(geom.axis_names)].to_numpy(float))
    T = pts[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
    true_um = ind.true_error_um(geom, truth, Q, T)
    pred = cmp.runs["joint"].result.predict(Q, T, with_uncertainty=False)
    pred = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
    nominal = ind.tool_points(geom, Q, T)
    rms, mx = ind.field_error_modulo_gauge(pred, true_um, nominal, return_max=True)
    assert t.loc["joint", "truth_error_rms_um"] == pytest.approx(np.sqrt(3) * rms, rel=1e-6)
    assert t.loc["joint", "truth_error_max_um"] >= mx  # a norm bounds each component
    # representable truth, noise at the budget: the joint field is right at the noise
    # floor, and its error is as large as its standard uncertainty modulo the gauge says
    assert t.loc["joint", "truth_error_rms_um"] < 0.5
    z = np.linalg.norm(cmp.truth_errors["joint"], axis=1) / pts["u_reference_um"]
    assert 0.4 < np.sqrt(np.mean(z**2)) < 2.5
    # classic with tool offsets is biased: worse against the truth, many u from joint
    assert t.loc["classic", "truth_error_rms_um"] > 3 * t.loc["joint", "truth_error_rms_um"]
    assert t.loc["classic", "field_diff_max_in_u"] > 5
    # the difference to joint is the difference of the two errors (modulo one gauge):
    # the triangle inequality in the RMS norm
    for s in ("two-phase", "points-only", "classic"):
        e_s, e_j = t.loc[s, "truth_error_rms_um"], t.loc["joint", "truth_error_rms_um"]
        assert abs(t.loc[s, "field_diff_rms_um"] - e_s) <= e_j + 1e-9
        assert t.loc[s, "points_compared"] == len(pts)
    # parameter differences in units of the reference's u, named in the table
    pdiff = cmp.parameter_differences
    top = pdiff.loc[pdiff["strategy"] == "classic"]
    worst = top.iloc[int(np.argmax(np.abs(top["difference_in_u"].to_numpy())))]
    assert worst["name"] in t.loc["classic", "largest_parameter_differences"]
    assert np.allclose(worst["difference"] / worst["u_reference"], worst["difference_in_u"])


def test_modulo_gauge_removes_exactly_a_rigid_motion():
    rng = np.random.default_rng(0)
    p = rng.uniform(-500, 500, (50, 3))
    d = rng.normal(size=(50, 3))
    a, w = rng.normal(size=3), rng.normal(size=3) * 1e-3
    moved = d + a + np.cross(w, p)
    assert np.allclose(modulo_gauge(p, moved), modulo_gauge(p, d), atol=1e-9)
    assert np.allclose(modulo_gauge(p, a + np.cross(w, p)), 0.0, atol=1e-9)


@pytest.fixture(scope="module")
def example_run(tmp_path_factory):
    """`volcal simulate` of the example (its model, true errors, stations and tool
    offsets on a coarser grid: a smoke size), then `volcal compare` with --truth and
    --trials."""
    tmp = tmp_path_factory.mktemp("cmp")
    assert main(["-q", "simulate", "--example", "mcv754", "--plan", "grid", "--grid",
                 "X=4,Y=3,Z=3", "--seed", "3", "--out", str(tmp / "sim")]) == 0
    out = tmp / "cmp"
    rc = main(["-q", "compare", "--model", "mcv754_wxyzt", "--data",
               str(tmp / "sim" / "measurements.csv"), "--truth",
               str(tmp / "sim" / "true_parameters.csv"), "--trials", "2", "--workers", "1",
               "--seed", "5", "--out", str(out)])
    return tmp, out, rc


def test_example_with_truth_and_trials(example_run):
    tmp, out, rc = example_run
    assert rc == 0
    for f in ("comparison.csv", "parameter_differences.csv", "workspace_points.csv",
              "trials.csv", "compare.md", "compare.html", "field_differences.png",
              "compare.json", "manifest.json", "reference/result.json"):
        assert (out / f).is_file(), f
    t = pd.read_csv(out / "comparison.csv").set_index("strategy")
    for c in ("residual_rms_um", "field_diff_rms_um", "field_diff_max_in_u",
              "truth_error_rms_um", "trials_error_rms_mean_um", "trials_error_rms_sd_um",
              "time_s"):
        assert c in t
    # the joint fit is at the noise floor against the simulated truth (its error as
    # large as its uncertainty says), the others are biased (paper 000: classic worst)
    assert t.loc["joint", "truth_error_rms_um"] < 1.0
    pts = pd.read_csv(out / "workspace_points.csv")
    z = pts["truth_error_joint_um"] / pts["u_reference_um"]
    assert 0.4 < np.sqrt(np.mean(z**2)) < 2.5
    assert t.loc["classic", "truth_error_rms_um"] > 5 * t.loc["joint", "truth_error_rms_um"]
    # the adequacy verdict per strategy, machine-readable with its causes: the biased
    # classic pipeline is named as such, never the budget
    assert t.loc["joint", "verdict"] == "fits"
    assert t.loc["classic", "verdict"] == "does_not_fit"
    assert t.loc["classic", "causes"].split()[0] == "strategy"
    assert "budget" not in t.loc["classic", "causes"].split()
    assert (t["trials_failed"] == 0).all()
    assert t.loc["joint", "trials_error_rms_mean_um"] < t.loc["classic", "trials_error_rms_mean_um"]
    trials = pd.read_csv(out / "trials.csv")
    assert len(trials) == 2 * 4
    assert list(trials["seed"].unique()) == [trial_seed(5, 0), trial_seed(5, 1)]
    doc = json.loads((out / "compare.json").read_text())
    assert doc["trials"] == 2 and doc["reference"] == "joint"
    md = (out / "compare.md").read_text()
    assert "| joint" in md and "error vs truth" in md
    # an earlier comparison is replaced only with --force (on a copy: later tests read out)
    import shutil

    copy = tmp / "cmp_copy"
    shutil.copytree(out, copy)
    again = ["-q", "compare", "--model", "mcv754_wxyzt", "--data",
             str(tmp / "sim" / "measurements.csv"), "--strategies", "joint", "--out", str(copy)]
    assert main(again) == 2
    assert list(pd.read_csv(copy / "comparison.csv")["strategy"]) != ["joint"]
    assert main([*again, "--force"]) == 0
    assert list(pd.read_csv(copy / "comparison.csv")["strategy"]) == ["joint"]


def test_report_embeds_the_comparison(example_run, tmp_path):
    _, out, _ = example_run
    for given in (out, out / "reference"):
        html = tmp_path / f"r_{given.name}.html"
        assert main(["-q", "report", "--result", str(given), "--no-plots", "--out",
                     str(html)]) == 0
        text = html.read_text()
        assert 'id="compare"' in text and "two-phase" in text
        assert "data:image/png;base64," in text
    # a folder that is not a comparison is refused, naming it
    from volcal.base.exceptions import InputError
    from volcal.outputs.html_report import html_report, write_report

    # never a file of a folder the report reads, also where find_comparison found it
    for given, target in ((out, out / "reference" / "result.json"),
                          (out / "reference", out / "compare.json")):
        before = target.read_bytes()
        with pytest.raises(InputError, match="would overwrite"):
            write_report(given, target, plots=False)
        assert target.read_bytes() == before

    with pytest.raises(InputError, match="volcal compare"):
        html_report(out / "reference", compare_dir=tmp_path)


@functools.cache
def _small_example():
    from volcal.measurement.plans import grid_plan
    from volcal.measurement.simulate import example, simulate

    ex = example("mcv754")
    plan = grid_plan(ex.machine.spec, {"X": 4, "Y": 3, "Z": 3})
    sim = simulate(ex.machine, ex.error_model, ex.theta_true, ex.stations, plan, ex.tools,
                   ex.budget, 8)
    # a layout that is not a full product: one station misses a tool offset
    m = sim.measurements
    keep = ~((m["station"] == m["station"].iloc[0]) & (m["tool_z"] == 0.0))
    return ex, m.loc[keep].reset_index(drop=True)


def test_same_seed_same_trials_serially_in_processes_and_on_dask(dask_client):
    ex, data = _small_example()
    cmp = compare(ex.machine, data, strategies=("joint", "classic"), error_model=ex.error_model,
                  budget=ex.budget, truth=ex.theta_true, trials=1, seed=11, workers=1,
                  true_stations=ex.stations)
    k = cmp.trial_kernel
    assert k.keep is not None and k.keep.sum() == len(data)  # the data's layout
    serial = run_trials(k, 2, workers=1)
    pd.testing.assert_frame_equal(serial.iloc[:2], cmp.trials)
    procs = run_trials(k, 2, workers=2)
    dask = run_trials(k, 2, scheduler=dask_client)
    assert serial["success"].all()
    pd.testing.assert_frame_equal(serial, procs)
    pd.testing.assert_frame_equal(serial, dask)
    # the two trials drew different noise
    a, b = (serial.loc[serial["trial"] == i, "field_error_rms_um"].to_numpy() for i in (0, 1))
    assert not np.array_equal(a, b)


def test_five_axis_with_truth_and_trials(tmp_path):
    # the default plan (linear grid plus rotary sweeps), three tool offsets
    assert main(["-q", "simulate", "--model", "trunnion_ac", "--tools",
                 "0,0,0;0,0,-100;60,0,-100", "--seed", "4", "--out", str(tmp_path / "sim")]) == 0
    out = tmp_path / "cmp"
    rc = main(["-q", "compare", "--model", "trunnion_ac", "--data",
               str(tmp_path / "sim" / "measurements.csv"), "--stations",
               str(tmp_path / "sim" / "stations.csv"), "--truth",
               str(tmp_path / "sim" / "true_parameters.csv"), "--strategies",
               "joint,classic", "--trials", "1", "--workers", "1", "--no-plots",
               "--out", str(out)])
    t = pd.read_csv(out / "comparison.csv").set_index("strategy")
    assert rc == (0 if t["success"].all() else 1)
    assert t.loc["joint", "success"]
    assert t.loc["joint", "truth_error_rms_um"] < 1.0
    assert t.loc["joint", "trials_error_rms_mean_um"] < 1.0
    # the rotary axes' errors in the comparison: points over the rotary travel
    pts = pd.read_csv(out / "workspace_points.csv")
    assert pts["A"].nunique() > 10 and pts["C"].nunique() > 10
    # where the joint fit determines the field it has an uncertainty; the classic fit is
    # compared there only
    det = pts["u_reference_um"].notna()
    assert det.mean() > 0.9 and (pts.loc[det, "u_reference_um"] > 0).all()
    assert t.loc["classic", "points_compared"] == det.sum()
    # classic's bias on a 5-axis machine: worse than joint against the truth
    assert t.loc["classic", "truth_error_rms_um"] > 3 * t.loc["joint", "truth_error_rms_um"]


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--strategies", "joint,foo"], "--strategies"),
        (["--strategies", "joint,classic", "--reference", "two-phase"], "--reference"),
        (["--trials", "-1"], "--trials"),
    ],
)
def test_bad_options_exit_2(tmp_path, capsys, args, needle):
    rc = main(["compare", "--example", "mcv754", *args, "--out", str(tmp_path / "o")])
    assert rc == 2
    assert needle in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_bad_truth_file_names_file_row_and_column(tmp_path, capsys):
    bad = tmp_path / "truth.csv"
    bad.write_text("name,value,unit\nEXX_1,2.0,um\nEXQ_9,1.0,um\n")
    rc = main(["compare", "--example", "mcv754", "--strategies", "joint", "--truth",
               str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "truth.csv" in err and "row 3" in err and "EXQ_9" in err
    assert not (tmp_path / "o").exists()


def test_a_failed_strategy_is_reported_and_the_others_compared(monkeypatch, tmp_path):
    """A strategy whose solver fails gets its status in the table, no figures, and the
    command's exit code 1; the other strategies are still compared and written."""
    import volcal.workflow.comparison as mod
    from volcal.base.exceptions import SolverError
    from volcal.outputs.compare_report import format_table, write_comparison

    real = mod.identify

    def failing(*args, strategy="joint", **kw):
        if strategy == "two-phase":
            raise SolverError("did not converge after 3000 iterations",
                              status="Maximum_Iterations_Exceeded")
        return real(*args, strategy=strategy, **kw)

    monkeypatch.setattr(mod, "identify", failing)
    ex, data = _small_example()
    cmp = compare(ex.machine, data, strategies=("joint", "two-phase", "classic"),
                  error_model=ex.error_model, budget=ex.budget)
    t = cmp.table.set_index("strategy")
    assert not cmp.success
    assert not t.loc["two-phase", "success"]
    assert t.loc["two-phase", "status"] == "Maximum_Iterations_Exceeded"
    assert np.isnan(t.loc["two-phase", "field_diff_rms_um"])
    assert t.loc["classic", "success"] and t.loc["classic", "field_diff_rms_um"] > 0
    assert "FAILED (Maximum_Iterations_Exceeded)" in format_table(cmp.table, "joint")
    out = write_comparison(cmp, tmp_path / "c", plots=True)
    assert (out / "field_differences.png").is_file()
    back = pd.read_csv(out / "comparison.csv").set_index("strategy")
    assert not back.loc["two-phase", "success"]


def test_trials_draw_every_repeat_of_a_reading():
    """Data that measure every reading twice: each trial simulates both, with their own
    noise (their differences scatter as sqrt(2) times the reading's standard
    uncertainty), not one reading standing for both."""
    from volcal.measurement.budget import load_budget
    from volcal.measurement.simulate import example
    from volcal.measurement.tables import load_measurements, load_stations
    from volcal.workflow.comparison import TrialKernel

    ex = example("mcv754")
    sim = ex.simulate()
    spec = ex.machine.spec
    again = sim.measurements.iloc[::3].copy()
    again["point"] = again["point"] + "r"  # repeats carry their own point ids
    data = pd.concat([sim.measurements, again], ignore_index=True)
    meas = load_measurements(data, spec, stations=load_stations(sim.stations))
    kernel = TrialKernel.from_data(
        ex.machine, ex.error_model, load_budget(ex.budget), meas, None,
        load_stations(sim.stations), ex.theta_true, ["joint"],
        np.zeros((1, len(spec.axes))), np.zeros((1, 3)), np.ones(1, bool), seed=3,
    )
    got = kernel.simulated(0)
    key = ["station", *spec.axis_names, "tool_x", "tool_y", "tool_z"]
    assert len(got) == len(data)
    want = data.groupby(key).size().sort_index()
    assert got.groupby(key).size().sort_index().equals(want)
    pairs = got[got.duplicated(key, keep=False)].sort_values(key)
    a, b = pairs.iloc[0::2], pairs.iloc[1::2]
    z = (a["length"].to_numpy() - b["length"].to_numpy()) / (np.sqrt(2) * a["sigma"].to_numpy())
    assert len(z) == len(sim.measurements.iloc[::3])
    assert 0.85 < np.std(z) < 1.15, np.std(z)
