"""The identified error field against a truth volcal did not generate.

The data come from tests/indep_sim.py: a separate rigid-body simulator (numpy, exact
homogeneous transforms, no volcal model code), error motions from other families than
volcal's bases, not satisfying any datum, several tool offsets, paper 002's noise.
``identify`` runs with its default options (plus approximate station positions); its
volumetric field is compared with the truth on a grid over the workspace (rotary poses
included) at the measured tool offsets, after removing only the rigid motion no
multilateration sees.  The reference figure is a plain least-squares fit of the same
data with volcal's parameterisation and no datum (``indep_sim.reference_fit``).

Targets: field error <= max(0.5 um, 1.1 x reference) RMS everywhere; <= 0.3 um where the
truth is representable (with chi2/dof near 1); periodic rotary errors (harmonics 1-3)
within 0.5 um RMS.

The first tests check that the two programs mean the same thing: nominal points equal,
and volcal's first-order tool point equal to the exact one to second order.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pytest

import indep_sim as ind
from volcal.analysis.identify import identify
from volcal.model.errors import ErrorModel
from volcal.model.machine import Machine

TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0], [0.0, 80.0, 60.0]])
MODELS = ["mcv754_wxyzt", "trunnion_ac"]


# --------------------------------------------------------------------------------------
# conventions: the independent simulator and volcal's model agree


def _random_poses(geom, n, rng):
    qf = np.column_stack([rng.uniform(*a.travel, n) for a in geom.axes])
    return geom.to_internal(qf), rng.uniform(-100.0, 100.0, (n, 3))


def _error_values(machine, geom, truth, q):
    """volcal's error vector e (N, n_errors) at poses q from an independent truth."""
    cols = []
    names = geom.axis_names
    for nm in machine.error_names:
        if nm in truth.constants:
            cols.append(np.full(len(q), truth.constants[nm]))
        else:
            axis = nm[2:]
            cols.append(truth.motion(nm, q[:, names.index(axis)]) if axis in names
                        else np.zeros(len(q)))
    return np.column_stack(cols)


@pytest.mark.parametrize("model", MODELS)
def test_nominal_tool_points_agree(model):
    machine, geom = Machine.from_model(model), ind.load_geometry(model)
    q, t = _random_poses(geom, 200, np.random.default_rng(0))
    p_volcal, _, _ = machine.evaluate(q, t, np.zeros(machine.n_errors))
    assert np.abs(p_volcal - ind.tool_points(geom, q, t)).max() < 1e-9


@pytest.mark.parametrize("model", MODELS)
def test_each_error_has_the_same_meaning(model):
    """One error at a time, constant: volcal's first-order effect equals the exact one of
    the independent simulator (to second order in a 1 um / 1 urad error)."""
    machine, geom = Machine.from_model(model), ind.load_geometry(model)
    q, t = _random_poses(geom, 100, np.random.default_rng(1))
    p0 = ind.tool_points(geom, q, t)
    bad = []
    for k, nm in enumerate(machine.error_names):
        val = 1e-3 if nm[1] in "XYZ" else 1e-6
        tr = ind.Truth()
        if nm[2] == "0":  # location / squareness / tool: constants
            tr.constants[nm] = val
        else:
            tr.motions[nm] = lambda x, v=val: np.full(np.shape(x), v)
        mine = ind.tool_points(geom, q, t, tr) - p0
        e = np.zeros(machine.n_errors)
        e[k] = val
        _, dp, _ = machine.evaluate(q, t, e)
        scale = max(np.abs(mine).max(), 1e-12)
        if np.abs(mine - dp).max() > 1e-5 * scale + 1e-12:
            bad.append(f"{nm}: volcal {dp[0]} vs independent {mine[0]}")
    assert not bad, "conventions disagree:\n" + "\n".join(bad)


@pytest.mark.parametrize("model", MODELS)
def test_first_order_model_agrees_to_second_order(model):
    """All errors at once, constant plus linear in the axis position (a representable
    truth): volcal's first-order volumetric error differs from the exact one at second
    order only (halving the errors divides the difference by 4)."""
    machine, geom = Machine.from_model(model), ind.load_geometry(model)
    rng = np.random.default_rng(2)
    q, t = _random_poses(geom, 300, rng)
    truth = ind.Truth()
    for a in geom.axes:
        for c in ind.TRANS + ind.ROTS:
            amp = 20e-3 if c in ind.TRANS else 60e-6
            truth.motions[f"E{c}{a.name}"] = ind.poly_motion(a, rng.uniform(-amp, amp, 2))
    for nm in machine.error_names:
        if nm[2] == "0":
            truth.constants[nm] = (rng.uniform(-20e-3, 20e-3) if nm[1] in "XYZ"
                                   else rng.uniform(-60e-6, 60e-6))
    diffs = []
    for s in (1.0, 0.5):
        tr = truth.scaled(s)
        exact = ind.true_error_um(geom, tr, q, t)
        _, dp, _ = machine.evaluate(q, t, _error_values(machine, geom, tr, q))
        diffs.append(np.abs(dp * 1e3 - exact).max())
        if s == 1.0:
            size = np.abs(exact).max()
    assert size > 20.0
    assert diffs[0] < 1e-3 * size, (diffs, size)
    assert 3.5 < diffs[0] / diffs[1] < 4.5, diffs


# --------------------------------------------------------------------------------------
# identification on independent data


@dataclass(frozen=True)
class Case:
    model: str
    family: str
    n_tools: int
    seed: int
    full_turn: str | None = None
    rotary_scale: float = 1.0
    c_angles: int = 8  # measured angles of a full-turn axis


CASES = {
    "3ax-1tool": Case("mcv754_wxyzt", "representable", 1, 11),
    "3ax-4tools": Case("mcv754_wxyzt", "representable", 4, 12),
    "3ax-nonrep": Case("mcv754_wxyzt", "nonrep", 4, 13),
    "5ax-tools": Case("trunnion_ac", "representable", 4, 14),
    "5ax-1tool": Case("trunnion_ac", "representable", 1, 16),
    "5ax-periodic": Case("trunnion_ac", "representable", 3, 15, full_turn="fourier",
                         rotary_scale=1.5, c_angles=10),
}


def _plan(geom, case):
    if len(geom.axes) == 3:
        return np.vstack([ind.grid(geom, {"X": 4, "Y": 4, "Z": 4}), ind.diagonals(geom, 6)])
    # 5-axis trunnion: a linear grid at A = C = 0, and at every (A, C) of a rotary grid a
    # tetrahedron of linear positions
    lin = ind.grid(geom, {"X": 4, "Y": 4, "Z": 4}, {"A": 0.0, "C": 0.0})
    tet = np.array([[-150, -125, -100], [150, -125, -350], [-150, 125, -350],
                    [150, 125, -100]], float)
    rot = [[c, a, *p] for a in ind.linspace_travel(geom.axis("A"), 4)
           for c in ind.linspace_travel(geom.axis("C"), case.c_angles) for p in tet]
    return np.vstack([lin, np.array(rot)])


def _field_grid(geom, tools):
    """Poses over the workspace (rotary angles between the measured ones too), each with
    every measured tool offset: internal q (N, n_axes) and tools (N, 3)."""
    if len(geom.axes) == 3:
        q = ind.grid(geom, {"X": 5, "Y": 5, "Z": 5})
    else:
        q = ind.grid(geom, {"C": 24, "A": 6, "X": 3, "Y": 3, "Z": 2})
    q = geom.to_internal(q)
    return np.repeat(q, len(tools), axis=0), np.tile(tools, (len(q), 1))


@functools.cache
def _simulation(name):
    case = CASES[name]
    geom = ind.load_geometry(case.model)
    rng = np.random.default_rng(case.seed)
    truth = ind.draw_truth(geom, rng, case.family, full_turn=case.full_turn,
                           rotary_scale=case.rotary_scale)
    tools = TOOLS[:case.n_tools]
    sim = ind.simulate(geom, truth, _plan(geom, case), tools, rng)
    return geom, truth, tools, sim


@functools.cache
def _run(name):
    case = CASES[name]
    geom, truth, tools, sim = _simulation(name)
    Q, T = _field_grid(geom, tools)
    true_um = ind.true_error_um(geom, truth, Q, T)
    nominal = ind.tool_points(geom, Q, T)

    res = identify(case.model, sim.measurements, sim.stations_start)
    pred = res.predict(Q, T, with_uncertainty=False)[["dx_um", "dy_um", "dz_um"]].to_numpy()
    field, field_max = ind.field_error_modulo_gauge(pred, true_um, nominal, return_max=True)

    machine = Machine.from_model(case.model)
    em = ErrorModel(machine.spec)
    ref = ind.reference_fit(machine, em, sim.measurements, sim.stations_start, sim.sigma_mm)
    ref_field = ind.field_error_modulo_gauge(
        ind.reference_field_um(machine, em, ref.theta, Q, T), true_um, nominal)
    out = {
        "case": name, "readings": len(sim.measurements), "truth_max_um": np.abs(true_um).max(),
        "field_um": field, "field_max_um": field_max, "chi2": res.conditions["chi2_per_dof"],
        "residual_um": res.residual_rms_um, "status": res.status, "success": res.success,
        "unidentifiable": int((~res.identifiable).sum()),
        "adequate": res.adequacy.adequate, "adequacy": res.adequacy.message,
        "ref_field_um": ref_field, "ref_chi2": ref.chi2_per_dof,
        "ref_residual_um": ref.residual_rms_um,
    }
    print("\n" + _describe(out))
    return out


def _describe(f):
    return (f"{f['case']}: {f['readings']} readings, true field up to {f['truth_max_um']:.1f} um;"
            f" identify: field error {f['field_um']:.3f} um RMS (max {f['field_max_um']:.2f}),"
            f" chi2/dof {f['chi2']:.2f}, residual {f['residual_um']:.3f} um RMS, "
            f"{f['unidentifiable']} unidentifiable, {f['status']}; plain lsq reference: field "
            f"{f['ref_field_um']:.3f} um, chi2/dof {f['ref_chi2']:.2f}, residual "
            f"{f['ref_residual_um']:.3f} um")


def _check(name, *, limit=None, chi2=False):
    f = _run(name)
    msg = _describe(f)
    assert f["success"], msg
    assert f["truth_max_um"] > 20.0, msg  # a realistic field, not a trivial one
    assert f["field_um"] <= max(0.5, 1.1 * f["ref_field_um"]), msg
    if limit is not None:
        assert f["field_um"] <= limit, msg
    if chi2:
        assert f["adequate"], f["adequacy"]
        # the reference fit shows what the data and the noise give: chi2/dof ~ 1
        assert 0.8 < f["ref_chi2"] < 1.25, msg
        assert 0.8 < f["chi2"] < 1.25, msg
    return f


def test_three_axis_one_tool_offset():
    _check("3ax-1tool", limit=0.3, chi2=True)


def test_three_axis_four_tool_offsets():
    _check("3ax-4tools", limit=0.3, chi2=True)


def test_three_axis_non_representable_truth():
    # sines with non-integer periods, steps and tables: no polynomial basis fits them, so
    # the target is the plain least-squares fit of the same parameterisation; and the
    # fit says that it does not fit
    f = _check("3ax-nonrep")
    assert not f["adequate"], f["adequacy"]


def test_five_axis_several_tool_offsets():
    _check("5ax-tools", limit=0.3, chi2=True)


def test_five_axis_one_tool_offset():
    # the reflector at the spindle reference point only: the spindle's orientation and the
    # tool-side angles it mixes with are not seen, and the field at that offset is right
    _check("5ax-1tool", limit=0.3, chi2=True)


def test_five_axis_periodic_rotary_errors():
    # the full-turn C axis with error motions of harmonics 1-3 of the angle (1.5 times the
    # usual size), measured at 10 angles, compared every 15 degrees
    _check("5ax-periodic", limit=0.5, chi2=True)


def test_reference_fit_does_not_depend_on_the_solver():
    """The reference figure is a property of the data and the parameterisation: scipy's
    trust-region fit and a minimum-norm Gauss-Newton iteration give the same field."""
    geom, truth, tools, sim = _simulation("3ax-4tools")
    machine = Machine.from_model("mcv754_wxyzt")
    em = ErrorModel(machine.spec)
    Q, T = _field_grid(geom, tools)
    fields = []
    for method in ("scipy", "gauss-newton"):
        ref = ind.reference_fit(machine, em, sim.measurements, sim.stations_start,
                                sim.sigma_mm, method=method)
        fields.append(ind.reference_field_um(machine, em, ref.theta, Q, T))
    assert ind.field_error_modulo_gauge(fields[0], fields[1], ind.tool_points(geom, Q, T)) < 1e-3
