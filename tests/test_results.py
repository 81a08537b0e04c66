"""The result folder of `volcal identify` (volcal.outputs.results), `volcal identify` and
`volcal predict`.

One small simulated data set (model xfyz, Legendre degree 2, 4 x 3 x 3 poses, 4 tool
offsets, 4 stations: 576 readings) is identified once and saved once per module.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import volcal.cli.main
import volcal.outputs.results as results
from volcal.analysis.identify import IdentificationResult, identify
from volcal.base.exceptions import InputError, SolverError
from volcal.measurement.plans import default_stations, grid_plan
from volcal.measurement.simulate import draw_true_parameters, simulate
from volcal.model.errors import ErrorForm, ErrorModel
from volcal.model.machine import Machine
from volcal.outputs.results import (
    DATA_FILES,
    PLOT_FILES,
    RESULT_FILES,
    load_result,
    read_points,
    save_result,
)
from volcal.solve.outcome import SolveOutcome

TOOLS = np.array([[0, 0, 0], [0, 0, -100.0], [80, 0, -100.0], [0, 80, -100.0]])
OUTLIER_INDEX = 37          # 0-based reading given a blunder in the robust CLI run
OUTLIER_MM = 0.05


def run_cli(argv: list[str], monkeypatch) -> int:
    """volcal.cli.main.main with only this file's commands registered (independent of the
    other commands' modules)."""
    monkeypatch.setattr(volcal.cli.main, "_COMMANDS",
                        ["volcal.cli.commands.identify", "volcal.cli.commands.predict"])
    return volcal.cli.main.main(argv)


def file_hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def folder_hashes(path: Path) -> dict[str, str]:
    return {p.name: file_hash(p) for p in sorted(Path(path).iterdir())}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("results")
    machine = Machine.from_model("xfyz")
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 2))
    theta = draw_true_parameters(machine, em, np.random.default_rng(3), 30.0)
    plan = grid_plan(machine.spec, {"X": 4, "Y": 3, "Z": 3})
    stations = default_stations(machine.spec, 4, seed=3, tools=TOOLS)
    sim = simulate(machine, em, theta, stations, plan, TOOLS, "paper002", 3)
    data = tmp / "measurements.csv"
    sim.measurements.to_csv(data, index=False)
    res = identify(machine, data, error_model=em)
    out = save_result(res, tmp / "result", data_name="measurements.csv")
    return {"tmp": tmp, "machine": machine, "em": em, "res": res, "out": out, "data": data,
            "plan": plan, "measurements": sim.measurements}


# --------------------------------------------------------------------------------------
# the folder


def test_every_file_is_written_with_its_columns_and_units(case):
    out = case["out"]
    names = sorted(p.name for p in out.iterdir())
    # solver_state.npz: optional for folders of format 2, always written now
    assert names == sorted([*RESULT_FILES, "manifest.json", "solver_state.npz"])
    for png in PLOT_FILES:
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    par = pd.read_csv(out / "parameters.csv")
    assert list(par.columns) == ["name", "value", "unit", "u", "identifiable", "imposed"]
    assert set(par["unit"]) == {"um", "urad"}
    st = pd.read_csv(out / "stations.csv")
    assert list(st.columns[:5]) == ["station", "x_mm", "y_mm", "z_mm", "dead_length_mm"]
    resid = pd.read_csv(out / "residuals.csv")
    meas = case["measurements"]
    assert list(resid.columns[:len(meas.columns)]) == list(meas.columns)
    assert list(resid.columns[len(meas.columns):]) == ["residual_um", "normalised_residual",
                                                       "rejected"]
    assert len(resid) == len(meas)
    np.testing.assert_allclose(resid["length"], meas["length"], rtol=0, atol=0)
    comp = pd.read_csv(out / "component_errors.csv")
    assert list(comp.columns[:2]) == ["axis", "position_mm"]
    assert "position_deg" not in comp  # no rotary axis in this model
    for a in "XYZ":
        for e in "XYZ":
            assert f"E{e}{a}_um" in comp and f"u_E{e}{a}_um" in comp
        for e in "ABC":
            assert f"E{e}{a}_urad" in comp and f"u_E{e}{a}_urad" in comp
    assert set(comp["axis"]) == {"X", "Y", "Z"}
    grid = pd.read_csv(out / "volumetric_grid.csv")
    assert list(grid.columns) == ["X", "Y", "Z", "dx_um", "dy_um", "dz_um", "u_dx_um",
                                  "u_dy_um", "u_dz_um", "norm_um"]
    assert len(grid) == 7 ** 3
    report = (out / "report.md").read_text()
    for needle in ("# volcal identification: xfyz", "error = actual - nominal", "correction",
                   "Solve", "residual RMS", "chi2 / dof", "largest volumetric error",
                   "Condition numbers", "### Datum", "Gauge freedoms held", "## Parameters",
                   "## Stations", "(component_errors.png)", "(volumetric_map.png)",
                   "(residuals.png)", "`measurements.csv`"):
        assert needle in report, needle
    # no temporary folder left next to the result
    assert sorted(p.name for p in out.parent.iterdir()) == ["measurements.csv", "result"]


def test_tables_hold_the_result(case):
    res, out = case["res"], case["out"]
    par = pd.read_csv(out / "parameters.csv")
    exp = res.parameters()
    assert list(par["name"]) == list(exp["name"])
    np.testing.assert_allclose(par["value"], exp["value"], rtol=1e-15, atol=0)
    np.testing.assert_allclose(par["u"], exp["u"], rtol=1e-15, atol=0)
    grid = pd.read_csv(out / "volumetric_grid.csv")
    q = case["machine"].axis_to_internal(grid[["X", "Y", "Z"]].to_numpy())
    pred = res.predict(q)
    pred = pred.drop(columns=["determined"])
    np.testing.assert_allclose(grid[pred.columns], pred, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(grid["norm_um"],
                               np.linalg.norm(pred[["dx_um", "dy_um", "dz_um"]], axis=1))
    doc = json.loads((out / "result.json").read_text())
    assert doc["max_volumetric_um"] == pytest.approx(grid["norm_um"].max(), rel=1e-12)
    assert doc["residual_rms_um"] == pytest.approx(res.residual_rms_um, rel=1e-12)


def test_component_errors_equal_an_independent_evaluation(case):
    em, res = case["em"], case["res"]
    comp = pd.read_csv(case["out"] / "component_errors.csv")
    spec = em.spec
    ref = np.array([a.reference for a in spec.axes])
    eye = np.eye(em.n_params)
    cov = np.nan_to_num(res.cov_theta)
    for j, a in enumerate(spec.axes):
        rows = comp[comp["axis"] == a.name]
        x = rows["position_mm"].to_numpy()
        assert x[0] == a.travel[0] and x[-1] == a.travel[1] and len(x) == 41
        q = np.tile(ref, (len(x), 1))
        q[:, j] = x
        e = em.values(q, res.theta)  # (N, n_errors) mm / rad
        # the error model is linear in theta: its columns from values() at unit vectors
        G = np.stack([em.values(q, eye[p]) for p in range(em.n_params)], axis=-1)
        for k, s in enumerate(em.errors):
            unit, f = ("um", 1e3) if s.unit == "mm" else ("urad", 1e6)
            col = f"{s.name}_{unit}"
            if s.axis != a.name or s.kind != "component":
                assert col not in comp or rows[col].isna().all()
                continue
            np.testing.assert_allclose(rows[col], e[:, k] * f, rtol=1e-12, atol=1e-12)
            var = np.einsum("np,pq,nq->n", G[:, k], cov, G[:, k])
            u = np.sqrt(np.clip(var, 0, None)) * f  # ~ -1e-20 at a datum point
            np.testing.assert_allclose(rows[f"u_{col}"], u, rtol=1e-9, atol=1e-12)
    # the datum (iso230): positioning and angular errors vanish at the reference position,
    # straightness at both ends of travel
    xrow = comp[comp["axis"] == "X"]
    assert abs(xrow["EXX_um"].iloc[0]) < 1e-9 and abs(xrow["EYX_um"].iloc[-1]) < 1e-9


def test_result_json_is_strict_json_and_round_trips(case):
    res, out, machine = case["res"], case["out"], case["machine"]
    text = (out / "result.json").read_text()
    doc = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert doc["format"] == results.RESULT_FORMAT
    assert doc["format_version"] == results.RESULT_FORMAT_VERSION
    assert doc["data"] == "measurements.csv" and doc["strategy"] == "joint"
    assert doc["versions"]["volcal"] and doc["versions"]["casadi"]
    assert doc["param_names"] == res.error_model.param_names
    assert doc["error_model"]["datum"] == "iso230"
    loaded = load_result(out)
    assert loaded.machine.spec == machine.spec
    assert loaded.error_model.param_names == res.error_model.param_names
    np.testing.assert_array_equal(loaded.theta, res.theta)
    np.testing.assert_array_equal(loaded.cov_theta, res.cov_theta)  # NaN where NaN
    np.testing.assert_array_equal(loaded.identifiable, res.identifiable)
    pd.testing.assert_frame_equal(loaded.parameters(), res.parameters())
    # predictions from the file equal the in-memory result, tool offsets included
    rng = np.random.default_rng(0)
    n = 25
    pts = pd.DataFrame({"point": [f"q{i}" for i in range(n)],
                        "X": rng.uniform(0, 800, n), "Y": rng.uniform(0, 500, n),
                        "Z": rng.uniform(-500, 0, n), "tool_x": rng.uniform(-50, 50, n),
                        "tool_z": rng.uniform(-150, 0, n)})
    before = pts.copy()
    got = loaded.predict(pts)
    pd.testing.assert_frame_equal(pts, before)  # the caller's table is not modified
    assert list(got.columns) == list(pts.columns) + ["dx_um", "dy_um", "dz_um", "u_dx_um",
                                                     "u_dy_um", "u_dz_um", "determined"]
    tool = np.column_stack([pts["tool_x"], np.zeros(n), pts["tool_z"]])
    exp = res.predict(machine.axis_to_internal(pts[["X", "Y", "Z"]].to_numpy()), tool)
    assert (got["determined"].to_numpy() == exp["determined"].to_numpy()).all()
    exp = exp.drop(columns=["determined"])
    np.testing.assert_allclose(got[exp.columns].to_numpy(), exp.to_numpy(), rtol=0, atol=1e-9)
    assert list(got["point"]) == list(pts["point"])


# --------------------------------------------------------------------------------------
# atomic writing


def _write_png(data, path):
    Path(path).write_bytes(b"png")


def _fail_draw(data, path):
    raise RuntimeError("plot failed")


def _die_draw(data, path):
    os._exit(3)  # a plotting child killed mid-figure (out of memory, a signal)


def test_a_failure_mid_write_leaves_no_folder(case, tmp_path, monkeypatch):
    # the component plot (slow) is stubbed; the failure comes after the tables, result.json
    # and one plot are in the temporary folder
    from volcal.outputs import figures

    monkeypatch.setattr(figures, "draw_component_errors", _write_png)
    monkeypatch.setattr(figures, "draw_volumetric_slices", _fail_draw)
    out = tmp_path / "new"
    with pytest.raises(RuntimeError, match="plot failed"):
        save_result(case["res"], out)
    assert list(tmp_path.iterdir()) == []  # neither out nor a temporary folder

    # a previous result stays exactly as it was
    prev = tmp_path / "prev"
    save_result(case["res"], prev, plots=False)
    before = folder_hashes(prev)
    with pytest.raises(RuntimeError, match="plot failed"):
        save_result(case["res"], prev, data_name="other.csv")
    assert folder_hashes(prev) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prev"]


def test_a_previous_result_is_replaced_and_other_folders_are_refused(case, tmp_path):
    out = tmp_path / "r"
    save_result(case["res"], out, plots=False, data_name="first.csv")
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted([*DATA_FILES, "manifest.json", "solver_state.npz"])
    save_result(case["res"], out, plots=False, data_name="second.csv")
    assert json.loads((out / "result.json").read_text())["data"] == "second.csv"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="other files"):
        save_result(case["res"], out, plots=False)
    assert (out / "notes.txt").read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "data.csv").write_text("x")
    with pytest.raises(InputError, match="choose a new or empty folder"):
        save_result(case["res"], other, plots=False)
    assert [p.name for p in other.iterdir()] == ["data.csv"]


# --------------------------------------------------------------------------------------
# a rotary model, a synthetic result (no identification needed)


def test_rotary_axes_unidentifiable_parameters_and_round_trip(tmp_path):
    machine = Machine.from_model("head_bc")
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 1), datum="reference")
    rng = np.random.default_rng(5)
    n = em.n_params
    theta = rng.normal(size=n) * np.where(np.array(em.param_units) == "mm", 2e-3, 5e-6)
    A = rng.normal(size=(n, n)) * 1e-4
    cov = A @ A.T
    identifiable = np.ones(n, bool)
    unid = [i for i, p in enumerate(em.param_names) if p.startswith("EBB_")]
    identifiable[unid] = False
    theta[unid] = 0.0
    cov[unid, :] = np.nan
    cov[:, unid] = np.nan
    resid = pd.DataFrame({"station": ["S1"] * 4, "point": ["a", "b", "c", "d"],
                          "X": 0.0, "Y": 0.0, "Z": 0.0, "C": 0.0, "B": 0.0,
                          "tool_x": 0.0, "tool_y": 0.0, "tool_z": 0.0,
                          "length": [1000.0, 1001.0, 1002.0, 1003.0],
                          "residual_um": [0.1, -0.2, 0.3, 5.0],
                          "normalised_residual": [0.2, -0.4, 0.6, 10.0],
                          "rejected": [False, False, False, True]})
    res = IdentificationResult(
        machine, em, "joint", theta, cov, identifiable,
        pd.DataFrame({"station": ["S1"], "x_mm": [1.0], "y_mm": [2.0], "z_mm": [3.0],
                      "dead_length_mm": [0.1], "fixed": [False]}),
        np.zeros(6), resid, None, [SolveOutcome(np.zeros(1), 0.0, "Solve_Succeeded", True, 3,
                                                0.01)],
        {"jacobian_scaled": 12.0, "chi2_per_dof": 1.0},
        resid.iloc[[3]].assign(row=[5]), 0.5, "budget test", ["a note"])
    out = save_result(res, tmp_path / "bc", plots=False, grid_points=3, component_points=5)
    comp = pd.read_csv(out / "component_errors.csv")
    assert list(comp.columns[:3]) == ["axis", "position_mm", "position_deg"]
    rows_b = comp[comp["axis"] == "B"]
    np.testing.assert_allclose(rows_b["position_deg"], np.linspace(-100, 100, 5))
    assert rows_b["position_mm"].isna().all()
    assert "ECC_urad" in comp and "u_EXB_um" in comp
    # an error motion with an unidentifiable parameter has no uncertainty; others do
    assert rows_b["u_EBB_urad"].isna().all() and rows_b["u_EAB_urad"].notna().all()
    assert (rows_b["EBB_urad"] == 0).all()
    grid = pd.read_csv(out / "volumetric_grid.csv")
    # the grid spans the rotary axes' travel too: C every 45 deg, B at 5 angles (0 among
    # them); with both at their reference it is the 3 x 3 x 3 grid of the linear axes
    assert len(grid) == 27 * 8 * 5
    assert grid["C"].nunique() == 8 and sorted(grid["B"].unique()) == [-100, -50, 0, 50, 100]
    assert ((grid["C"] == 0) & (grid["B"] == 0)).sum() == 27
    report = (out / "report.md").read_text()
    assert "`EBB_0`" in report and "`EBB_1`" in report and "a note" in report
    assert "| 5 | S1 | d |" in report  # the rejected reading, with its file row
    assert ".png" not in report.split("## Files")[0]
    loaded = load_result(out)
    pts = pd.DataFrame({"X": [100.0, 900.0], "Y": [0.0, 800.0], "Z": [-600.0, -10.0],
                        "C_deg": [-170.0, 45.0], "B_deg": [30.0, -90.0],
                        "tool_z": [-120.0, -80.0]})
    got = loaded.predict(pts)
    q = machine.axis_to_internal(pts[["X", "Y", "Z", "C_deg", "B_deg"]].to_numpy())
    exp = res.predict(q, np.column_stack([np.zeros(2), np.zeros(2), pts["tool_z"]]))
    if "determined" in exp:
        assert (got["determined"].to_numpy() == exp["determined"].to_numpy()).all()
        exp = exp.drop(columns=["determined"])
    np.testing.assert_allclose(got[exp.columns].to_numpy(), exp.to_numpy(), rtol=0, atol=1e-9)
    assert list(got.columns[:6]) == list(pts.columns)


# --------------------------------------------------------------------------------------
# points validation


def test_bad_points_name_file_row_and_column(case, tmp_path):
    spec = case["machine"].spec
    bad = tmp_path / "points.csv"
    bad.write_text("point,X,Y,Z\np1,0,0,-10\np2,10,abc,-10\n")
    with pytest.raises(InputError) as ei:
        read_points(bad, spec)
    msg = str(ei.value)
    assert str(bad) in msg and "row 3" in msg and "column 'Y'" in msg and "'abc'" in msg
    assert ei.value.row == 3 and ei.value.column == "Y"

    bad.write_text("X,Y\n0,0\n")
    with pytest.raises(InputError, match=r"row 1.*column 'Z'.*missing column\(s\) for Z"):
        read_points(bad, spec)

    bad.write_text("X,Y,Z\n0,0,-10\n900,0,-10\n")
    with pytest.raises(InputError) as ei:
        read_points(bad, spec)
    assert ei.value.row == 3 and ei.value.column == "X" and "outside the travel" in str(ei.value)

    bad.write_text("X,Y,Z,tool_xx\n0,0,-10,5\n")
    with pytest.raises(InputError, match="unknown column 'tool_xx'.*did you mean 'tool_x'"):
        read_points(bad, spec)

    bad.write_text("X,Y,Z,tool_x\n0,0,-10,\n")
    with pytest.raises(InputError, match=r"row 2, column 'tool_x': missing value"):
        read_points(bad, spec)

    with pytest.raises(InputError, match=r"<DataFrame>, row 2, column 'Z'"):
        read_points(pd.DataFrame({"X": [0.0], "Y": [0.0], "Z": [np.inf]}), spec)


# --------------------------------------------------------------------------------------
# the commands


def test_predict_cli_stdout_and_file(case, tmp_path, monkeypatch, capsys):
    out = case["out"]
    pts = tmp_path / "poses.csv"
    pd.DataFrame({"point": ["a", "b", "c"], "X_mm": [0.0, 400.0, 800.0],
                  "Y_mm": [0.0, 250.0, 500.0], "Z_mm": [-500.0, -250.0, 0.0],
                  "tool_z": [0.0, -100.0, -50.0]}).to_csv(pts, index=False)
    h_points, h_result = file_hash(pts), folder_hashes(out)
    assert run_cli(["predict", "--result", str(out), "--points", str(pts)], monkeypatch) == 0
    printed = capsys.readouterr().out
    from io import StringIO
    table = pd.read_csv(StringIO(printed))
    assert list(table.columns) == ["point", "X_mm", "Y_mm", "Z_mm", "tool_z", "dx_um", "dy_um",
                                   "dz_um", "u_dx_um", "u_dy_um", "u_dz_um", "determined"]
    exp = load_result(out).predict(pts)
    num = [c for c in exp.columns[5:] if c != "determined"]
    # printed with six significant digits
    np.testing.assert_allclose(table[num], exp[num], rtol=6e-6, atol=1e-9)
    v = tmp_path / "sub" / "v.csv"
    assert run_cli(["predict", "--result", str(out), "--points", str(pts), "--out", str(v),
                    "--no-uncertainty"], monkeypatch) == 0
    written = pd.read_csv(v)
    assert "u_dx_um" not in written and "dx_um" in written
    np.testing.assert_allclose(written["dx_um"], exp["dx_um"], rtol=1e-12)
    assert file_hash(pts) == h_points and folder_hashes(out) == h_result
    assert sorted(p.name for p in v.parent.iterdir()) == ["v.csv"]
    # an existing file is replaced only with --force
    before = v.read_bytes()
    assert run_cli(["predict", "--result", str(out), "--points", str(pts), "--out",
                    str(v)], monkeypatch) == 2
    assert v.read_bytes() == before
    assert run_cli(["predict", "--result", str(out), "--points", str(pts), "--out", str(v),
                    "--force"], monkeypatch) == 0
    assert "u_dx_um" in pd.read_csv(v)


def test_predict_cli_bad_input_exits_2(case, tmp_path, monkeypatch, capsys):
    pts = tmp_path / "poses.csv"
    pts.write_text("X,Y,Z\n0,0,-10\n1,2,oops\n")
    code = run_cli(["predict", "--result", str(case["out"]), "--points", str(pts)], monkeypatch)
    err = capsys.readouterr().err
    assert code == 2 and "row 3" in err and "column 'Z'" in err and str(pts) in err
    code = run_cli(["predict", "--result", str(tmp_path), "--points", str(pts)], monkeypatch)
    assert code == 2 and "no result.json" in capsys.readouterr().err
    code = run_cli(["predict", "--result", str(case["out"]), "--points", str(pts), "--out",
                    str(pts)], monkeypatch)
    assert code == 2 and "overwrite the points file" in capsys.readouterr().err
    assert pts.read_text() == "X,Y,Z\n0,0,-10\n1,2,oops\n"


def test_identify_cli_robust_summary_and_inputs_untouched(case, tmp_path, monkeypatch,
                                                          capsys):
    meas = case["measurements"].copy()
    meas.loc[OUTLIER_INDEX, "length"] += OUTLIER_MM
    data = tmp_path / "blunder.csv"
    meas.to_csv(data, index=False)
    h = file_hash(data)
    out = tmp_path / "res"
    t0 = time.perf_counter()
    code = run_cli(["identify", "--model", "xfyz", "--data", str(data), "--degree", "2",
                    "--robust", "--out", str(out), "--no-plots"], monkeypatch)
    elapsed = time.perf_counter() - t0
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert file_hash(data) == h
    written = sorted(p.name for p in out.iterdir())
    assert written == sorted([*DATA_FILES, "manifest.json", "solver_state.npz"])
    for needle in ("Solve", "residual RMS", "largest volumetric error",
                   "unidentifiable           none", "rejected readings        1",
                   str(out / "report.md")):
        assert needle in printed, needle
    resid = pd.read_csv(out / "residuals.csv")
    assert list(np.flatnonzero(resid["rejected"])) == [OUTLIER_INDEX]
    report = (out / "report.md").read_text()
    row = OUTLIER_INDEX + 2  # spreadsheet row: header = row 1
    assert f"| {row} | {meas.loc[OUTLIER_INDEX, 'station']} |" in report
    doc = json.loads((out / "result.json").read_text())
    assert doc["options"]["robust"] is True and doc["options"]["degree"] == 2
    assert doc["n_rejected"] == 1 and doc["data"] == str(data)
    # the stage record the speed benchmark splits the run by (benchmarks/compare_scipy.py):
    # every stage of the command, each measured once (they do not overlap: together no
    # longer than the command), the adequacy test a stage of its own and not in the
    # writing (it had been hidden in no stage at all)
    stages = doc["timings_s"]
    for name in ("reading the data", "building the model",
                 "start values and reading uncertainties", "building the problem", "solving",
                 "uncertainty and identifiability", "writing the tables",
                 "testing the model's adequacy"):
        assert sum(v for k, v in stages.items() if k.startswith(name)) > 0.0, (name, stages)
    assert sum(stages.values()) <= elapsed
    assert doc["adequacy"]["verdict"]
    # the blunder is out: the result agrees with the clean identification
    loaded = load_result(out)
    pts = case["plan"]
    got = loaded.predict(pts)
    ref = load_result(case["out"]).predict(pts)
    diff = (got[["dx_um", "dy_um", "dz_um"]] - ref[["dx_um", "dy_um", "dz_um"]]).abs()
    assert float(diff.to_numpy().max()) < 0.5


def test_identify_cli_bad_input_and_options_exit_2(case, tmp_path, monkeypatch, capsys):
    data = tmp_path / "d.csv"
    case["measurements"].drop(columns=["length"]).to_csv(data, index=False)
    out = tmp_path / "res"
    code = run_cli(["identify", "--model", "xfyz", "--data", str(data), "--out", str(out)],
                   monkeypatch)
    err = capsys.readouterr().err
    assert code == 2 and str(data) in err and "'length'" in err
    assert not out.exists()
    code = run_cli(["identify", "--model", "xfyz", "--data", str(case["data"]), "--out",
                    str(out), "--reject-k", "3"], monkeypatch)
    assert code == 2 and "--robust" in capsys.readouterr().err
    # an input inside the output folder (which would be replaced) is refused
    out2 = tmp_path / "prev"
    out2.mkdir()
    inside = out2 / "d.csv"
    inside.write_bytes(case["data"].read_bytes())
    code = run_cli(["identify", "--model", "xfyz", "--data", str(inside), "--out", str(out2)],
                   monkeypatch)
    assert code == 2 and inside.exists()
    assert not out.exists()


def test_identify_cli_solver_failure_exits_1(case, tmp_path, monkeypatch, capsys):
    import volcal.analysis.identify

    def fail(*args, **kwargs):
        raise SolverError("identification (joint) did not converge",
                          status="Maximum_Iterations_Exceeded")

    # the single fit the workflow layer dispatches to (volcal.workflow.single.fit imports
    # it at call time), so the failure travels the whole way up to the command
    monkeypatch.setattr(volcal.analysis.identify, "_identify", fail)
    out = tmp_path / "res"
    code = run_cli(["identify", "--model", "xfyz", "--data", str(case["data"]), "--out",
                    str(out)], monkeypatch)
    assert code == 1 and "Maximum_Iterations_Exceeded" in capsys.readouterr().err
    assert not out.exists() and os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "figure, draw, message",
    [
        ("draw_residuals", _fail_draw, "(?s)plotting failed:.*plot failed"),
        ("draw_correlations", _die_draw, "ended unexpectedly"),
    ],
    ids=["fails", "dies"],
)
def test_a_plot_failing_in_the_plotting_process_leaves_no_folder(
    case, tmp_path, monkeypatch, figure, draw, message
):
    """With the plots drawn by plotting children (as ``volcal identify`` does), a figure
    that fails there, or a child that ends without answering (killed mid-figure), fails
    the write with an error that says so (not a wait forever): nothing is renamed into
    place."""
    from volcal.outputs import figures
    from volcal.outputs.plot_process import PlotProcess

    monkeypatch.setattr(figures, figure, draw)
    pp = PlotProcess.start(workers=2)
    if pp is None:
        pytest.skip("no plotting process on this platform")
    try:
        with pytest.raises(RuntimeError, match=message):
            save_result(case["res"], tmp_path / "new", plotter=pp)
    finally:
        pp.close()
    assert list(tmp_path.iterdir()) == []


def test_plots_drawn_by_the_plotting_processes_equal_those_drawn_here(case, tmp_path):
    """The plotting children draw from the same data with the same code: every PNG is
    byte for byte the one this process draws without them (the module's result folder,
    written here without plotting children)."""
    from volcal.outputs.plot_process import PlotProcess

    here = case["out"]
    pp = PlotProcess.start(workers=2)
    if pp is None:
        pytest.skip("no plotting process on this platform")
    try:
        there = save_result(case["res"], tmp_path / "there", data_name="measurements.csv",
                            plotter=pp)
    finally:
        pp.close()
    pngs = sorted(p.name for p in here.glob("*.png"))
    assert len(pngs) == 5 and pngs == sorted(p.name for p in there.glob("*.png"))
    for name in pngs:
        assert (here / name).read_bytes() == (there / name).read_bytes(), name


def _framed_requests(case):
    """The module result's plot data, for the figures with a frame built ahead."""
    from volcal.outputs.figures import volumetric_frame_key
    from volcal.outputs.plots import saved_plot_requests

    reqs = saved_plot_requests(load_result(case["out"]))
    axes = case["machine"].spec.axes
    n = len(axes)
    keys = {
        # from the model alone, as volcal identify builds it before the solve
        "volumetric_map.png": volumetric_frame_key([(*a.travel, a.is_rotary) for a in axes]),
        "component_errors.png": ("component_errors", n),
        "correlations.png": ("correlations",),
        "residuals.png": ("residuals",),
        "residuals_vs_axes.png": ("residuals_vs_axes", n),
    }
    return [(keys[name], name, draw, data) for name, draw, data, _ in reqs if name in keys]


def test_a_figure_drawn_in_a_frame_built_ahead_is_the_same_picture(case, tmp_path):
    """A frame built ahead (figure, axes, styling and ticks, as a plotting child builds it
    while it waits) is taken by its figure, which is byte for byte the one in the result
    folder (drawn without a frame); a frame of another layout is left alone."""
    from volcal.outputs import figures

    framed = _framed_requests(case)
    assert len(framed) == 5
    for key, name, draw, data in framed:
        figures.prepare_frame(key)
        assert key in figures._FRAMES
        draw(data, tmp_path / name)
        assert key not in figures._FRAMES  # taken
        # the result folder's figure was drawn without a frame
        assert (tmp_path / name).read_bytes() == (case["out"] / name).read_bytes(), name
    other = ("component_errors", len(case["machine"].spec.axes) + 1)
    figures.prepare_frame(other)
    try:
        key, name, draw, data = framed[0]
        draw(data, tmp_path / "other.png")
        assert other in figures._FRAMES  # not this figure's layout: not used
        assert (tmp_path / "other.png").read_bytes() == (case["out"] / name).read_bytes()
    finally:
        figures._FRAMES.clear()


def test_a_plotting_child_builds_its_frames_while_it_waits_and_survives_a_failing_one(
    case, tmp_path
):
    """The calls a plotting child makes before its first request (its frames) are made
    one at a time, a failing one is skipped, and the figure then drawn on request takes
    its frame (the same picture); served here in a thread, so that the test knows when
    the frames are built."""
    import threading
    from multiprocessing import Pipe

    from volcal.outputs import figures
    from volcal.outputs.plot_process import _serve_requests

    key, name, draw, data = _framed_requests(case)[1]  # residuals.png
    assert key == ("residuals",)
    built = threading.Event()

    def fails():
        raise RuntimeError("no frame")

    here, there = Pipe()
    ahead = [(fails, ()), (figures.prepare_frame, (key,)), (built.set, ())]
    served = threading.Thread(target=_serve_requests, args=(there, ahead))
    served.start()
    try:
        assert built.wait(300)  # a bound against a hang, not a speed limit
        assert key in figures._FRAMES
        here.send((draw, (data, tmp_path / name)))
        assert here.recv() == ("ok", "")
        assert key not in figures._FRAMES
    finally:
        here.send(None)
        served.join()
        figures._FRAMES.clear()
    assert (tmp_path / name).read_bytes() == (case["out"] / name).read_bytes()


def test_frame_plan_gives_each_child_the_frames_of_the_figures_it_is_sent():
    """With two children the figures (in the order sent: those that need no covariance
    first, then by drawing cost) go volumetric map -> 0, residuals -> 1, component errors
    -> 0, correlations -> 1, residuals vs axes -> 1 (the least drawing queued first), so
    those are the frames each builds (the volumetric map's when its key is known); one
    child builds them all."""
    from volcal.outputs.figures import frame_plan, prepare_frame

    plan = frame_plan(4, 2)
    assert all(f is prepare_frame for child in plan for f, _ in child)
    assert [[args[0] for _, args in child] for child in plan] == [
        [("component_errors", 4)],
        [("residuals",), ("correlations",), ("residuals_vs_axes", 4)],
    ]
    vol = ("volumetric", 3, 800.0, 500.0)
    assert [args[0] for _, args in frame_plan(4, 2, vol)[0]] == [vol, ("component_errors", 4)]
    (one,) = frame_plan(3, 1, vol)
    assert [args[0][0] for _, args in one] == [
        "volumetric",
        "residuals",
        "component_errors",
        "correlations",
        "residuals_vs_axes",
    ]


def test_font_lookups_cached_give_the_same_pictures(case, tmp_path, monkeypatch):
    """A plotting child reads the font's tables once and looks a text's font files up
    once per font properties (plot_process._font_lookups_cached, matplotlib 3.11): the
    figures drawn so are byte for byte those of the result folder, drawn with
    matplotlib's own look-ups."""
    import matplotlib
    import matplotlib.text as mtext

    from volcal.outputs.plot_process import _font_lookups_cached

    manager = mtext.fontManager
    # both restored after the test
    monkeypatch.setattr(mtext, "get_font", mtext.get_font)
    monkeypatch.setattr(manager, "_find_fonts_by_props", manager._find_fonts_by_props)
    _font_lookups_cached()
    if not matplotlib.__version__.startswith("3.11."):
        assert mtext.get_font is matplotlib.font_manager.get_font  # left alone
        return
    assert mtext.get_font is not matplotlib.font_manager.get_font
    prop = mtext.FontProperties(size=9)
    files = manager._find_fonts_by_props(prop)
    assert manager._find_fonts_by_props(prop.copy()) is files  # looked up once
    assert manager._find_fonts_by_props(mtext.FontProperties(size=10)) is not files
    font = mtext.get_font(files)
    assert font.get_sfnt_table("head") is font.get_sfnt_table("head")  # read once
    for _, name, draw, data in _framed_requests(case):
        draw(data, tmp_path / name)
        assert (tmp_path / name).read_bytes() == (case["out"] / name).read_bytes(), name


def test_plots_sent_before_the_uncertainty_stage_are_the_same_files(case, tmp_path):
    """The residual and volumetric plots sent to the plotting children once the solve has
    ended (before the result, hence its folder, exists: drawn into memory, written when
    the folder is made) are byte for byte those drawn from the finished result; the other
    three are drawn as before, and each figure is drawn once."""
    from volcal.analysis.identify import Solved
    from volcal.outputs.plot_process import PlotProcess
    from volcal.outputs.plots import hold_solved_plots, solved_plot_requests

    res = case["res"]
    solved = Solved(res.machine, res.error_model, res.theta, res.residuals)
    assert [n for n, *_ in solved_plot_requests(solved)] == ["volumetric_map.png",
                                                             "residuals.png"]
    pp = PlotProcess.start(workers=2)
    if pp is None:
        pytest.skip("no plotting process on this platform")
    try:
        held = hold_solved_plots(pp, solved)
        # one to each child (the least drawing queued), as the frames built ahead expect
        assert held == {"volumetric_map.png": 0, "residuals.png": 1}
        there = save_result(res, tmp_path / "there", data_name="measurements.csv",
                            plotter=pp, held=held)
        assert pp._pending == [0, 0]  # every request answered: 5 figures and 2 writes
    finally:
        pp.close()
    here = case["out"]
    pngs = sorted(p.name for p in here.glob("*.png"))
    assert len(pngs) == 5 and pngs == sorted(p.name for p in there.glob("*.png"))
    for name in pngs:
        assert (here / name).read_bytes() == (there / name).read_bytes(), name


def test_a_plotting_child_of_a_process_without_matplotlib_draws_the_same_files(case,
                                                                              tmp_path):
    """A plotting child whose parent never imported matplotlib (as in ``volcal identify``)
    imports it without building its artists' ``set`` docstrings (a quarter of the
    import): the five figures of the result, drawn there from the saved folder, are byte
    for byte those drawn in this process, and the child's docstrings were indeed left
    out while this process's are whole."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import sys
        from pathlib import Path
        from volcal.outputs.plot_process import PlotProcess
        from volcal.outputs.plots import saved_plot_requests
        from volcal.outputs.results import load_result

        def docs(path):
            import matplotlib.lines
            Path(path).write_text(str(len(matplotlib.lines.Line2D.set.__doc__ or "")))

        assert "matplotlib" not in sys.modules
        pp = PlotProcess.start(workers=2)
        out = Path({str(tmp_path)!r})
        for name, draw, data, cost in saved_plot_requests(load_result({str(case["out"])!r})):
            pp.draw(draw, data, out / name, cost=cost)
        pp.draw(docs, out / "docs.txt", child=0)
        pp.wait()
        pp.close()
        assert "matplotlib" not in sys.modules
    """)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=600)
    for name in PLOT_FILES:
        assert (tmp_path / name).read_bytes() == (case["out"] / name).read_bytes(), name
    import matplotlib.lines

    here = len(matplotlib.lines.Line2D.set.__doc__)
    assert int((tmp_path / "docs.txt").read_text()) < 1000 < here


def test_on_solved_gets_the_estimates_and_residuals_of_the_result(case):
    """identify's on_solved is called once, after the solve and before the uncertainty
    stage, with the parameters and the residuals (station, residual, normalised residual,
    rejected) the result then holds; not for the classic pipeline (another pipeline)."""
    import volcal
    from volcal.base import progress

    seen, stages = [], []

    def on_solved(solved):
        seen.append(solved)
        stages.append(progress.timings())  # the stages ended when it was called

    progress.reset_timings()
    res = volcal.identify(case["machine"], case["data"], error_model=case["em"],
                          on_solved=on_solved)
    assert len(seen) == 1
    # after the solve, before the uncertainty stage (whose covariance it must not wait for)
    assert "solving" in stages[0] and "uncertainty and identifiability" not in stages[0]
    assert "uncertainty and identifiability" in progress.timings()
    solved = seen[0]
    assert solved.machine is res.machine and solved.error_model is res.error_model
    np.testing.assert_array_equal(solved.theta, res.theta)
    cols = ["station", "residual_um", "normalised_residual", "rejected"]
    assert list(solved.residuals.columns) == cols
    pd.testing.assert_frame_equal(solved.residuals.reset_index(drop=True),
                                  res.residuals[cols].reset_index(drop=True))
    np.testing.assert_allclose(res.theta, case["res"].theta, rtol=0, atol=1e-12)
    seen.clear()
    volcal.identify(case["machine"], case["data"], error_model=case["em"],
                    strategy="classic", on_solved=on_solved)
    assert seen == []


def test_printed_positions_are_described_from_their_grid():
    """The printed error-motion tables say where their rows are from the rows
    themselves: a tenth of the travel for the 41-row table (every fourth row), a quarter
    for a 5-row table, and not evenly spaced for 25 rows (24 steps do not split into
    ten); the peak-to-peak table and the component table come from one sweep."""
    machine = Machine.from_model("xfyz")
    em = ErrorModel(machine.spec, default=ErrorForm("poly", 2))
    theta = draw_true_parameters(machine, em, np.random.default_rng(8), 30.0)
    texts = {}
    for n in (41, 5, 25):
        comp = results.component_error_table(em, theta, n=n)
        tables = dict(results.error_motions_at_positions(comp))
        texts[n] = {a: results.positions_text(t) for a, t in tables.items()}
    for a in machine.spec.axes:
        lo, hi = a.travel
        assert texts[41][a.name] == f"every {(hi - lo) / 10:g} mm (a tenth of the travel)"
        assert texts[5][a.name] == f"every {(hi - lo) / 4:g} mm (a quarter of the travel)"
        assert texts[25][a.name].startswith("at the positions listed (not evenly spaced")
    # the peak-to-peak values on the 41 positions are the component table's extremes
    comp = results.component_error_table(em, theta, n=41)
    pp = results.error_motion_table(em, theta, n=41)
    for r in pp.itertuples():
        col = comp.loc[comp["axis"] == r.axis, f"{r.error_motion}_{r.unit}"]
        assert r.peak_to_peak_in_unit == pytest.approx(col.max() - col.min(), abs=1e-9)


def test_identify_frees_the_ipopt_graph_and_builds_it_again(case):
    """release_graph (what `volcal identify` asks for): the same result, bit for bit,
    without the IPOPT solver and the CasADi graph of every reading once the fit has
    converged; the identifier builds them again to solve again (and stays at the
    answer).  No result holds what the chunked evaluation kept between its passes."""
    import volcal
    from volcal.measurement.tables import load_measurements

    args = (case["machine"], case["data"])
    kept = volcal.identify(*args, error_model=case["em"], solver="ipopt")
    freed = volcal.identify(*args, error_model=case["em"], solver="ipopt", release_graph=True)
    np.testing.assert_array_equal(freed.theta, kept.theta)
    np.testing.assert_array_equal(freed.cov_theta, kept.cov_theta)
    pd.testing.assert_frame_equal(freed.residuals, kept.residuals)
    pd.testing.assert_frame_equal(freed.stations, kept.stations)
    assert kept.identifier.solver is not None and "_graph" in kept.identifier.problem.__dict__
    ider = freed.identifier
    assert ider.solver is None and "_graph" not in ider.problem.__dict__
    # nor do the results hold the passes the chunked evaluation kept for the solve
    for res in (kept, freed):
        chunked = res.identifier.problem.__dict__["chunked"]
        assert chunked._pass_kept is None and not chunked._g_kept
    meas = load_measurements(case["data"], case["machine"].spec)
    p = ider.problem.pack_data(meas.q_internal, meas.tool, meas.length, freed.state.weights)
    x, outcomes, _, _ = ider.run("joint", freed.state.x, p)
    assert ider.solver is not None and outcomes[-1].success
    np.testing.assert_allclose(x, freed.state.x, rtol=1e-7, atol=1e-9)
