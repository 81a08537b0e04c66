"""A result carries the solver state downstream steps need (unknowns, held set, weights,
datum in force, fingerprint of the problem): saved with the folder (format 3), read back,
and used by Monte Carlo instead of reconstructing the held set and the weights."""
from __future__ import annotations

import numpy as np

from test_identify import simulated
from volcal.analysis.identify import Identifier, identify
from volcal.analysis.uncertainty.montecarlo import fixed_mask, identification_data
from volcal.measurement.tables import load_measurements
from volcal.outputs.results import RESULT_FORMAT_VERSION, load_result, save_result
from volcal.problem.residuals import Layout


def test_state_round_trips_and_is_used(tmp_path):
    machine, em, _, sim = simulated("mcv754_wxyzt", grid=3)
    res = identify(machine, sim.measurements, error_model=em, strategy="two-phase")
    st = res.state
    assert st is not None and st.solver == "ipopt" and st.instrument == "tracker"
    out = save_result(res, tmp_path / "r", plots=False)
    assert (out / "solver_state.npz").exists() and RESULT_FORMAT_VERSION >= 3
    loaded = load_result(out)
    assert loaded.state is not None
    np.testing.assert_array_equal(loaded.state.x, st.x)
    np.testing.assert_array_equal(loaded.state.fixed, st.fixed)
    np.testing.assert_array_equal(loaded.state.weights, st.weights)
    assert loaded.state.names == st.names and loaded.state.fingerprint == st.fingerprint
    # a rebuilt problem of the same data has the same fingerprint; the held set and the
    # weights come from the state, not from a reconstruction
    meas = load_measurements(sim.measurements, machine.spec)
    ider = Identifier(machine, em, Layout.from_measurements(meas))
    assert loaded.state.matches(ider.problem)
    np.testing.assert_array_equal(fixed_mask(ider, loaded), st.fixed)
    np.testing.assert_array_equal(ider.problem.datum_active, st.datum_active)
    x, w = identification_data(loaded, meas)
    np.testing.assert_array_equal(x, st.x)
    np.testing.assert_array_equal(w, st.weights)
    # another layout (fewer readings) does not match
    sub = sim.measurements.iloc[: len(sim.measurements) // 2]
    meas2 = load_measurements(sub, machine.spec)
    other = Identifier(machine, em, Layout.from_measurements(meas2)).problem
    assert not loaded.state.matches(other)
