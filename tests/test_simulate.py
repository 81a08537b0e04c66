"""The simulator (volcal.measurement.simulate), measurement plans
(volcal.measurement.plans) and `volcal simulate`.

The forward kinematics used as reference here is written from the conventions of
volcal.model.symbolic.chain (docstring and _axis_factors) with plain numpy, independently of the
SymPy/CasADi pipeline the simulator uses.
"""
from __future__ import annotations

import json
import warnings
import zlib

import numpy as np
import pandas as pd
import pytest

from volcal.base.exceptions import InputError
from volcal.cli import main as cli
from volcal.measurement.budget import Budget, Source, load_budget
from volcal.measurement.plans import (
    check_plan,
    default_stations,
    diagonal_plan,
    grid_plan,
    line_plan,
    nominal_points,
    plan_from_csv,
)
from volcal.measurement.simulate import (
    SIMULATION_FILES,
    Simulation,
    draw_true_parameters,
    example,
    load_true_parameters,
    max_volumetric_error_um,
    parse_tools,
    save_simulation,
    simulate,
)
from volcal.measurement.tables import DataWarning, load_measurements, load_stations
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine
from volcal.model.spec import bundled_models

# paper 000, Table 5, calculated values (mm)
TABLE5 = {
    "LT1": (-154.799406, 125.978808, -471.460113),
    "LT2": (-143.324882, 328.559001, -471.386505),
    "LT3": (862.105512, 291.242899, -340.459834),
    "LT4": (833.3820, 103.1588, -340.4466),
    "LT5": (891.307748, 152.634701, -507.868235),
    "LT6": (885.579601, 154.917244, -507.865002),
}


# ---------------------------------------------------------------------------------------
# independent numpy forward kinematics (exact rigid-body composition)


def _rot(i: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    if i == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if i == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _H(R=None, t=None) -> np.ndarray:
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def _small(w, inverse=False) -> np.ndarray:
    R = _rot(0, w[0]) @ _rot(1, w[1]) @ _rot(2, w[2])  # Rx(a) Ry(b) Rz(c)
    return _H(R.T if inverse else R)


def fk(spec, q: np.ndarray, t: np.ndarray, err: dict[str, float]) -> np.ndarray:
    """Actual tool point (mm) for internal axis positions q (mm, rad), tool offset t (mm)
    and error values err (name -> mm / rad; absent names are zero)."""
    T = np.eye(4)
    for axis, qa in zip(spec.axes, q):
        n = axis.name
        g = lambda name: err.get(name, 0.0)  # noqa: E731
        delta = np.array([g(f"EX{n}"), g(f"EY{n}"), g(f"EZ{n}")])
        eps = np.array([g(f"EA{n}"), g(f"EB{n}"), g(f"EC{n}")])
        i = axis.dir_index
        sign = axis.dir_sign if axis.branch == "tool" else -axis.dir_sign
        if axis.kind == "linear":
            om = np.array([g(f"EA0{n}"), g(f"EB0{n}"), g(f"EC0{n}")])
            move = np.zeros(3)
            move[i] = sign * qa
            A = _small(om) @ _H(t=move) @ _small(om, True) @ _H(t=delta) @ _small(eps)
        else:
            c = np.array(axis.center, float)
            lt = np.array([g(f"EX0{n}"), g(f"EY0{n}"), g(f"EZ0{n}")])
            lr = np.array([g(f"EA0{n}"), g(f"EB0{n}"), g(f"EC0{n}")])
            A = (_H(t=c) @ _H(t=delta) @ _small(eps) @ _H(t=-c)
                 @ _H(t=c + lt) @ _small(lr) @ _H(R=_rot(i, sign * qa)) @ _small(lr, True)
                 @ _H(t=-c - lt))
        if axis.branch == "workpiece":
            A = np.linalg.inv(A)
        T = T @ A
    # the tool's zero position and orientation relative to the last axis
    g = lambda name: err.get(name, 0.0)  # noqa: E731
    T = T @ _H(t=np.array([g("EX0T"), g("EY0T"), g("EZ0T")])) \
        @ _small(np.array([g("EA0T"), g("EB0T"), g("EC0T")]))
    return (T @ np.append(t, 1.0))[:3]


def _random_plan(spec, n, rng) -> pd.DataFrame:
    return pd.DataFrame({a.name: rng.uniform(*a.travel, n) for a in spec.axes})


def _random_theta(em: ErrorModel, rng) -> np.ndarray:
    """Large errors (about 50 um / 1 mrad per coefficient) so that second-order terms
    (about 1 um at 1 m) are far above the comparison tolerance."""
    scale = np.where(np.array(em.param_units) == "mm", 0.05, 1e-3)
    return rng.normal(size=em.n_params) * scale


@pytest.fixture(scope="module")
def mcv():
    return example("mcv754")


# ---------------------------------------------------------------------------------------
# (1) noise-free lengths against the independent kinematics, every bundled model


@pytest.mark.parametrize("model", sorted(bundled_models()))
def test_noise_free_lengths_equal_independent_exact_kinematics(model):
    rng = np.random.default_rng(zlib.crc32(model.encode()))
    machine = Machine.from_model(model)
    spec = machine.spec
    em = ErrorModel(spec)
    theta = _random_theta(em, rng)
    plan = _random_plan(spec, 12, rng)
    tools = np.array([[0.0, 0.0, 0.0], rng.uniform(-100, 100, 3), rng.uniform(-100, 100, 3)])
    stations = default_stations(spec, 4, seed=3, tools=tools)
    sim = simulate(machine, em, theta, stations, plan, tools, "paper002", seed=5, noise=False)
    m = sim.measurements
    assert len(m) == 4 * 12 * 3
    st = stations.set_index("station")
    q_all = machine.axis_to_internal(m[spec.axis_names].to_numpy())
    e_all = em.values(q_all, theta)
    tool_all = m[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
    P1_all, _, _ = machine.evaluate(q_all, tool_all, e_all, exact=False)
    worst_first_order = 0.0
    for r in range(len(m)):
        row = m.iloc[r]
        t = row[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
        err = dict(zip([s.name for s in em.errors], e_all[r]))
        P = fk(spec, q_all[r], t, err)
        Q = st.loc[row["station"], ["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        expected = np.linalg.norm(P - Q) - st.loc[row["station"], "dead_length_mm"]
        assert row["length"] == pytest.approx(expected, abs=1e-9)
        worst_first_order = max(worst_first_order,
                                abs(np.linalg.norm(P1_all[r] - Q) - np.linalg.norm(P - Q)))
    # a first-order simulator would fail the comparison above by far
    assert worst_first_order > 1e-5
    # true volumetric errors: exact actual minus nominal at the commanded poses
    v = sim.volumetric
    for r in range(0, len(v), 7):
        row = v.iloc[r]
        q = machine.axis_to_internal(row[spec.axis_names].to_numpy(float))
        t = row[["tool_x", "tool_y", "tool_z"]].to_numpy(float)
        err = dict(zip([s.name for s in em.errors], em.values(q[None, :], theta)[0]))
        d = (fk(spec, q, t, err) - fk(spec, q, t, {})) * 1e3
        np.testing.assert_allclose(row[["dx_um", "dy_um", "dz_um"]].to_numpy(float), d,
                                   atol=1e-6)


# ---------------------------------------------------------------------------------------
# (2) noise statistics against the budget


def _dist(sim: Simulation) -> np.ndarray:
    dead = sim.stations.set_index("station")["dead_length_mm"]
    return sim.measurements["length"].to_numpy() + dead.loc[sim.measurements["station"]].to_numpy()


def test_length_noise_matches_budget(mcv):
    z = []
    budget = load_budget("paper002")
    for seed in (1, 2, 3):
        clean = mcv.simulate(seed, noise=False)
        noisy = mcv.simulate(seed, noise=("length",))
        diff = noisy.measurements["length"].to_numpy() - clean.measurements["length"].to_numpy()
        z.append(diff / budget.length_sigma(_dist(clean)))
    z = np.concatenate(z)
    n = z.size
    assert n > 10_000
    assert abs(z.mean()) < 4.0 / np.sqrt(n)
    assert abs(z.std() - 1.0) < 5.0 * np.sqrt(0.5 / n) * 1.5  # kurtosis of the mixture < 3


def test_axis_repeatability_matches_budget(mcv):
    budget = load_budget("paper002")
    clean = mcv.simulate(4, noise=False)
    noisy = mcv.simulate(4, noise=("axes",))
    diff = noisy.measurements["length"].to_numpy() - clean.measurements["length"].to_numpy()
    m = clean.measurements
    # beam direction from the nominal points (3-axis, tool-branch axes along +x +y +z:
    # dP/dq is the identity)
    P = m[["X", "Y", "Z"]].to_numpy() + m[["tool_x", "tool_y", "tool_z"]].to_numpy()
    Q = mcv.stations.set_index("station").loc[m["station"], ["x_mm", "y_mm", "z_mm"]].to_numpy()
    u = (P - Q) / np.linalg.norm(P - Q, axis=1)[:, None]
    a = np.array([budget.axis_repeatability(x)[1] for x in "XYZ"])
    assert np.all(np.abs(diff) <= np.abs(u) @ a * (1 + 1e-3) + 1e-9)  # bounded (rectangular)
    # sigma uses the nominal geometry: length sources at the nominal distance
    L0 = np.linalg.norm(P - Q, axis=1)
    sig_axes = np.sqrt(m["sigma"].to_numpy() ** 2 - budget.length_sigma(L0) ** 2)
    np.testing.assert_allclose(sig_axes, np.sqrt((u ** 2) @ (a ** 2 / 3)), rtol=1e-6)
    z = diff / sig_axes
    assert abs(z.mean()) < 4.0 / np.sqrt(z.size)
    assert abs(z.std() - 1.0) < 0.05
    # and the total sigma column: combined noise / sigma has unit standard deviation
    both = mcv.simulate(4, noise=True)
    zt = (both.measurements["length"] - clean.measurements["length"]) / m["sigma"]
    assert abs(zt.std() - 1.0) < 0.06


def test_single_axis_repeatability_is_rectangular(mcv):
    from scipy import stats

    a = 5e-3  # mm half-width
    budget = Budget("x_only", (Source("rep_x", 5.0, "um", "rectangular", "axis:X"),))
    kw = dict(machine=mcv.machine, error_model=mcv.error_model, theta_true=mcv.theta_true,
              stations=mcv.stations, plan=mcv.plan, tools=mcv.tools, budget=budget, seed=9)
    clean = simulate(**kw, noise=False).measurements
    noisy = simulate(**kw, noise=("axes",)).measurements
    P = clean[["X", "Y", "Z"]].to_numpy() + clean[["tool_x", "tool_y", "tool_z"]].to_numpy()
    Q = mcv.stations.set_index("station").loc[clean["station"], ["x_mm", "y_mm", "z_mm"]]
    u = (P - Q.to_numpy()) / np.linalg.norm(P - Q.to_numpy(), axis=1)[:, None]
    sel = np.abs(u[:, 0]) > 0.5
    dqx = ((noisy["length"] - clean["length"]).to_numpy() / u[:, 0])[sel]
    assert sel.sum() > 1000
    assert np.abs(dqx).max() <= a * 1.001
    assert np.var(dqx) == pytest.approx(a ** 2 / 3, rel=0.08)
    assert stats.kstest(dqx / a, stats.uniform(loc=-1, scale=2).cdf).pvalue > 1e-3


# ---------------------------------------------------------------------------------------
# (3) determinism


def test_same_seed_same_tables_different_seed_different(mcv):
    a, b, c = mcv.simulate(11), mcv.simulate(11), mcv.simulate(12)
    pd.testing.assert_frame_equal(a.measurements, b.measurements)
    pd.testing.assert_frame_equal(a.volumetric, b.volumetric)
    assert not np.array_equal(a.measurements["length"], c.measurements["length"])
    # everything but the lengths is the same plan
    pd.testing.assert_frame_equal(a.measurements.drop(columns="length"),
                                  c.measurements.drop(columns="length"))
    # sources are separate streams: switching one off leaves the other's draws alone
    clean = mcv.simulate(11, noise=False).measurements["length"]
    d_len = mcv.simulate(11, noise=("length",)).measurements["length"] - clean
    d_ax = mcv.simulate(11, noise=("axes",)).measurements["length"] - clean
    np.testing.assert_allclose(a.measurements["length"] - clean, d_len + d_ax, atol=1e-8)


def test_layout_ids_and_times(mcv):
    sim = mcv.simulate(1)
    m = sim.measurements
    S, N, K = len(mcv.stations), len(mcv.plan), len(mcv.tools)
    assert len(m) == S * N * K
    assert list(m.columns) == ["station", "point", "X", "Y", "Z", "tool_x", "tool_y", "tool_z",
                               "length", "time", "sigma"]
    # every station sees every (pose, tool) exactly once; point ids unique per (pose, tool)
    assert (m.groupby("station")["point"].nunique() == N * K).all()
    pose_cols = ["X", "Y", "Z", "tool_x", "tool_y", "tool_z"]
    assert m.groupby("point")[pose_cols].nunique().max().max() == 1
    assert m["point"].iloc[0] == "p0001"
    assert np.all(np.diff(m["time"]) > 0) and m["time"].iloc[0] == 0.0
    assert set(sim.volumetric["point"]) == set(m["point"])
    assert (m["sigma"] > 0).all() and (m["sigma"] < 1e-3).all()


# ---------------------------------------------------------------------------------------
# (4) drawn true parameters


@pytest.mark.parametrize("model", ["mcv754_wxyzt", "head_bc"])
def test_draw_true_parameters_datum_and_scale(model):
    machine = Machine.from_model(model)
    em = ErrorModel(machine.spec)
    th = draw_true_parameters(machine, em, np.random.default_rng(0), 60.0)
    C, _ = em.constraints()
    assert np.abs(C @ th).max() <= 1e-12 * np.abs(th).max()
    grid = grid_plan(machine.spec)
    q = machine.axis_to_internal(grid.to_numpy())
    e = em.values(q, th)
    names = [s.name for s in em.errors]
    step = 1 if len(q) < 200 else 7  # the 5-axis grid: a sample, plus the volcal maximum
    vol = [np.linalg.norm(fk(machine.spec, q[r], np.zeros(3), dict(zip(names, e[r])))
                          - fk(machine.spec, q[r], np.zeros(3), {})) * 1e3
           for r in range(0, len(q), step)]
    _, dp, _ = machine.evaluate(q, np.zeros(3), e, exact=True)
    assert np.linalg.norm(dp, axis=1).max() * 1e3 == pytest.approx(60.0, rel=1e-8)
    assert max(vol) <= 60.0 * (1 + 1e-8)
    if step == 1:
        assert max(vol) == pytest.approx(60.0, rel=1e-8)
    # same generator state -> same parameters; another scale -> proportionally (nearly)
    th2 = draw_true_parameters(machine, em, np.random.default_rng(0), 30.0)
    np.testing.assert_allclose(th2, th / 2, rtol=1e-3, atol=1e-12)
    assert np.array_equal(th, draw_true_parameters(machine, em, np.random.default_rng(0), 60.0))


def test_drawn_magnitudes_are_realistic():
    machine = Machine.from_model("mcv754_wxyzt")
    em = ErrorModel(machine.spec)
    th = draw_true_parameters(machine, em, 5, None)  # unscaled
    x = np.linspace(0.0, 754.0, 50)[:, None] * np.array([[1.0, 0.0, 0.0]])
    e = em.values(x, th)
    i = {s.name: k for k, s in enumerate(em.errors)}
    exx = np.ptp(e[:, i["EXX"]]) * 1e3
    eyx = np.abs(e[:, i["EYX"]]).max() * 1e3
    eax = np.abs(e[:, i["EAX"]]).max() * 1e6
    assert 5 < exx < 150        # tens of um over travel
    assert 0.2 < eyx < 20       # a few um
    assert 2 < eax < 120        # tens of urad
    sq = abs(th[em.param_names.index("EC0Y")]) * 1e6
    assert 20 <= sq <= 50


# ---------------------------------------------------------------------------------------
# (5) the bundled example


def test_example_matches_paper000(mcv):
    st = mcv.stations
    assert list(st["station"]) == list(TABLE5)
    np.testing.assert_array_equal(st[["x_mm", "y_mm", "z_mm"]].to_numpy(),
                                  np.array(list(TABLE5.values())))
    assert ((st["dead_length_mm"] > 0) & (st["dead_length_mm"] < 1)).all()
    assert mcv.model == "mcv754_wxyzt" and mcv.budget.name == "paper002"
    assert len(mcv.tools) >= 3 and np.any(mcv.tools[:, :2] != 0)
    C, _ = mcv.error_model.constraints()
    assert np.abs(C @ mcv.theta_true).max() < 1e-15
    assert max_volumetric_error_um(mcv.machine, mcv.error_model, mcv.theta_true) == \
        pytest.approx(64.0, rel=1e-6)
    pts = nominal_points(mcv.machine.spec, mcv.plan, mcv.tools)
    d = np.linalg.norm(pts[:, None, :] - st[["x_mm", "y_mm", "z_mm"]].to_numpy()[None], axis=-1)
    assert d.min() >= 50.0
    assert len(mcv.plan) >= 140
    sim = mcv.simulate()
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        meas = load_measurements(sim.measurements, mcv.machine.spec, stations=sim.stations)
    assert meas.n == len(sim.measurements)


# ---------------------------------------------------------------------------------------
# files


def test_save_and_reload(tmp_path, mcv):
    sim = mcv.simulate(2)
    out = save_simulation(sim, tmp_path / "sim")
    assert sorted(p.name for p in out.iterdir()) == sorted([*SIMULATION_FILES, "manifest.json"])
    assert [p.name for p in tmp_path.iterdir()] == ["sim"]  # no temporary folder left
    theta = load_true_parameters(out / "true_parameters.csv", mcv.error_model)
    np.testing.assert_allclose(theta, sim.theta, rtol=1e-14, atol=1e-20)
    m = load_measurements(out / "measurements.csv", mcv.machine.spec,
                          stations=out / "stations.csv")
    np.testing.assert_array_equal(m.length, sim.measurements["length"].to_numpy())
    st = load_stations(out / "stations.csv")
    np.testing.assert_array_equal(st["dead_length_mm"], sim.stations["dead_length_mm"])
    assert json.loads((out / "simulation.json").read_text())["seed"] == 2
    # a previous output is replaced; a folder with other files is refused
    save_simulation(mcv.simulate(3), out)
    assert json.loads((out / "simulation.json").read_text())["seed"] == 3
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="other files"):
        save_simulation(sim, tmp_path / "other")
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_load_true_parameters_errors(tmp_path, mcv):
    p = tmp_path / "p.csv"
    p.write_text("name,value,unit\nEXX_1,10,um\nEC0Y,20,urad\n")
    th = load_true_parameters(p, mcv.error_model)
    assert th[mcv.error_model.param_names.index("EXX_1")] == pytest.approx(0.01)
    assert th[mcv.error_model.param_names.index("EC0Y")] == pytest.approx(20e-6)
    assert np.count_nonzero(th) == 2
    p.write_text("name,value,unit\nEXX_1,10,um\nEXX_9,1,um\n")
    with pytest.raises(InputError, match=r"row 3.*unknown parameter 'EXX_9'"):
        load_true_parameters(p, mcv.error_model)
    p.write_text("name,value,unit\nEXX_1,10,urad\n")
    with pytest.raises(InputError, match="translational"):
        load_true_parameters(p, mcv.error_model)


# ---------------------------------------------------------------------------------------
# plans and stations


def test_plans_shapes():
    g = grid_plan("mcv754_wxyzt", {"X": 6, "Y": 5, "Z": 5})
    assert g.shape == (150, 3) and list(g.columns) == ["X", "Y", "Z"]
    assert g["X"].min() == 0 and g["X"].max() == 754 and g["Z"].min() == -550
    g5 = grid_plan("head_bc")
    assert sorted(g5["C"].unique()) == [-180, -90, 0, 90] and sorted(g5["B"].unique()) == \
        [-100, 0, 100]
    assert len(g5) == 125 * 12
    assert grid_plan("mcv754_wxyzt", 3, margin=10)["X"].max() == 744
    lines = line_plan("trunnion_ac", n=5)
    # C (full turn) every 72 deg from 0, A -120..30 (no 0), X, Y, Z through 0: the
    # reference pose once
    assert len(lines) == 5 * 5 - 3
    assert (lines == 0).all(axis=1).sum() == 1
    assert sorted(lines.loc[lines["C"] != 0, "C"]) == [-144, -72, 72, 144]
    d = diagonal_plan("mcv754_wxyzt", n=11)
    assert len(d) == 4 * 11 - 3  # the centre once
    corners = {tuple(r) for r in d.to_numpy() if r[0] in (0, 754)}
    assert len(corners) == 8
    assert (diagonal_plan("head_bc")[["C", "B"]] == 0).all().all()


def test_plan_from_csv_validation(tmp_path):
    p = tmp_path / "plan.csv"
    p.write_text("X,Y,Z\n0,0,0\n100,50,-20\n")
    assert plan_from_csv(p, "mcv754_wxyzt").shape == (2, 3)
    p.write_text("X_mm,Y,Z\n0,0,0\n100,abc,-20\n")
    with pytest.raises(InputError, match=r"plan\.csv, row 3, column 'Y'"):
        plan_from_csv(p, "mcv754_wxyzt")
    p.write_text("X,Y,Z\n0,0,0\n900,0,-20\n")
    with pytest.raises(InputError, match=r"row 3, column 'X'.*outside the travel"):
        plan_from_csv(p, "mcv754_wxyzt")
    p.write_text("X,Y,W\n0,0,0\n")
    with pytest.raises(InputError, match="row 1"):
        plan_from_csv(p, "mcv754_wxyzt")
    with pytest.raises(InputError, match="outside the travel"):
        check_plan(pd.DataFrame({"X": [0.0], "Y": [0.0], "Z": [10.0]}), "mcv754_wxyzt")


@pytest.mark.parametrize("model", sorted(bundled_models()))
def test_default_stations(model):
    st = default_stations(model, 6, seed=1)
    load_stations(st)
    xyz = st[["x_mm", "y_mm", "z_mm"]].to_numpy()
    sv = np.linalg.svd(xyz - xyz.mean(0), compute_uv=False)
    assert sv[2] > 0.01 * sv[0]  # not coplanar
    pts = nominal_points(model, grid_plan(model))
    assert np.linalg.norm(pts[:, None] - xyz[None], axis=-1).min() >= 50.0
    pd.testing.assert_frame_equal(st, default_stations(model, 6, seed=1))
    assert not st.equals(default_stations(model, 6, seed=2))


# ---------------------------------------------------------------------------------------
# (6) the command line


@pytest.fixture
def only_simulate(monkeypatch):
    # the CLI imports every registered command; test this one alone
    monkeypatch.setattr(cli, "_COMMANDS", ["volcal.cli.commands.simulate"])


def test_cli_example(tmp_path, only_simulate, capsys):
    out = tmp_path / "sim"
    assert cli.main(["simulate", "--example", "mcv754", "--seed", "5", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted([*SIMULATION_FILES, "manifest.json"])
    assert "wrote" in capsys.readouterr().out
    ex = example("mcv754")
    m = pd.read_csv(out / "measurements.csv", dtype={"station": str, "point": str})
    pd.testing.assert_frame_equal(m, ex.simulate(5).measurements.astype({"station": str,
                                                                         "point": str}),
                                  check_dtype=False, rtol=0, atol=0)


def test_cli_model_path(tmp_path, only_simulate):
    out = tmp_path / "x"
    rc = cli.main(["simulate", "--model", "xfyz", "--plan", "diagonals", "--grid", "5",
                   "--tools", "0,0,0;0,0,-100;50,0,-100", "--max-volumetric-um", "40",
                   "--no-noise", "--seed", "1", "--out", str(out)])
    assert rc == 0
    m = load_measurements(out / "measurements.csv", "xfyz", stations=out / "stations.csv")
    assert m.n == 6 * (4 * 5 - 3) * 3
    machine = Machine.from_model("xfyz")
    em = ErrorModel(machine.spec)
    theta = load_true_parameters(out / "true_parameters.csv", em)
    assert max_volumetric_error_um(machine, em, theta) == pytest.approx(40.0, rel=1e-9)
    assert pd.read_csv(out / "true_volumetric.csv").shape == ((4 * 5 - 3) * 3, 10)


def test_cli_bad_tools(tmp_path, only_simulate, capsys):
    rc = cli.main(["simulate", "--example", "mcv754", "--tools", "0,0,0;0,0", "--seed", "1",
                   "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--tools" in err and "tool offset #2" in err and "three numbers" in err
    assert not (tmp_path / "o").exists()
    assert cli.main(["simulate", "--model", "xfyz", "--tools", "a,b,c", "--seed", "1",
                     "--out", str(tmp_path / "o")]) == 2
    assert cli.main(["simulate", "--model", "xfyz", "--plan", "nope.csv", "--seed", "1",
                     "--out", str(tmp_path / "o")]) == 2
    assert "nope.csv" in capsys.readouterr().err


def test_parse_tools():
    np.testing.assert_array_equal(parse_tools("0,0,0; 1.5,-2,3"), [[0, 0, 0], [1.5, -2, 3]])
    for bad in ("", "0,0,0;", "1,2,3,4", "1,2,nan", "0,0,0;0,0,0"):
        with pytest.raises(InputError):
            parse_tools(bad)


def test_drift_and_noise_switches(mcv):
    from volcal.measurement.budget import PAPER001_DRIFT

    b = load_budget("paper002").with_drift(PAPER001_DRIFT)
    kw = dict(machine=mcv.machine, error_model=mcv.error_model, theta_true=mcv.theta_true,
              stations=mcv.stations, plan=mcv.plan, tools=mcv.tools, budget=b, seed=3)
    on = simulate(**kw, drift=True).measurements
    off = simulate(**kw, drift=False).measurements
    d = (on["length"] - off["length"]).to_numpy()
    assert d.std() == pytest.approx(PAPER001_DRIFT.sigma_mm, rel=0.2)
    pd.testing.assert_frame_equal(on, simulate(**kw, drift=True).measurements)
    with pytest.raises(InputError, match="noise source"):
        simulate(**kw, noise=("lenght",))
    with pytest.raises(InputError, match="parameters"):
        simulate(**{**kw, "theta_true": mcv.theta_true[:-1]})
    with pytest.raises(InputError, match="not be positive"):
        st = mcv.stations.copy()
        st.loc[0, ["x_mm", "y_mm", "z_mm"]] = [0.0, 0.0, -550.0]  # on a measured point
        simulate(**{**kw, "stations": st})


def test_sigma_projects_repeatability_on_the_beam_five_axis():
    # sigma's axis part uses d(distance)/dq of the nominal model: check it against central
    # differences of the independent kinematics on a 5-axis model with a rotary source
    from volcal.measurement.simulate import _position_jacobian

    machine = Machine.from_model("head_bc")
    spec = machine.spec
    rng = np.random.default_rng(8)
    plan = _random_plan(spec, 6, rng)
    q = machine.axis_to_internal(plan.to_numpy())
    t = rng.uniform(-100, 100, (6, 3))
    J = _position_jacobian(machine, q, t)
    for r in range(6):
        for j in range(machine.n_axes):
            h = np.zeros(machine.n_axes)
            h[j] = 1e-6
            fd = (fk(spec, q[r] + h, t[r], {}) - fk(spec, q[r] - h, t[r], {})) / 2e-6
            np.testing.assert_allclose(J[r, :, j], fd, atol=1e-5)
    budget = Budget("rot", (Source("rep_b", 10.0, "urad", "normal", "axis:B", k=2.0),))
    stations = default_stations(spec, 4, seed=1, tools=t)
    for k in range(len(t)):
        sim = simulate(machine, None, np.zeros(ErrorModel(spec).n_params), stations, plan,
                       t[k:k + 1], budget, 1, noise=False)
        m = sim.measurements
        Q = stations.set_index("station").loc[m["station"], ["x_mm", "y_mm", "z_mm"]].to_numpy()
        P = np.array([fk(spec, qq, t[k], {}) for qq in q])[np.tile(np.arange(6), 4)]
        u = (P - Q) / np.linalg.norm(P - Q, axis=1)[:, None]
        jb = spec.axis_names.index("B")
        Jk = _position_jacobian(machine, q, np.tile(t[k], (6, 1)))
        g = np.einsum("ri,ri->r", u, Jk[np.tile(np.arange(6), 4), :, jb])
        np.testing.assert_allclose(m["sigma"], np.abs(g) * 5e-6, rtol=1e-9, atol=1e-15)
