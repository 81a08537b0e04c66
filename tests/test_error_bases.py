"""Error bases (volcal.model.errors): Fourier for rotary axes, cubic B-splines, their declaration in
model files, the API and the command line, the result round trip, and ``degree="auto"``
(volcal.workflow.orders) on simulated data."""
from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.model.errors import ErrorForm, ErrorModel, bspline, fourier, parse_basis
from volcal.model.spec import (
    AxisSpec,
    MachineSpec,
    load_model_file,
    machine_from_dict,
    resolve_model,
    spec_to_dict,
)

CXYZ = """
name = "cxyz_bases"
description = "C table on X, Y and Z on the tool side (test model for error bases)"

[[axis]]
name = "C"
kind = "rotary"
direction = "+z"
branch = "workpiece"
travel = [-180.0, 180.0]
{c_extra}

[[axis]]
name = "X"
kind = "linear"
direction = "+x"
branch = "workpiece"
travel = [0.0, 600.0]
{x_extra}

[[axis]]
name = "Y"
kind = "linear"
direction = "+y"
branch = "tool"
travel = [0.0, 400.0]

[[axis]]
name = "Z"
kind = "linear"
direction = "+z"
branch = "tool"
travel = [-400.0, 0.0]
"""


def model_text(c_extra: str = "", x_extra: str = "") -> str:
    return CXYZ.format(c_extra=c_extra, x_extra=x_extra)


def load(tmp_path, text: str):
    p = tmp_path / "m.toml"
    p.write_text(text, encoding="utf-8")
    return load_model_file(p)


@pytest.fixture(scope="module")
def trunnion():
    return resolve_model("trunnion_ac")


def _sx_columns(em: ErrorModel, k: int, x: np.ndarray) -> np.ndarray:
    xs = ca.SX.sym("x")
    f = ca.Function("b", [xs], [ca.vertcat(*em._basis_columns(k, xs))])
    return np.array(f.map(len(x))(x)).T


# --------------------------------------------------------------------------------------
# the bases


@pytest.mark.parametrize("form", [ErrorForm("poly", 4), ErrorForm("fourier", 3),
                                  ErrorForm("bspline", segments=1),
                                  ErrorForm("bspline", segments=5),
                                  ErrorForm("table", knots=(-180.0, -30.0, 90.0, 180.0)),
                                  ErrorForm("constant")])
@pytest.mark.parametrize("axis", ["C", "A"])
def test_numpy_and_casadi_bases_agree(trunnion, form, axis):
    if form.kind == "table" and axis == "A":
        form = ErrorForm("table", knots=(-120.0, -50.0, 0.0, 30.0))
    em = ErrorModel(trunnion, {axis: form})
    k = [s.name for s in em.errors].index(f"EX{axis}")
    lo, hi, _ = em._axis_range(em.errors[k])
    x = np.linspace(lo - 0.3, hi + 0.3, 401)  # beyond the travel too
    num = np.column_stack([np.broadcast_to(c, x.shape) for c in em._basis_columns(k, x)])
    assert num.shape[1] == form.n_params
    assert np.abs(_sx_columns(em, k, x) - num).max() < 1e-13
    # the lowered values function agrees with the numpy evaluation
    th = np.random.default_rng(0).normal(size=em.n_params)
    q = np.zeros((len(x), len(trunnion.axes)))
    q[:, trunnion.axis_names.index(axis)] = x
    f = em.values_function()
    e_sx = np.array(f.map(len(x))(q.T, th)).T
    assert np.abs(e_sx - em.values(q, th)).max() < 1e-12


def test_basis_rows_of_chosen_errors(trunnion):
    """``basis(q, errors)`` gives those errors' rows of the whole basis, in the order asked,
    and the whole basis reproduces the error values (evaluated column by column by
    ``values``) with each parameter's column in its own error's row only."""
    em = ErrorModel(trunnion, {"C": ErrorForm("fourier", 3), "A": ErrorForm("bspline", segments=4),
                               "X": ErrorForm("poly", 3)})
    rng = np.random.default_rng(5)
    q = rng.uniform(-1.0, 1.0, size=(57, len(trunnion.axes)))
    th = rng.normal(size=em.n_params)
    B = em.basis(q)
    assert np.abs(np.einsum("nkp,p->nk", B, th) - em.values(q, th)).max() < 1e-12
    own = np.zeros((em.n_errors, em.n_params), bool)
    own[em.param_error_arr, np.arange(em.n_params)] = True
    assert not np.any(B[:, ~own])
    for rows in ([3], [em.n_errors - 1, 0, 7], list(range(em.n_errors))[::-2]):
        assert np.array_equal(em.basis(q, rows), B[:, rows, :])
    assert em.basis(q, []).shape == (57, 0, em.n_params)


def test_fourier_reproduces_a_harmonic_function_exactly(trunnion):
    em = ErrorModel(trunnion, {"C": ErrorForm("fourier", 3)})
    f = lambda x: 2e-3 + 1e-3 * np.cos(x) - 4e-3 * np.sin(2 * x) + 5e-4 * np.cos(3 * x + 0.3)  # noqa: E731
    th = em.fit_functions({"EZC": f})
    x = np.deg2rad(np.linspace(-180, 180, 73))
    q = np.zeros((len(x), 5))
    q[:, 0] = x
    k = [s.name for s in em.errors].index("EZC")
    assert np.abs(em.values(q, th)[:, k] - f(x)).max() < 1e-15
    names = [n for n in em.param_names if n.startswith("EZC_")]
    assert names == ["EZC_0", "EZC_c1", "EZC_s1", "EZC_c2", "EZC_s2", "EZC_c3", "EZC_s3"]
    v = dict(zip(em.param_names, th))
    assert v["EZC_s2"] == pytest.approx(-4e-3, abs=1e-15)
    assert v["EZC_c3"] == pytest.approx(5e-4 * np.cos(0.3), abs=1e-15)
    # periodic: -180 deg and 180 deg are the same pose
    assert np.allclose(fourier(np.array([-np.pi]), 3), fourier(np.array([np.pi]), 3))


def test_bspline_partition_of_unity_and_cubics():
    x = np.linspace(-50.0, 650.0, 701)
    for m in (1, 2, 3, 7):
        B = np.array(bspline(x, 0.0, 600.0, m))
        assert B.shape == (m + 3, len(x))
        assert np.abs(B.sum(axis=0) - 1).max() < 1e-12
        inside = (x >= 0) & (x <= 600)
        assert B[:, inside].min() > -1e-14  # non-negative on the travel
        g = 1 + 0.01 * x - 3e-5 * x ** 2 + 4e-8 * x ** 3
        c = np.linalg.lstsq(B.T, g, rcond=None)[0]
        assert np.abs(B.T @ c - g).max() < 1e-12
    # local support: with 6 segments, b0 vanishes from the second segment on
    B = np.array(bspline(np.array([150.0, 400.0]), 0.0, 600.0, 6))
    assert B[0, 0] == 0.0 and B[0, 1] == 0.0 and B[8, 0] == 0.0


def test_default_forms(trunnion):
    em = ErrorModel(trunnion)
    forms = {s.name: f for s, f in zip(em.errors, em.forms)}
    assert trunnion.axis("C").full_turn and not trunnion.axis("A").full_turn
    assert forms["EXC"] == ErrorForm("fourier", 3)  # full turn: periodic
    assert forms["EXA"] == ErrorForm("poly", 3)     # partial turn: Legendre
    assert forms["EXX"] == ErrorForm("poly", 3)
    assert forms["EX0C"].kind == "constant"
    # the default degree carries over to the Fourier series
    em5 = ErrorModel(trunnion, default=ErrorForm("poly", 5))
    assert em5.forms[[s.name for s in em5.errors].index("EBC")] == ErrorForm("fourier", 5)
    # an explicit form wins
    em2 = ErrorModel(trunnion, {"C": ErrorForm("poly", 2)})
    assert em2.forms[[s.name for s in em2.errors].index("EBC")] == ErrorForm("poly", 2)


def test_constraints_and_orders_with_new_bases(trunnion):
    em = ErrorModel(trunnion, {"X": ErrorForm("bspline", segments=4)}, datum="iso230")
    C, labels = em.constraints()
    assert C.shape[1] == em.n_params and len(labels) == C.shape[0]
    assert any("EXC" in lab for lab in labels) and any("EYX" in lab for lab in labels)
    # parameters satisfying the datum: EYX (straightness) zero at both ends of X
    th = np.random.default_rng(2).normal(size=em.n_params)
    th -= np.linalg.pinv(C) @ (C @ th)
    names = [s.name for s in em.errors]
    for xv in (-300.0, 300.0):
        q = np.zeros((1, 5))
        q[0, 2] = xv
        assert abs(em.values(q, th)[0, names.index("EYX")]) < 1e-12
    order = dict(zip(em.param_names, em.param_order))
    assert order["EXC_c2"] == order["EXC_s2"] == 2 and order["EXA_3"] == 3
    assert order["EXX_b5"] == 0


def test_bad_forms(trunnion):
    with pytest.raises(InputError, match="rotary axes only"):
        ErrorModel(trunnion, {"X": ErrorForm("fourier", 2)})
    with pytest.raises(InputError, match="segments"):
        ErrorModel(trunnion, {"X": ErrorForm("bspline", segments=0)})
    with pytest.raises(InputError, match="degree"):
        ErrorModel(trunnion, {"C": ErrorForm("fourier", -1)})
    with pytest.raises(InputError, match="unknown basis kind"):
        ErrorForm("spline")


# --------------------------------------------------------------------------------------
# declarations


def test_model_file_basis_declarations(tmp_path):
    spec = load(tmp_path, model_text(
        c_extra='basis = { kind = "fourier", degree = 2 }\n'
                'error_basis = { EZC = { kind = "fourier", degree = 4 } }',
        x_extra='basis = { kind = "bspline", segments = 3 }\n'
                '[axis.error_basis.EXX]\nkind = "table"\nknots = [0.0, 300, 600.0]'))
    assert spec.axis("C").basis == ErrorForm("fourier", 2)
    assert dict(spec.axis("C").error_basis) == {"EZC": ErrorForm("fourier", 4)}
    em = ErrorModel(spec)
    forms = {s.name: f for s, f in zip(em.errors, em.forms)}
    assert forms["EXC"] == ErrorForm("fourier", 2) and forms["EZC"] == ErrorForm("fourier", 4)
    assert forms["EYX"] == ErrorForm("bspline", segments=3)
    assert forms["EXX"] == ErrorForm("table", knots=(0.0, 300.0, 600.0))
    assert forms["EXY"] == ErrorForm("poly", 3)
    assert "EYX_b5" in em.param_names and "EXX@300" in em.param_names
    # the API overrides the file: axis name, then error name
    em2 = ErrorModel(spec, {"C": ErrorForm("poly", 1), "EXX": ErrorForm("poly", 2)})
    forms2 = {s.name: f for s, f in zip(em2.errors, em2.forms)}
    assert forms2["EZC"] == ErrorForm("poly", 1) and forms2["EXX"] == ErrorForm("poly", 2)
    # round trip, and the bases are not part of the topology's fingerprint
    assert machine_from_dict(spec_to_dict(spec)) == spec
    plain = load(tmp_path, model_text())
    assert plain.fingerprint() == spec.fingerprint() and plain != spec


@pytest.mark.parametrize("extra, patterns", [
    ('basis = { kind = "wavelet" }', [r"basis\.kind", r"wavelet", r"fourier"]),
    ('basis = { kind = "fourier", degree = "3" }', [r"basis\.degree", r"integer"]),
    ('basis = { kind = "fourier", degree = 2.0 }', [r"basis\.degree", r"integer"]),
    ('basis = { kind = "fourier", degree = -1 }', [r"'basis'", r">= 0"]),
    ('basis = { kind = "poly", segments = 4 }', [r"unknown key", r"segments", r"degree"]),
    ('basis = "fourier"', [r"'basis'", r"expected a table"]),
    ('error_basis = { EQC = { kind = "poly" } }', [r"error_basis", r"EQC"]),
    ('error_basis = { EZC = { kind = "table", knots = [0.0, "1"] } }',
     [r"error_basis\.EZC\.knots", r"number"]),
    ('error_basis = { EZC = { kind = "table", knots = [10.0, 0.0] } }',
     [r"error_basis\.EZC", r"increasing"]),
])
def test_bad_basis_declarations_name_the_key(tmp_path, extra, patterns):
    import re

    with pytest.raises(InputError) as info:
        load(tmp_path, model_text(c_extra=extra))
    msg = str(info.value)
    assert "axis C" in msg and "m.toml" in msg
    for pat in patterns:
        assert re.search(pat, msg), (pat, msg)


def test_fourier_on_a_linear_axis_in_a_file(tmp_path):
    with pytest.raises(InputError, match=r"axis X.*rotary axes only"):
        load(tmp_path, model_text(x_extra='basis = { kind = "fourier", degree = 2 }'))


def test_parse_basis():
    assert parse_basis("C=fourier:3") == ("C", ErrorForm("fourier", 3))
    assert parse_basis("X=bspline:6") == ("X", ErrorForm("bspline", segments=6))
    assert parse_basis("EXX=table:0,200,400") == ("EXX", ErrorForm("table",
                                                                   knots=(0.0, 200.0, 400.0)))
    assert parse_basis("EBX=constant") == ("EBX", ErrorForm("constant"))
    assert parse_basis("Y=poly") == ("Y", ErrorForm("poly", 3))
    for bad in ("C", "C=cheb:3", "X=bspline:x", "X=poly:-2", "X=bspline:0", "X=constant:2"):
        with pytest.raises(InputError, match="--basis"):
            parse_basis(bad)


def test_spec_api_matches_files():
    ax = AxisSpec("C", "rotary", "+z", "workpiece", (0.0, 360.0),
                  basis=ErrorForm("fourier", 2, knots=(1.0,)))
    assert ax.basis.knots == ()  # fields a kind does not use are reset
    spec = MachineSpec("c_only", (ax,))
    assert machine_from_dict(spec_to_dict(spec)) == spec
    assert spec_to_dict(spec)["axis"][0]["basis"] == {"kind": "fourier", "degree": 2}


# --------------------------------------------------------------------------------------
# identification: result round trip and degree="auto"


def _simulate(machine, em, theta, plan, tools, seed=3, n_stations=4):
    from volcal.measurement.plans import default_stations
    from volcal.measurement.simulate import simulate

    stations = default_stations(machine.spec, n_stations, seed=seed, tools=tools)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return simulate(machine, em, theta, stations, plan, tools, "paper002", seed)


@pytest.mark.filterwarnings("ignore:.*tool offset")
def test_result_round_trip_with_fourier_and_bspline(tmp_path):
    from volcal.analysis.identify import identify
    from volcal.measurement.plans import grid_plan
    from volcal.measurement.simulate import draw_true_parameters
    from volcal.model.machine import Machine
    from volcal.outputs.results import load_result, save_result

    spec = load(tmp_path, model_text(c_extra='basis = { kind = "fourier", degree = 2 }',
                                     x_extra='basis = { kind = "bspline", segments = 2 }'))
    machine = Machine.from_model(spec)
    em = ErrorModel(spec)
    theta = draw_true_parameters(machine, em, np.random.default_rng(1), 20.0)
    tools = np.zeros((1, 3))
    plan = grid_plan(spec, {"C": 6, "X": 5, "Y": 2, "Z": 2})
    sim = _simulate(machine, em, theta, plan, tools)
    res = identify(machine, sim.measurements, error_model=em)
    assert any(n.startswith("EXC_c2") for n in res.error_model.param_names)
    out = save_result(res, tmp_path / "res", plots=False)
    loaded = load_result(out)
    assert loaded.error_model.forms == res.error_model.forms
    assert loaded.error_model.param_names == res.error_model.param_names
    assert loaded.spec == spec  # the basis declarations travel with the model document
    pts = plan.head(20)
    got = loaded.predict(pts, with_uncertainty=False)
    q = machine.axis_to_internal(pts[machine.axis_names].to_numpy(float))
    ref = res.predict(q, with_uncertainty=False)
    assert np.allclose(got[["dx_um", "dy_um", "dz_um"]].to_numpy(),
                       ref[["dx_um", "dy_um", "dz_um"]].to_numpy(), atol=1e-9)
    report = (out / "report.md").read_text()
    assert "Fourier series, harmonics 1..2" in report and "cubic B-spline, 2 segments" in report


@pytest.fixture(scope="module")
def xfyz_case():
    from volcal.measurement.plans import grid_plan
    from volcal.model.machine import Machine

    machine = Machine.from_model("xfyz")
    plan = grid_plan(machine.spec, {"X": 9, "Y": 2, "Z": 2})
    return machine, plan


def _truth(machine, high: bool) -> tuple[ErrorModel, np.ndarray]:
    """Linear error motions everywhere (a small, datum-consistent field); with ``high``
    also a 5th-order positioning and straightness error of X of several um."""
    from volcal.measurement.simulate import draw_true_parameters

    em = ErrorModel(machine.spec, {"X": ErrorForm("poly", 5)}, default=ErrorForm("poly", 1))
    theta = draw_true_parameters(machine, em, np.random.default_rng(5), 20.0)
    for name in [n for n in em.param_names if n.startswith(("EXX_", "EYX_", "EZX_"))]:
        if int(name.rsplit("_", 1)[1]) >= 2:
            theta[em.param_names.index(name)] = 0.0
    if high:
        s = lambda x: 2 * x / 800.0 - 1  # noqa: E731
        theta += em.fit_functions({"EXX": lambda x: 6e-3 * np.sin(3.2 * s(x)),
                                   "EYX": lambda x: 4e-3 * np.cos(3.0 * s(x))})
    return em, theta


@pytest.mark.filterwarnings("ignore:.*tool offset")
@pytest.mark.parametrize("high", [True, False])
def test_degree_auto_follows_the_truth(xfyz_case, tmp_path, high):
    from volcal.outputs.results import save_result
    from volcal.workflow import identify

    machine, plan = xfyz_case
    em_true, theta = _truth(machine, high)
    sim = _simulate(machine, em_true, theta, plan, np.zeros((1, 3)))
    res = identify(machine, sim.measurements, degree="auto")
    sel = res.order_selection
    chosen = {s.axis: f.degree for s, f in zip(res.error_model.errors, res.error_model.forms)
              if s.kind == "component"}
    if high:
        assert chosen["X"] >= 4, sel
    else:
        assert chosen["X"] <= 2, sel
    assert chosen["Y"] <= 2 and chosen["Z"] <= 2
    # the criterion's values per candidate: the chosen one is the smallest of its sweep
    assert {"axis", "order", "value", "chi2", "k", "chosen"} <= set(sel.columns)
    last = sel[(sel["sweep"] == sel["sweep"].max()) & (sel["axis"] == "X")]
    assert last.loc[last["chosen"], "value"].min() == pytest.approx(last["value"].min())
    assert (sel["criterion"] == "bic").all()
    assert any("BIC" in n for n in res.notes)
    if high:
        out = save_result(res, tmp_path / "auto", plots=False)
        table = pd.read_csv(out / "order_selection.csv")
        assert len(table) == len(sel)
        assert "Orders chosen from the data" in (out / "report.md").read_text()


@pytest.mark.filterwarnings("ignore:.*tool offset")
def test_degree_auto_cross_validation(xfyz_case):
    from volcal.measurement.plans import grid_plan
    from volcal.workflow.orders import select_orders

    machine, _ = xfyz_case
    em_true, theta = _truth(machine, True)
    # held-out poses must leave every axis position measured in each training set
    plan = grid_plan(machine.spec, {"X": 9, "Y": 3, "Z": 3})
    sim = _simulate(machine, em_true, theta, plan, np.zeros((1, 3)))
    res = select_orders(machine, sim.measurements, criterion="cv", folds=3,
                        candidates={"poly": (1, 5)})
    sel = res.order_selection
    assert (sel["criterion"] == "cv").all()
    x = sel[sel["axis"] == "X"].drop_duplicates("order").set_index("order")["value"]
    assert x[5] < x[1]  # held-out readings are predicted better by the higher order
    assert res.error_model.forms[0] == ErrorForm("poly", 5)


@pytest.mark.filterwarnings("ignore:.*tool offset")
def test_cli_basis_and_degree_auto(xfyz_case, tmp_path, monkeypatch, capsys):
    import json

    import volcal.cli.main

    monkeypatch.setattr(volcal.cli.main, "_COMMANDS", ["volcal.cli.commands.identify"])
    machine, plan = xfyz_case
    em_true, theta = _truth(machine, False)
    data = tmp_path / "m.csv"
    _simulate(machine, em_true, theta, plan, np.zeros((1, 3))).measurements.to_csv(
        data, index=False)
    out = tmp_path / "res"
    code = volcal.cli.main.main(["identify", "--model", "xfyz", "--data", str(data), "--out",
                            str(out), "--no-plots", "--degree", "auto",
                            "--basis", "X=bspline:2", "--basis", "EXY=table:0,250,500"])
    assert code == 0, capsys.readouterr()
    doc = json.loads((out / "result.json").read_text())
    forms = {f["error"]: f for f in doc["error_model"]["forms"]}
    assert forms["EYX"]["kind"] == "bspline" and forms["EXY"]["kind"] == "table"
    assert doc["options"]["degree"] == "auto"
    table = pd.read_csv(out / "order_selection.csv")
    assert set(table.loc[table["axis"] == "X", "kind"]) == {"bspline"}
    for argv, needle in ((["--basis", "X=fourier:2"], "rotary axes only"),
                         (["--degree", "three"], "--degree"),
                         (["--order-criterion", "cv"], "--degree auto"),
                         (["--basis", "Q=poly:2"], "unknown")):
        code = volcal.cli.main.main(["identify", "--model", "xfyz", "--data", str(data), "--out",
                                str(tmp_path / "bad"), "--no-plots", *argv])
        assert code == 2 and needle in capsys.readouterr().err, argv


@pytest.mark.parametrize("model", ["mcv754_wxyzt", "trunnion_ac", "head_bc"])
def test_values_and_apply_basis_equal_the_dense_basis(model):
    """ErrorModel.values and apply_basis work column by column without forming B(q)
    (N, n_errors, n_params); they must equal the products with the dense basis, for every
    family of basis (Legendre, Fourier on full-turn axes, B-splines, tables of hat
    functions, constants)."""
    from volcal.model.errors import ErrorForm, ErrorModel
    from volcal.model.machine import Machine

    machine = Machine.from_model(model)
    rng = np.random.default_rng(5)
    lo = np.array([a.travel[0] for a in machine.spec.axes], float)
    hi = np.array([a.travel[1] for a in machine.spec.axes], float)
    q = machine.axis_to_internal(lo + rng.uniform(size=(40, len(lo))) * (hi - lo))
    first, second = machine.spec.axes[0], machine.spec.axes[1]
    knots = tuple(np.linspace(second.travel[0], second.travel[1], 5))
    for forms, default in (
        (None, ErrorForm("poly", 3)),  # Fourier on the full-turn axes of the 5-axis models
        (
            {
                first.name: ErrorForm("bspline", segments=4),
                second.name: ErrorForm("table", knots=knots),
            },
            ErrorForm("poly", 2),
        ),
        (None, ErrorForm("constant")),
    ):
        em = ErrorModel(machine.spec, forms, default=default)
        B = em.basis(q)
        th = rng.normal(size=em.n_params)
        A = rng.normal(size=(len(q), 3, em.n_errors))
        assert np.allclose(em.values(q, th), np.einsum("nkp,p->nk", B, th), atol=1e-12)
        assert np.allclose(em.apply_basis(A, q), A @ B, atol=1e-12)
