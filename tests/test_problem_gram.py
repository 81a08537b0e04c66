"""Invariant: the Gauss-Newton Hessian and the gradient the solvers are given are J^T J and
J^T r of the residual Function, whatever the order of the readings and however many
stations see each pose.

``IdentificationProblem`` assembles J^T J pose by pose from the structure of J (the readings'
d(r)/d(point) grouped by pose, the poses' d(point)/d(theta)) instead of by AD; the reference
here is the central differences of ``problem.residual``, which does not use that structure.
The readings are shuffled and a third of them dropped so that poses have uneven numbers of
readings and are not contiguous: the cases where a pose-wise assembly can mix poses up.
"""

from __future__ import annotations

import numpy as np
import pytest

from test_identify import simulated
from volcal.measurement.tables import load_measurements
from volcal.problem.residuals import IdentificationProblem, Layout


@pytest.mark.parametrize("poses", [True, False])
def test_gram_and_gradient_are_those_of_the_residual(poses):
    from volcal.measurement.instruments import get_instrument

    machine, em, _, sim = simulated("xfyz", grid=2)
    rng = np.random.default_rng(5)
    df = sim.measurements
    keep = rng.permutation(len(df))[: (2 * len(df)) // 3]
    meas = load_measurements(df.iloc[keep].reset_index(drop=True), machine.spec)
    lay = Layout.from_measurements(meas)
    if not poses:  # every reading its own pose
        lay = Layout(lay.station_index, lay.n_stations, lay.station_ids)
    counts = np.bincount(lay.poses[0])
    assert not poses or counts.min() < counts.max()  # uneven readings per pose
    pr = IdentificationProblem(machine, em, get_instrument("tracker"), lay)
    xs = rng.normal(size=pr.n_x)
    n_ps = pr.instrument.n_station_params
    for k in range(lay.n_stations):  # stations about 1.5 m away (scaled units of 1 um)
        xs[pr.n_theta + n_ps * k : pr.n_theta + n_ps * k + 3] += 1.5e6 * rng.uniform(-1, 1, 3)
    w = rng.uniform(0.5, 2.0, len(meas))  # uneven weights: w enters J^T J squared
    p = pr.pack_data(meas.q_internal, meas.tool, meas.length, w)

    r = np.asarray(pr.residual(xs, p)).ravel()
    J = np.empty((len(r), pr.n_x))
    for j in range(pr.n_x):
        h = np.zeros(pr.n_x)
        h[j] = 1e-3
        up, down = pr.residual(xs + h, p), pr.residual(xs - h, p)
        J[:, j] = (np.asarray(up) - np.asarray(down)).ravel() / 2e-3
    H_ref, g_ref = J.T @ J, J.T @ r

    r_g, g, H = (np.asarray(v.full()) for v in pr.gram(xs, p))
    assert np.allclose(r_g.ravel(), r, rtol=0, atol=1e-12 * np.abs(r).max())
    assert np.max(np.abs(H - H_ref)) <= 1e-6 * np.abs(H_ref).max()
    assert np.max(np.abs(g.ravel() - g_ref)) <= 1e-6 * np.abs(g_ref).max()
    f, g_f = (np.asarray(v.full()) for v in pr.grad_f(xs, p))
    assert np.isclose(f.item(), 0.5 * r @ r, rtol=1e-12)
    assert np.array_equal(g_f, g)
    n_g = pr.hess_lag.size1_in(3)
    H_l = np.asarray(pr.hess_lag(xs, p, 1.0, np.zeros(n_g)).full())
    assert np.array_equal(H_l, np.triu(H))
