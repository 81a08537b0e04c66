"""Exported C solvers: gcc -Wall -Werror build, agreement with the Python identification,
libc/libm-only dependencies, honest non-convergence flags, reuse, model-only export.

The export of the bundled 3-axis example is built once per module (about 5 s)."""
from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

from volcal.analysis.identify import identify
from volcal.measurement.simulate import example
from volcal.outputs.codegen import export_model, export_solver, load
from volcal.outputs.codegen.export import DEFAULT_OPTIONS

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("make") is None,
                                reason="needs gcc and make")

CFLAGS = "-O2 -Wall -Werror"
AXES = ["X", "Y", "Z"]
ST_COLS = ["x_mm", "y_mm", "z_mm", "dead_length_mm"]


@pytest.fixture(scope="module")
def ex():
    return example()


@pytest.fixture(scope="module")
def data(ex, tmp_path_factory):
    df = ex.simulate().measurements
    path = tmp_path_factory.mktemp("data") / "measurements.csv"
    df.to_csv(path, index=False)
    return df, path


@pytest.fixture(scope="module")
def exported(ex, data, tmp_path_factory):
    df, _ = data
    out = tmp_path_factory.mktemp("export") / "solver"
    return export_solver(ex.model, df, out, cflags=CFLAGS)


@pytest.fixture(scope="module")
def python_result(ex, data):
    return identify(ex.model, data[0])


@pytest.fixture(scope="module")
def c_run(exported, data, tmp_path_factory):
    """The example program on the measurement file, in a subprocess."""
    out = tmp_path_factory.mktemp("c_out")
    proc = subprocess.run([str(exported.example), str(data[1]), str(out)],
                          capture_output=True, text=True, timeout=60)
    return proc, out


def _status(path):
    return dict(line.split(" = ", 1) for line in path.read_text().splitlines())


def test_export_folder_has_the_promised_files(exported):
    names = {p.name for p in exported.path.iterdir()}
    n = exported.name
    for f in (f"{n}.h", f"{n}.c", f"{n}_generated.c", f"{n}_generated.h", "main.c", "Makefile",
              "README.md", "manifest.json", "plan.csv", f"lib{n}.a", f"lib{n}.so",
              f"{n}_example"):
        assert f in names, f
    man = json.loads((exported.path / "manifest.json").read_text())
    assert man["model"]["name"] == "mcv754_wxyzt"
    assert man["versions"]["casadi"] and man["versions"]["volcal"]
    assert man["content_hash"] and set(man["files"]) <= names
    # the variables held fixed are those of the Python analysis: the six frame parameters
    assert sorted(man["phases"][0]["fixed"]) == sorted(
        ["frame_tx_mm", "frame_ty_mm", "frame_tz_mm", "frame_rx_rad", "frame_ry_rad",
         "frame_rz_rad"])


def test_c_example_reproduces_python_identification(c_run, python_result, ex, exported):
    proc, out = c_run
    assert proc.returncode == 0, proc.stderr + proc.stdout
    st = _status(out / "status.txt")
    assert st["converged"] == "1" and st["status"] == "0"
    assert float(st["kkt_rel"]) <= DEFAULT_OPTIONS["tol_kkt"]
    assert exported.manifest["options"]["runtime_defaults"]["max_chi2"] == 100.0

    par_c = pd.read_csv(out / "parameters.csv")
    par_py = python_result.parameters()
    assert list(par_c["name"]) == list(par_py["name"])
    assert list(par_c["unit"]) == list(par_py["unit"])
    vc, vp = par_c["value"].to_numpy(), par_py["value"].to_numpy()
    # within 1e-9 relative to the parameter vector (um / urad) ...
    assert np.max(np.abs(vc - vp)) <= 1e-9 * np.max(np.abs(vp))
    # ... and to each parameter's own size or standard uncertainty, whichever is larger
    # (a parameter near zero is known only to its uncertainty)
    scale = np.fmax(np.abs(vp), par_py["u"].to_numpy())
    # (1e-8: the C solver's own stationarity tolerance; held at zero: exactly zero)
    assert np.all(np.abs(vc - vp) <= 1e-8 * scale)

    st_c = pd.read_csv(out / "stations.csv")
    assert list(st_c["station"]) == list(python_result.stations["station"])
    assert np.abs(st_c[ST_COLS].to_numpy()
                  - python_result.stations[ST_COLS].to_numpy()).max() < 1e-9  # mm

    # the same volumetric errors at every distinct point of the measurement
    vol = pd.read_csv(out / "volumetric.csv")
    q = ex.machine.axis_to_internal(vol[AXES].to_numpy())
    pred = python_result.predict(q, vol[["tool_x", "tool_y", "tool_z"]].to_numpy(),
                                 with_uncertainty=False)
    dc = vol[["dx_um", "dy_um", "dz_um"]].to_numpy()
    dp = pred[["dx_um", "dy_um", "dz_um"]].to_numpy()
    assert len(vol) == data_points(python_result)
    assert np.abs(dc - dp).max() <= 1e-9 * np.abs(dp).max()

    res = pd.read_csv(out / "residuals.csv")
    r_py = python_result.residuals["residual_um"].to_numpy()
    assert np.abs(res["residual_um"].to_numpy() - r_py).max() < 1e-6  # um


def data_points(result):
    return result.residuals["point"].nunique()


def test_library_needs_only_libc_and_libm(exported):
    allowed = ("linux-vdso", "libc.so", "libm.so", "ld-linux")
    for binary in (exported.library, exported.example):
        if shutil.which("readelf"):
            dyn = subprocess.run(["readelf", "-d", str(binary)], capture_output=True,
                                 text=True, check=True).stdout
            needed = [ln.split("[")[1].rstrip("]") for ln in dyn.splitlines() if "(NEEDED)" in ln]
            assert set(needed) <= {"libc.so.6", "libm.so.6"}, needed
        if shutil.which("ldd"):
            out = subprocess.run(["ldd", str(binary)], capture_output=True, text=True,
                                 check=True).stdout
            libs = [ln.split()[0] for ln in out.splitlines() if ln.strip()]
            assert libs and all(any(lib.startswith(a) or a in lib for a in allowed)
                                for lib in libs), libs


def test_loader_matches_example_and_reports_its_checks(exported, data, c_run):
    solver = load(exported.path)
    res = solver.identify_table(data[0])
    assert res.converged and res.status == 0 and res.status_text == "converged"
    par_c = pd.read_csv(c_run[1] / "parameters.csv")
    assert np.array_equal(res.parameters()["value"].to_numpy(), par_c["value"].to_numpy())
    assert res.step <= DEFAULT_OPTIONS["tol_step"]
    assert res.constraint_violation <= DEFAULT_OPTIONS["tol_constraint"]
    assert 0.7 < res.chi2_per_dof < 1.3
    # the model function alone gives what the example wrote
    vol = pd.read_csv(c_run[1] / "volumetric.csv")
    _, dp = solver.volumetric(vol[AXES].to_numpy()[:20], vol[["tool_x", "tool_y",
                                                               "tool_z"]].to_numpy()[:20],
                              res.theta)
    assert np.abs(dp * 1e3 - vol[["dx_um", "dy_um", "dz_um"]].to_numpy()[:20]).max() < 1e-9


def test_budget_weights_when_the_data_have_no_sigma(exported, data, ex):
    df = data[0].drop(columns=["sigma"])
    res_c = load(exported.path).identify_table(df)
    res_py = identify(ex.model, df)
    assert res_c.converged
    vc, vp = res_c.parameters()["value"].to_numpy(), res_py.parameters()["value"].to_numpy()
    # Python's budget uses a finite-difference derivative of the nominal point (about 1e-7
    # relative in the weights); the C export the exact one
    assert np.max(np.abs(vc - vp)) <= 1e-8 * np.max(np.abs(vp))


def test_non_convergence_is_flagged_never_hidden(exported, data):
    solver = load(exported.path)
    a = solver.arrays_from_table(data[0])
    good = solver.identify(a["q"], a["tool"], a["length"], a["sigma"])
    assert good.converged
    st_good = good.stations[ST_COLS].to_numpy()

    def run(**kw):
        args = {k: kw.pop(k, a[k]) for k in ("q", "tool", "length", "sigma")}
        return solver.identify(args["q"], args["tool"], args["length"], args["sigma"], **kw)

    def best_iterate(r):
        """flagged, with the best iterate: finite values and the real chi2 per dof"""
        assert not r.converged and r.status != 0
        assert r.status_text.endswith("best iterate returned")
        assert np.isfinite(r.theta).all() and np.isfinite(r.stations[ST_COLS].to_numpy()).all()
        assert np.isfinite(r.chi2_per_dof) and r.chi2_per_dof > 0 and r.dof > 0
        assert np.isfinite(r.kkt_rel) and np.isfinite(r.cost)

    def nothing_computed(r):
        """flagged, and NaN where no finite iterate exists: never a chi2 per dof of 0"""
        assert not r.converged and np.isnan(r.theta).all() and np.isnan(r.chi2_per_dof)

    # too few iterations from the usual start: the best iterate (here the last), flagged
    r = run(max_iter=1)
    best_iterate(r)
    assert r.status_text == "iteration limit reached; best iterate returned"
    assert r.iterations == 1 and r.kkt_rel > DEFAULT_OPTIONS["tol_kkt"]
    # one Gauss-Newton step from the usual start is already close (chi2 per dof real)
    assert abs(r.chi2_per_dof - good.chi2_per_dof) < 1e-3 * good.chi2_per_dof
    assert np.abs(r.theta - good.theta).max() < 1e-2 * np.abs(good.theta).max()
    # no iteration at all: the start point, with its own (large) chi2 per dof
    r0 = run(max_iter=0)
    best_iterate(r0)
    assert r0.iterations == 0 and r0.chi2_per_dof > r.chi2_per_dof
    # absurd start stations: either flagged, or converged to the same answer
    rng = np.random.default_rng(0)
    flagged = 0
    for start in (np.zeros_like(st_good), st_good + [0, 0, 1e5, 0], st_good * 10,
                  st_good + rng.normal(0, 1e3, st_good.shape), np.full_like(st_good, 1e12)):
        r = run(stations0=start)
        if r.converged:
            assert np.abs(r.theta - good.theta).max() <= 1e-9 * np.abs(good.theta).max()
        else:
            flagged += 1
            if r.status_text.startswith("NaN or Inf"):
                nothing_computed(r)   # the first iterate was not finite already
            else:
                best_iterate(r)
                assert r.chi2_per_dof > 100   # far from the answer, and it says so
    assert flagged >= 2
    # absurd start parameters
    r = run(theta0=np.full(len(good.theta), 1.0), max_iter=3)
    best_iterate(r)
    assert r.chi2_per_dof > 100
    # corrupted data: one reading off by 1 mm converges numerically but is not plausible
    L = a["length"].copy()
    L[10] += 1.0
    r = run(length=L)
    assert not r.converged and r.status_text.startswith("poor fit") and r.chi2_per_dof > 100
    # corrupted data: the readings of one station in reverse order (a file sorted wrongly)
    L = a["length"].copy()
    i0 = np.flatnonzero(np.asarray(solver.plan["station"]) == "LT1")
    L[i0] = L[i0[::-1]]
    r = run(length=L)
    assert not r.converged
    # ... also when good start stations are given (the fit then cannot be plausible)
    r = run(length=L, stations0=st_good)
    assert not r.converged and r.chi2_per_dof > 100
    # invalid input is refused before any iteration
    L = a["length"].copy()
    L[3] = np.nan
    r = run(length=L)
    assert r.status_text.startswith("invalid input")
    nothing_computed(r)
    s = a["sigma"].copy()
    s[5] = 0.0
    r = run(sigma=s)
    assert r.status_text.startswith("invalid input")
    nothing_computed(r)


def test_example_program_exit_code_flags_corrupted_file(exported, data, tmp_path):
    df = data[0].copy()
    rng = np.random.default_rng(1)
    df["length"] = rng.permutation(df["length"].to_numpy())
    bad = tmp_path / "bad.csv"
    df.to_csv(bad, index=False)
    proc = subprocess.run([str(exported.example), str(bad), str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert _status(tmp_path / "out" / "status.txt")["converged"] == "0"
    # a reading the plan does not have is bad input (exit code 2)
    df = data[0].copy()
    df.loc[0, "point"] = "nowhere"
    df.to_csv(bad, index=False)
    proc = subprocess.run([str(exported.example), str(bad), str(tmp_path / "out2")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "not a reading of the exported plan" in proc.stderr


def test_example_program_at_iteration_limit_writes_best_iterate(ex, data, tmp_path):
    """At the iteration limit the example program writes the best iterate, flagged (exit
    code 1, converged = 0), with the real chi2 per dof: never NaN values and chi2/dof 0."""
    info = export_solver(ex.model, data[0], tmp_path / "it1", options={"max_iter": 1},
                         cflags=CFLAGS)
    out = tmp_path / "out"
    proc = subprocess.run([str(info.example), str(data[1]), str(out)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "iteration limit reached; best iterate returned" in proc.stdout
    assert "NOT CONVERGED" in proc.stdout and "chi2/dof 0\n" not in proc.stdout
    st = _status(out / "status.txt")
    assert st["converged"] == "0" and st["status"] == "5" and st["iterations"] == "1"
    assert 0.5 < float(st["chi2_per_dof"]) < 2.0 and int(st["dof"]) > 0
    assert f"chi2/dof {float(st['chi2_per_dof']):.4g}" in proc.stdout
    assert np.isfinite(pd.read_csv(out / "parameters.csv")["value"]).all()
    vol = pd.read_csv(out / "volumetric.csv")
    assert np.isfinite(vol[["dx_um", "dy_um", "dz_um"]].to_numpy()).all()


def test_unchanged_export_is_reused(exported, ex, data, tmp_path):
    again = export_solver(ex.model, data[0], exported.path, cflags=CFLAGS)
    assert again.reused and again.manifest["content_hash"] == exported.manifest["content_hash"]
    # a plan without lengths (stations table instead) with other options is a new export
    plan = data[0].drop(columns=["length", "sigma", "time"])
    other = export_solver(ex.model, plan, tmp_path / "other", stations=ex.stations, degree=2,
                          build_it=False)
    assert not other.reused and other.manifest["input_hash"] != exported.manifest["input_hash"]
    assert other.manifest["parameters"]["names"][:3] == ["EXX_0", "EXX_1", "EXX_2"]
    assert export_solver(ex.model, plan, tmp_path / "other", stations=ex.stations, degree=2,
                         build_it=False).reused


def test_model_only_export(ex, tmp_path, python_result):
    info = export_model(ex.model, tmp_path / "model", cflags=CFLAGS)
    model = load(info.path)
    rng = np.random.default_rng(2)
    q = rng.uniform([0, 0, -550], [754, 500, 0], (30, 3))
    tool = rng.uniform(-100, 100, (30, 3))
    theta = python_result.theta
    p, dp, J_th, J_q = model.volumetric(q, tool, theta, jacobians=True)
    m, em = ex.machine, ex.error_model
    e = em.values(q, theta)
    p_py, dp_py, Je = m.evaluate(q, tool, e)
    assert np.abs(p - p_py).max() < 1e-12 and np.abs(dp - dp_py).max() < 1e-15
    G = np.einsum("nik,nkp->nip", Je, em.basis(q))  # d dp / d theta
    assert np.abs(J_th - G).max() < 1e-12
    h = 1e-3
    p1, _ = model.volumetric(q + [h, 0, 0], tool, theta)
    assert np.abs((p1 - p) / h - J_q[:, :, 0]).max() < 1e-6
    assert np.abs(model.error_values(q, theta) - e).max() < 1e-15


def test_two_phase_strategy_agrees_with_tight_python(ex, data, tmp_path):
    from volcal.analysis.identify import initial_stations
    from volcal.measurement.tables import load_measurements
    from volcal.outputs.codegen import define_solver
    from volcal.solve.ipopt import NLPSolver

    df = data[0]
    info = export_solver(ex.model, df, tmp_path / "two", strategy="two-phase", cflags=CFLAGS)
    assert [ph["name"] for ph in info.manifest["phases"]] == ["stations", "errors"]
    res_c = info.load().identify_table(df)
    assert res_c.converged and res_c.phase == 1
    # Python's identifier with the same fixed sets, IPOPT tightened to converge as far
    d = define_solver(ex.model, df, strategy="two-phase")
    pr, ider = d.problem, d.identifier
    meas = load_measurements(df, ex.machine.spec)
    st0, _, _ = initial_stations(ex.machine, meas, None)
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, 1 / meas.sigma)
    ider.solver = NLPSolver(pr, tol=1e-10)
    x, outs, fixed, _ = ider.run("two-phase", pr.pack_x(np.zeros(pr.n_theta), st0), p)
    assert np.array_equal(fixed, d.phases[-1].fixed)
    th = x[:pr.n_theta]
    # the C solver ends phase 1 (stations) once its step is <= tol_step = 1e-7 um, which
    # moves the phase-2 parameters by up to ~2e-10 mm (1e-8 of the largest here)
    assert np.abs(res_c.theta - th).max() <= 2e-8 * np.abs(th).max()


def test_cli_codegen(exported, ex, data, capsys, tmp_path):
    from volcal.cli.main import main

    plan = tmp_path / "plan.csv"
    data[0].to_csv(plan, index=False)
    rc = main(["codegen", "--model", ex.model, "--plan", str(plan), "--out",
               str(exported.path)])
    out = capsys.readouterr().out
    assert rc == 0 and "reused unchanged export" in out
    with pytest.raises(SystemExit) as err:  # argparse refuses a strategy it cannot export
        main(["codegen", "--model", ex.model, "--plan", str(plan), "--strategy", "classic",
              "--out", str(tmp_path / "x")])
    assert err.value.code == 2
