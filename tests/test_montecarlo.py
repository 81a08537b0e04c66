"""Monte Carlo uncertainty: the structured re-solver against IPOPT, linearised against
Monte Carlo uncertainties, determinism across workers and on Dask, resuming, source
contributions, the evaluation factor E_n and the ``volcal mc`` command."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from volcal.analysis.uncertainty.evaluation import compare_with_reference, evaluation_factor
from volcal.analysis.uncertainty.montecarlo import (
    contributions,
    monte_carlo,
    quantity_table,
    run_trials,
    verify_against_ipopt,
)
from volcal.base.threads import blas_threads


@pytest.fixture(scope="module")
def example_mc():
    """The bundled example identified once, with a 2000-trial nonlinear Monte Carlo."""
    from volcal.measurement.simulate import example

    ex = example("mcv754")
    sim = ex.simulate()
    with blas_threads(1):
        out = monte_carlo(ex.machine, sim.measurements, budget=ex.budget,
                          error_model=ex.error_model, trials=2000, seed=11, workers=1)
    out["example"] = ex
    return out


def test_structured_solver_is_the_nonlinear_minimiser(example_mc):
    # the same trials solved by IPOPT on the identification's own NLP (tight tolerance)
    ver = verify_against_ipopt(example_mc["kernel"], example_mc["identifier"],
                               example_mc["p"], seed=11, trials=[0, 1, 2])
    assert ver["theta_rel"] < 1e-9, ver
    assert ver["max_abs_scaled"] < 1e-8, ver      # 1e-8 um / urad
    s = example_mc["mc"].samples
    assert s.converged.all()
    assert s.iterations.max() <= 5


def test_linearised_and_monte_carlo_uncertainties_agree_within_10_percent(example_mc):
    mc = example_mc["mc"]
    ag = mc.agreement()
    # 2000 trials: the MC standard deviation itself scatters by ~1.6 % (1 sigma)
    assert ag["parameters_max_rel_diff"] < 0.10, ag
    assert ag["volumetric_max_rel_diff"] < 0.10, ag
    assert abs(ag["parameters_median_ratio"] - 1) < 0.03, ag
    # the linearised covariance from the kernel is the identification's own covariance
    res = example_mc["result"]
    nt = len(res.theta)
    u_id = np.sqrt(np.diag(res.cov_theta))
    u_k = np.sqrt(np.diag(mc.cov_linear)[:nt])
    assert np.allclose(u_k, u_id, rtol=1e-6)


def test_estimates_intervals_and_expanded_uncertainty(example_mc):
    mc = example_mc["mc"]
    par = mc.parameters()
    assert np.allclose(par["U"], 2 * par["u"])
    # parameters the datum holds exactly (the tool's zero position) have u = 0 and a
    # degenerate interval; every other one a proper interval around its value
    held = par["u"] == 0
    assert set(par.loc[held, "name"]) <= {"EX0T", "EY0T", "EZ0T"}, par.loc[held, "name"]
    par = par[~held]
    assert (par["ci95_low"] < par["value"]).all() and (par["ci95_high"] > par["value"]).all()
    # the GUM S1 estimate (mean of trials) is the identification's estimate within noise
    assert np.all(np.abs(par["mc_mean"] - par["value"]) < 4 * par["u"] / np.sqrt(2000) + 1e-9)
    # the 95 % interval of a near-normal output spans about 2 x 1.96 u
    width = (par["ci95_high"] - par["ci95_low"]) / (2 * 1.96 * par["u"])
    assert width.between(0.9, 1.1).all()
    vol = mc.volumetric()
    assert {"dx_um", "u_dx_um", "U_norm_um", "norm_ci95_low_um"} <= set(vol.columns)
    mv = mc.max_volumetric()
    assert 60 < mv["max_norm_um"] < 70 and 0 < mv["U_norm_at_max_um"] < 5
    q = quantity_table(mc, example_mc["example"].error_model, ["EXX(754)", "EC0Y", "EXX_1"])
    assert list(q["unit"]) == ["um", "urad", "um"]
    assert (q["U"] > 0).all()


def test_same_seed_same_numbers_whatever_the_workers(example_mc):
    k = example_mc["kernel"]
    a = run_trials(k, 500, 5, workers=1, chunk_size=100)
    b = run_trials(k, 500, 5, workers=2, chunk_size=100)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.vol, b.vol)
    c = run_trials(k, 500, 6, workers=1, chunk_size=100)
    assert not np.array_equal(a.x, c.x)
    # the linear mode is the same map for every trial: close to the nonlinear solutions
    lin = run_trials(k, 500, 5, workers=1, chunk_size=100, mode="linear")
    dev = np.abs(lin.x - a.x) / k.engine.scale
    assert dev.max() < 1e-3  # um / urad: the problem is nearly linear


def test_dask_local_cluster_gives_identical_results(example_mc, dask_client):
    k = example_mc["kernel"]
    local = run_trials(k, 400, 9, workers=1, chunk_size=100)
    remote = run_trials(k, 400, 9, scheduler=dask_client, chunk_size=100)
    assert np.array_equal(local.x, remote.x)
    assert np.array_equal(local.vol, remote.vol)


@pytest.mark.parametrize("mode", ["nonlinear", "linear"])
def test_same_seed_identical_serially_with_processes_and_on_dask(example_mc, mode, monkeypatch,
                                                               dask_client):
    """One seed, one chunk size: the same numbers in this process, in local worker
    processes (forked: the kernel inherited; spawned: the kernel pickled; by default this
    process computing chunks too) and on a Dask LocalCluster."""
    k = example_mc["kernel"]
    opts = dict(mode=mode, chunk_size=60)
    serial = run_trials(k, 240, 21, workers=1, **opts)
    runs = {}
    for method in ("fork", "spawn"):
        monkeypatch.setenv("VOLCAL_MP_START", method)
        runs[method] = run_trials(k, 240, 21, workers=2, **opts)
        runs[method + ", this process too"] = run_trials(k, 240, 21, workers=None, **opts)
    monkeypatch.delenv("VOLCAL_MP_START")
    runs["dask"] = run_trials(k, 240, 21, scheduler=dask_client, **opts)
    for name, other in runs.items():
        for f in ("x", "vol", "iterations", "converged", "step"):
            assert np.array_equal(getattr(serial, f), getattr(other, f)), (name, f)


class _Interrupt(Exception):
    pass


def test_interrupted_run_resumes_from_saved_chunks(example_mc, tmp_path):
    import copy

    k = example_mc["kernel"]
    full = run_trials(k, 500, 3, workers=1, chunk_size=100)
    broken = copy.copy(k)
    calls = {"n": 0}
    orig = k.run_chunk

    def flaky(chunk):
        calls["n"] += 1
        if calls["n"] == 3:
            raise _Interrupt("simulated interruption")
        return orig(chunk)

    broken.run_chunk = flaky
    with pytest.raises(_Interrupt):
        run_trials(broken, 500, 3, workers=1, chunk_size=100, out_dir=tmp_path)
    files = sorted((tmp_path / "samples").glob("*/chunk*.npz"))
    assert len(files) == 2
    again = run_trials(k, 500, 3, workers=1, chunk_size=100, out_dir=tmp_path)
    assert again.resumed_chunks == 2
    assert np.array_equal(again.x, full.x)
    # recomputed from the saved parameters by a new BLAS product on a loaded copy: equal
    # to its rounding (a differently aligned operand may take another kernel path and
    # change the last bit, seen as 1e-17 mm on 5e-2 mm values when run alone)
    np.testing.assert_allclose(again.vol, full.vol, rtol=0, atol=1e-14)
    # a damaged chunk file is recomputed, never trusted
    files = sorted((tmp_path / "samples").glob("*/chunk*.npz"))
    files[0].write_bytes(b"garbage")
    third = run_trials(k, 500, 3, workers=1, chunk_size=100, out_dir=tmp_path)
    assert third.resumed_chunks == 4 and np.array_equal(third.x, full.x)


def test_contributions_one_source_at_a_time(example_mc):
    k = example_mc["kernel"]
    names = k.source_names
    assert names[:4] == ["laser_length", "resolution", "fixed_sphere", "reflector_form"]
    assert {"repeatability_X", "repeatability_Y", "repeatability_Z"} <= set(names)
    # linearised: the sources' covariances add up to the total exactly
    total = k.linear_covariance()
    parts = sum(k.linear_covariance([n]) for n in names)
    assert np.allclose(parts, total, rtol=1e-10, atol=1e-30)
    tab, runs = contributions(k, 200, 11, workers=1)
    assert set(tab["source"]) == set(names)
    # Monte Carlo with the same draws: the deviations of the one-source runs add up to the
    # full run's (exactly for a linear problem; this one is linear to ~1e-5)
    full = run_trials(k, 200, 11, workers=1)
    x0 = k.engine.x_hat
    dev_sum = sum(runs[n].x - x0 for n in names)
    scale = np.abs(full.x - x0).max(axis=0) + 1e-30
    assert np.max(np.abs(dev_sum - (full.x - x0)) / scale) < 1e-4
    u_full = full.x[:, :k.n_theta].std(axis=0)
    u_sum = np.sqrt(sum(runs[n].x[:, :k.n_theta].std(axis=0) ** 2 for n in names))
    live = u_full > 0  # not the parameters the datum holds exactly
    assert abs(np.median(u_sum[live] / u_full[live]) - 1) < 0.05
    # the trials of a source alone are the full run's draws of that source
    dm_full, _ = k.sampler.draw(11, [0])
    parts_dm = sum(k.sampler.draw(11, [0], enabled=[n])[0] for n in names)
    assert np.allclose(parts_dm, dm_full, rtol=0, atol=1e-15)


def test_sampler_variances_match_the_budget(example_mc):
    k = example_mc["kernel"]
    dM, _ = k.sampler.draw(1, range(400))
    var_budget = sum(k.sampler.reading_variance(n) for n in k.source_names)
    ratio = dM.var(axis=0).mean() / var_budget.mean()
    assert abs(ratio - 1) < 0.03
    # and the weights of the identification are the budget's (1/sigma)
    assert np.allclose(1 / k.engine.w ** 2, var_budget, rtol=1e-3)


def test_evaluation_factor():
    # paper 002 Table 4: squareness 116.7 +- 14.8 vs 106 +- 6.2 urad -> E_n 0.67
    assert evaluation_factor(116.7, 14.8, 106.0, 6.2) == pytest.approx(0.6668, abs=1e-3)
    assert np.allclose(evaluation_factor([1, 2], [1, 1], [1, 4], [0, 1]),
                       [0.0, 2 / np.sqrt(2)])
    with pytest.raises(ValueError):
        evaluation_factor(1, -1, 1, 1)
    res = pd.DataFrame({"name": ["EXX(754)", "EC0Y"], "value": [11.5, -13.0],
                        "unit": ["um", "urad"], "U": [0.3, 0.9]})
    ref = pd.DataFrame({"name": ["EC0Y", "EXX(754)"], "value": [-13.5e-6, 0.0120],
                        "unit": ["rad", "mm"], "U": [1e-6, 0.0004]})
    cmp = compare_with_reference(res, ref)
    assert list(cmp["name"]) == ["EC0Y", "EXX(754)"]
    assert cmp["E_n"].iloc[0] == pytest.approx(0.5 / np.hypot(0.9, 1.0))
    assert cmp["E_n"].iloc[1] == pytest.approx(0.5 / np.hypot(0.3, 0.4))
    assert cmp["agrees"].all()


def test_mc_command_writes_results_and_resumes(tmp_path, capsys):
    from volcal.cli.main import main

    out = tmp_path / "mc"
    ref = tmp_path / "ref.csv"
    pd.DataFrame({"name": ["EXX(754)"], "value": [11.5], "unit": ["um"],
                  "U": [0.5]}).to_csv(ref, index=False)
    argv = ["mc", "--example", "mcv754", "--trials", "300", "--workers", "1",
            "--chunk-size", "100", "--verify", "1", "--no-progress", "--no-plots",
            "--reference", str(ref), "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "IPOPT cross-check" in text and "reference comparison" in text
    assert "  identification           fits (chi2/dof" in text
    for f in ("parameters.csv", "error_motions.csv", "volumetric.csv", "summary.json",
              "report.md", "comparison.csv"):
        assert (out / f).is_file(), f
    summ = json.loads((out / "summary.json").read_text())
    assert summ["trials"] == 300 and summ["not_converged"] == 0
    assert summ["identification"]["adequacy"] == "fits"
    assert summ["verify_against_ipopt"]["theta_rel"] < 1e-9
    first = pd.read_csv(out / "parameters.csv")
    assert main(argv) == 2          # an earlier run is replaced only with --force
    assert main(argv + ["--force"]) == 0
    assert "3 chunk(s) resumed" in capsys.readouterr().out
    pd.testing.assert_frame_equal(first, pd.read_csv(out / "parameters.csv"))
    assert main(["mc", "--model", "mcv754_wxyzt", "--out", str(out)]) == 2


def test_mc_program_with_plots_and_stage_timings(tmp_path):
    """The whole program as a user runs it: the plots drawn by the plotting process, the
    stage timings of -v, the process ended without the interpreter's teardown."""
    import subprocess
    import sys

    out = tmp_path / "mc"
    run = subprocess.run(
        [sys.executable, "-m", "volcal.cli.main", "mc", "--example", "mcv754", "--trials",
         "60", "--chunk-size", "30", "--workers", "2", "--verify", "1", "--no-progress",
         "--out", str(out), "-v"],
        capture_output=True, text=True, timeout=600,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    for f in ("volumetric_U.png", "max_volumetric.png", "summary.json", "parameters.csv"):
        assert (out / f).is_file(), f
    assert (out / "volumetric_U.png").read_bytes()[:4] == b"\x89PNG"
    assert "stage timings" in run.stdout and "identification" in run.stdout


def test_plot_process_reports_a_failed_plot(tmp_path):
    from volcal.outputs.mc_plots import _plot_max_hist
    from volcal.outputs.plot_process import PlotProcess

    pp = PlotProcess.start(workers=2)
    if pp is None:
        pytest.skip("no plotting process on this platform")
    try:
        pp.draw(_plot_max_hist, np.linspace(1.0, 2.0, 50), tmp_path / "h.png")
        pp.wait()
        assert (tmp_path / "h.png").is_file()
        pp.draw(_plot_max_hist, np.linspace(1.0, 2.0, 50), tmp_path / "h2.png")
        pp.draw(_plot_max_hist, np.linspace(1.0, 2.0, 50), tmp_path / "no" / "such" / "h.png")
        with pytest.raises(RuntimeError, match="plotting failed"):
            pp.wait()
        assert (tmp_path / "h2.png").is_file()  # the other child's figure still drawn
    finally:
        pp.close()


def test_paper002_study_smoke(tmp_path):
    """studies/paper002/run.py --smoke: the 17-error model of paper 002 at its Table 2
    stations with its Table 1 budget (the full run's figures are in its README)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "studies" / "paper002" / "run.py"
    spec = importlib.util.spec_from_file_location("paper002_run", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--smoke", "--no-plots", "--workers", "1", "--out", str(tmp_path)]) == 0
    summ = json.loads((tmp_path / "summary.json").read_text())
    assert summ["plan_analysis"]["unidentifiable_17"] == []
    assert "ECY, EAZ, EBZ, ECZ" in summ["plan_analysis"]["unidentifiable_21"][0]
    v = summ["variants"]["poly3"]
    assert v["not_converged"] == 0
    assert v["verify_against_ipopt"]["theta_rel"] < 1e-9
    # 300 trials: MC and linearised standard uncertainties within MC noise
    assert v["agreement_with_linearised"]["parameters_max_rel_diff"] < 0.25
    assert 2.0 < v["max_volumetric"]["U_norm_at_max_um"] < 12.0
    tab = pd.read_csv(tmp_path / "table3_poly3.csv")
    assert len(tab) == 17 and (tab["U"] > 0).all()


def test_drift_tool_and_station_inputs(example_mc):
    """Optional inputs: the budget's drift (one realisation per station over the time
    stamps), tool offset and fixed-station uncertainties: sampled, and their linearised
    covariance matches the Monte Carlo spread of the linear map."""
    from volcal.analysis.uncertainty.montecarlo import build_kernel
    from volcal.measurement.budget import PAPER001_DRIFT

    ex = example_mc["example"]
    ider, p = example_mc["identifier"], example_mc["p"]
    meas = example_mc["measurements"]
    fixed = example_mc["fixed"].copy()
    nt = ider.problem.n_theta
    fixed[nt:nt + 4] = True                        # hold the first station
    bud = ex.budget.with_drift(PAPER001_DRIFT)
    k = build_kernel(ider, example_mc["kernel"].engine.x_hat, p, fixed, bud,
                     time_s=meas.time, tool_sigma_mm=2e-3, station_sigma_mm=5e-3)
    assert {"drift", "tool_offsets", "stations"} <= set(k.source_names)
    for name in ("drift", "tool_offsets", "stations"):
        s = run_trials(k, 1500, 4, mode="linear", enabled=[name], workers=1, chunk_size=500)
        u_mc = s.x[:, :nt].std(axis=0, ddof=1)
        u_lin = np.sqrt(np.diag(k.linear_covariance([name]))[:nt])
        ok = u_lin > 1e-3 * u_lin.max()
        ratio = np.median(u_mc[ok] / u_lin[ok])
        assert abs(ratio - 1) < 0.06, (name, ratio)
    # the held station moves in the trials with the station source on, not without it
    s = run_trials(k, 50, 4, mode="nonlinear", enabled=["stations"], workers=1)
    assert s.converged.all() and s.x[:, nt:nt + 3].std(axis=0).min() > 1e-3
