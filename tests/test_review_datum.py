"""Review checks of the minimal datum, the gauge / unidentifiable split and ``determined``.

The data come from tests/indep_sim.py (exact rigid-body simulation, several tool offsets).
"""
from __future__ import annotations

import functools

import numpy as np

import indep_sim as ind
from volcal.analysis.identify import identify

MODEL = "mcv754_wxyzt"
TOOLS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 100.0], [80.0, 0.0, 60.0]])


@functools.cache
def _sim():
    geom = ind.load_geometry(MODEL)
    rng = np.random.default_rng(5)
    truth = ind.draw_truth(geom, rng, "representable")
    plan = np.vstack([ind.grid(geom, {n: 4 for n in "XYZ"}), ind.diagonals(geom, 6)])
    return geom, ind.simulate(geom, truth, plan, TOOLS, rng)


def _grid(geom):
    q = geom.to_internal(ind.grid(geom, {n: 3 for n in "XYZ"}))
    return np.repeat(q, len(TOOLS), axis=0), np.tile(TOOLS, (len(q), 1))


def test_exact_model_keeps_measured_poses_determined():
    """A 3-axis machine measured with three tool offsets over its whole travel: every
    pose at a measured tool offset is determined, with the first-order model (it is) and
    with the exact model too (the two fields agree to far below a nanometre; the exact
    model must not turn gauge freedoms into 'unidentifiable' ones)."""
    geom, sim = _sim()
    Q, T = _grid(geom)
    first = identify(MODEL, sim.measurements, sim.stations_start)
    exact = identify(MODEL, sim.measurements, sim.stations_start, exact=True)
    p1, p2 = first.predict(Q, T), exact.predict(Q, T)
    assert p1["determined"].all()
    cols = ["dx_um", "dy_um", "dz_um"]
    nominal = ind.tool_points(geom, Q, T)
    assert ind.field_error_modulo_gauge(p2[cols].to_numpy(), p1[cols].to_numpy(),
                                        nominal) < 0.01
    assert exact.null_space.n_unidentifiable == 0
    assert p2["determined"].all(), f"{(~p2['determined']).mean():.0%} of poses flagged"
    assert np.isfinite(p2[["u_dx_um", "u_dy_um", "u_dz_um"]].to_numpy()).all()


def _scaled_model(tmp_path, s):
    text = (ind.MODELS_DIR / f"{MODEL}.toml").read_text()
    import re
    text = re.sub(r"travel = \[([-\d.]+), ([-\d.]+)\]",
                  lambda m: f"travel = [{float(m.group(1)) * s}, {float(m.group(2)) * s}]", text)
    path = tmp_path / "small.toml"
    path.write_text(text.replace(f'name = "{MODEL}"', 'name = "small"'))
    return path


def test_small_travel_without_datum_reports_no_unidentifiable_combination(tmp_path):
    """A machine of about 50 mm travel measured with three tool offsets, ``datum="none"``:
    the field null space has no unidentifiable direction (every pose is determined), so
    no held combination may be labelled unidentifiable either."""
    s = 0.07
    path = _scaled_model(tmp_path, s)
    geom = ind.load_geometry(path)
    rng = np.random.default_rng(5)
    truth = ind.draw_truth(geom, rng, "representable")
    plan = np.vstack([ind.grid(geom, {n: 4 for n in "XYZ"}), ind.diagonals(geom, 6)])
    sim = ind.simulate(geom, truth, plan, TOOLS * s, rng, start_jitter_mm=2.0 * s)
    res = identify(path, sim.measurements, sim.stations_start, datum="none")
    assert res.null_space.n_unidentifiable == 0
    kinds = res.identifiability.kinds
    bad = [c for c, k in zip(res.identifiability.combinations, kinds) if k != "gauge"]
    assert not bad, f"{len(bad)} of {len(kinds)} held combinations labelled unidentifiable"


def test_measured_poses_stay_determined_when_an_axis_has_few_positions():
    """X measured at its two ends only: the higher orders of the X error motions are
    unidentifiable between them, but at the measured poses themselves the error follows
    from the readings (every datum gives the same field there modulo a rigid motion, and
    it matches the truth), so ``determined`` must be True there."""
    geom = ind.load_geometry(MODEL)
    tools = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -100.0]])
    rng = np.random.default_rng(7)
    truth = ind.draw_truth(geom, rng, "representable")
    plan = ind.grid(geom, {"X": 2, "Y": 4, "Z": 4})
    sim = ind.simulate(geom, truth, plan, tools, rng)
    res = identify(MODEL, sim.measurements, sim.stations_start)
    assert res.null_space.n_unidentifiable > 0
    q = geom.to_internal(plan)
    Q, T = np.repeat(q, len(tools), axis=0), np.tile(tools, (len(q), 1))
    pred = res.predict(Q, T)
    field = ind.field_error_modulo_gauge(pred[["dx_um", "dy_um", "dz_um"]].to_numpy(),
                                         ind.true_error_um(geom, truth, Q, T),
                                         ind.tool_points(geom, Q, T))
    assert field < 0.5
    assert pred["determined"].all(), f"{(~pred['determined']).mean():.0%} of measured poses flagged"
